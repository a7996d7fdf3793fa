"""SPICED-dagger: PPO plus a KL penalty toward a frozen behaviour-cloning reference."""

from cpalgo.methods import register
from cpsim._lazy import lazy_exports

_LAZY = {"Spiced": "cpalgo.spiced.spiced", "tracking_reference": "cpalgo.spiced.reference",
         "load_reference": "cpalgo.spiced.reference", "ReferenceStepper": "cpalgo.spiced.reference"}
__getattr__, __dir__ = lazy_exports("cpalgo.spiced", _LAZY, globals())
__all__ = list(_LAZY)

register("spiced", "SPICED: PPO + KL toward a frozen BC policy cloned from log-tracking actions",
         "cpalgo.spiced.spiced:Spiced", group="baseline", label="SPICED\u2020",
         components={"B": "-", "C": "-", "S": "-", "D": "-"}, replace=True)
