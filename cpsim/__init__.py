"""cpsim: a batched driving simulator written as NVIDIA Warp kernels.

Public names are loaded lazily so that ``import cpsim`` stays fast (no Warp
compilation, no torch import) and registers the Gymnasium environments.
"""

from __future__ import annotations

from cpsim._lazy import lazy_exports
from cpsim.conditions import (
    CONDITION_FIELDS,
    NUM_CONDITION_FIELDS,
    PANEL,
    PROFILES,
    normalize_condition,
    profile,
    sample_conditions,
)
from cpsim.scenario.datatypes import AgentType, RoadType, Scenario, ScenarioError

__version__ = "0.1.0"

# name -> module that defines it (imported on first access)
_LAZY = {
    "SimConfig": "cpsim.config",
    "Simulator": "cpsim.simulator",
    "Snapshot": "cpsim.simulator",
    "ObsLayout": "cpsim.observation",
    "Controller": "cpsim.config",
    "Outcome": "cpsim.config",
    "SelfPlayVecEnv": "cpsim.envs.selfplay",
    "DriveEnv": "cpsim.envs.drive",
    "render": "cpsim.render",
    "scenario": "cpsim.scenario",
}

__getattr__, __dir__ = lazy_exports("cpsim", _LAZY, globals())


def _register_envs() -> None:
    import gymnasium

    if "cpsim/Drive-v0" not in gymnasium.registry:
        gymnasium.register(
            id="cpsim/Drive-v0",
            entry_point="cpsim.envs.drive:DriveEnv",
            vector_entry_point="cpsim.envs.drive:DriveVectorEnv",
            max_episode_steps=91,  # the fixed horizon (SimConfig.episode_steps, cpsim.envs.drive.HORIZON)
        )
    # `python -m rl_zoo3.train --gym-packages cpsim`: default hyperparameters for cpsim/ ids
    import sys

    if "rl_zoo3.exp_manager" in sys.modules:
        from cpsim.envs.zoo_support import install_if_zoo_loaded

        install_if_zoo_loaded()


_register_envs()

__all__ = [
    "AgentType", "RoadType", "Scenario", "ScenarioError", "CONDITION_FIELDS",
    "NUM_CONDITION_FIELDS", "PANEL", "PROFILES", "normalize_condition", "profile",
    "sample_conditions", *_LAZY,
]
