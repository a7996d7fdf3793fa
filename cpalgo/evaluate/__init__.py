"""BehaviorBench-style evaluation of driving policies over traffic regimes.

* :mod:`cpalgo.evaluate.metrics`: per-task metrics, score, outcome classes (pure NumPy;
  at-fault collisions come from the simulator's kernel, ``cpsim.kernels.geometry``).
* :mod:`cpalgo.evaluate.runner`: ``evaluate(policy, tasks, regimes, ...)``, batched through
  one :class:`cpsim.Simulator`.
* :mod:`cpalgo.evaluate.tables` / :mod:`cpalgo.evaluate.plots`: Markdown/JSON/CSV tables and
  figures, written atomically.
* ``python -m cpalgo.evaluate``: the command line.

Heavy modules (simulator, torch, matplotlib) are imported lazily on first access.
"""

from __future__ import annotations

from cpalgo.evaluate.metrics import OutcomeClass, outcome_class, task_score
from cpsim._lazy import lazy_exports

_LAZY = {
    "evaluate": "cpalgo.evaluate.runner",
    "EvalConfig": "cpalgo.evaluate.runner",
    "EvalResult": "cpalgo.evaluate.runner",
    "Evaluator": "cpalgo.evaluate.runner",
    "REGIMES": "cpalgo.evaluate.runner",
    "make_tasks": "cpalgo.evaluate.runner",
    "Task": "cpalgo.evaluate.runner",
    "write_results": "cpalgo.evaluate.tables",
    "markdown_tables": "cpalgo.evaluate.tables",
}

__getattr__, __dir__ = lazy_exports("cpalgo.evaluate", _LAZY, globals())

__all__ = ["OutcomeClass", "task_score", "outcome_class", *_LAZY]
