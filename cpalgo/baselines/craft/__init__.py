"""CRAFT-dagger: score-function objective over continuations, traffic proxy, residual, EMA KL."""

import cpalgo.baselines.registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"CRAFT": "cpalgo.baselines.craft.craft", "ResidualTable": "cpalgo.baselines.craft.craft",
         "score_function_objective": "cpalgo.baselines.craft.craft", "hold_then_decay": "cpalgo.baselines.craft.proxy"}
__getattr__, __dir__ = lazy_exports("cpalgo.baselines.craft", _LAZY, globals())
__all__ = list(_LAZY)
