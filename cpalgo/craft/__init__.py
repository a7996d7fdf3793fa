"""CRAFT-dagger: score-function objective over continuations, traffic proxy, residual, EMA KL."""

from cpalgo.methods import register
from cpsim._lazy import lazy_exports

_LAZY = {"CRAFT": "cpalgo.craft.craft", "ResidualTable": "cpalgo.craft.craft",
         "score_function_objective": "cpalgo.craft.craft", "hold_then_decay": "cpalgo.craft.proxy"}
__getattr__, __dir__ = lazy_exports("cpalgo.craft", _LAZY, globals())
__all__ = list(_LAZY)

register("craft", "CRAFT: score function on 6 continuations, hold/decay traffic proxy + closed-loop residual, EMA KL",
         "cpalgo.craft.craft:CRAFT", group="baseline", label="CRAFT\u2020",
         components={"B": "-", "C": "-", "S": "-", "D": "-"}, replace=True)
