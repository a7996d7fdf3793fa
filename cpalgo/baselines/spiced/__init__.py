"""SPICED-dagger: PPO plus a KL penalty toward a frozen behaviour-cloning reference."""

import cpalgo.baselines.registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"Spiced": "cpalgo.baselines.spiced.spiced", "tracking_reference": "cpalgo.baselines.spiced.reference",
         "load_reference": "cpalgo.baselines.spiced.reference", "ReferenceStepper": "cpalgo.baselines.spiced.reference"}
__getattr__, __dir__ = lazy_exports("cpalgo.baselines.spiced", _LAZY, globals())
__all__ = list(_LAZY)
