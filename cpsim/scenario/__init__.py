"""Scenarios: the data model, procedural families, WOMD JSON loading and splits.

* :class:`Scenario` / :class:`ScenarioError`: the validated NumPy data model.
* ``generate(family, seed)``, ``FAMILIES``, ``pool(n, seed, families=None)``: built-in
  procedural scenarios (``cpsim.scenario.procedural``).
* ``load(path)``, ``load_dir(path)``, ``convert_dir(src, dst)``, ``scenario_files(folder)``:
  WOMD JSON (``.json`` or gzip-compressed ``.json.gz``) and the ``.npz`` cache
  (``cpsim.scenario.womd``).
* ``interactivity_score``, ``interactive_split``, ``random_split``, ``track_tasks``:
  BehaviorBench splits, of a list of tasks or of a WOMD folder (one task per
  ``tracks_to_predict`` vehicle) (``cpsim.scenario.splits``).
"""

from __future__ import annotations

from cpsim._lazy import lazy_exports
from cpsim.scenario.datatypes import DT, MIN_GOAL_DISTANCE, NUM_STEPS, AgentType, RoadType, Scenario, ScenarioError

_LAZY = {
    "generate": "cpsim.scenario.procedural",
    "pool": "cpsim.scenario.procedural",
    "FAMILIES": "cpsim.scenario.procedural",
    "train_pool": "cpsim.scenario.procedural",
    "eval_pool": "cpsim.scenario.procedural",
    "ego_log_reaches_goal": "cpsim.scenario.procedural",
    "load": "cpsim.scenario.womd",
    "load_dir": "cpsim.scenario.womd",
    "convert_dir": "cpsim.scenario.womd",
    "LoadReport": "cpsim.scenario.womd",
    "scenario_files": "cpsim.scenario.womd",
    "interactivity_score": "cpsim.scenario.splits",
    "interactive_split": "cpsim.scenario.splits",
    "random_split": "cpsim.scenario.splits",
    "track_tasks": "cpsim.scenario.splits",
    "interactivity_terms": "cpsim.scenario.splits",
    "interactivity_report": "cpsim.scenario.splits",
    "load_json": "cpsim.scenario.womd",
    "load_cache": "cpsim.scenario.womd",
    "save_cache": "cpsim.scenario.womd",
}

__getattr__, __dir__ = lazy_exports("cpsim.scenario", _LAZY, globals())

__all__ = ["DT", "MIN_GOAL_DISTANCE", "NUM_STEPS", "AgentType", "RoadType", "Scenario",
           "ScenarioError", *_LAZY]
