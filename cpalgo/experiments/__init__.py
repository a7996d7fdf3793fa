"""Experiment grids: post-training runs (methods x seeds) at one budget, their evaluation,
the seed paper's tables, on Ray or in-process.

* :mod:`cpalgo.experiments.grid`: grid files (:func:`load_grid`, :class:`GridConfig`).
* :mod:`cpalgo.experiments.runs`: one run (train to B_post with resumable checkpoints, evaluate).
* :mod:`cpalgo.experiments.runner`: :func:`run_experiment` (Ray tasks or sequential).
* :mod:`cpalgo.experiments.tables`: ``results.csv``, ``tables.md`` (Tables I-V, search
  statistics, targets) and the plots.
* :mod:`cpalgo.experiments.mainjob`: ``counterplay run``: PPO-Continue and CounterPlay from
  the shipped anchor at one budget, both against the anchor on the same held-out tasks.

Command line: ``counterplay experiment --config zoo/experiments/paper_small.yml --out DIR``.
"""

from __future__ import annotations

from cpsim._lazy import lazy_exports

_LAZY = {
    "load_grid": "cpalgo.experiments.grid",
    "GridConfig": "cpalgo.experiments.grid",
    "GridError": "cpalgo.experiments.grid",
    "run_experiment": "cpalgo.experiments.runner",
    "ExperimentResult": "cpalgo.experiments.runner",
    "write_tables": "cpalgo.experiments.tables",
    "run_main_job": "cpalgo.experiments.mainjob",
}

__getattr__, __dir__ = lazy_exports("cpalgo.experiments", _LAZY, globals())

__all__ = list(_LAZY)
