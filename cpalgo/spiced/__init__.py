"""SPICED-dagger: PPO plus a KL penalty toward a frozen behaviour-cloning reference."""

import cpalgo.common.baseline_registry  # noqa: F401  (registers the six in table order)
from cpsim._lazy import lazy_exports

_LAZY = {"Spiced": "cpalgo.spiced.spiced", "tracking_reference": "cpalgo.spiced.reference",
         "load_reference": "cpalgo.spiced.reference", "ReferenceStepper": "cpalgo.spiced.reference"}
__getattr__, __dir__ = lazy_exports("cpalgo.spiced", _LAZY, globals())
__all__ = list(_LAZY)
