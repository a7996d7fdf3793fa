"""CRAFT-dagger: score-function objective over continuations, traffic proxy, residual, EMA KL."""

import cpalgo.common.baseline_registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"CRAFT": "cpalgo.craft.craft", "ResidualTable": "cpalgo.craft.craft",
         "score_function_objective": "cpalgo.craft.craft", "hold_then_decay": "cpalgo.craft.proxy"}
__getattr__, __dir__ = lazy_exports("cpalgo.craft", _LAZY, globals())
__all__ = list(_LAZY)
