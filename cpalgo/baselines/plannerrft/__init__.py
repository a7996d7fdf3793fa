"""PlannerRFT-dagger: GRPO on continuations against log-replayed traffic, learned temperature."""

import cpalgo.baselines.registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"PlannerRFT": "cpalgo.baselines.plannerrft.plannerrft", "grpo_objective": "cpalgo.baselines.plannerrft.plannerrft",
         "ExplorationHead": "cpalgo.baselines.plannerrft.policies"}
__getattr__, __dir__ = lazy_exports("cpalgo.baselines.plannerrft", _LAZY, globals())
__all__ = list(_LAZY)
