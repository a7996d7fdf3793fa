"""PlannerRFT-dagger: GRPO on continuations against log-replayed traffic, learned temperature."""

import cpalgo.common.baseline_registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"PlannerRFT": "cpalgo.plannerrft.plannerrft", "grpo_objective": "cpalgo.plannerrft.plannerrft",
         "ExplorationHead": "cpalgo.plannerrft.policies"}
__getattr__, __dir__ = lazy_exports("cpalgo.plannerrft", _LAZY, globals())
__all__ = list(_LAZY)
