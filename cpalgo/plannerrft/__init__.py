"""PlannerRFT-dagger: GRPO on continuations against log-replayed traffic, learned temperature."""

from cpalgo.methods import register
from cpsim._lazy import lazy_exports

_LAZY = {"PlannerRFT": "cpalgo.plannerrft.plannerrft", "grpo_objective": "cpalgo.plannerrft.plannerrft",
         "ExplorationHead": "cpalgo.plannerrft.policies"}
__getattr__, __dir__ = lazy_exports("cpalgo.plannerrft", _LAZY, globals())
__all__ = list(_LAZY)

register("plannerrft", "PlannerRFT: clipped group-relative objective vs log-replayed traffic, learned temperature",
         "cpalgo.plannerrft.plannerrft:PlannerRFT", group="baseline", label="PlannerRFT\u2020",
         components={"B": "-", "C": "-", "S": "-", "D": "-"}, replace=True)
