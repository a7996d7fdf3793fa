"""cpalgo: CounterPlay counterfactual post-training on top of sb3-contrib's RecurrentPPO.

``from cpalgo import CounterPlay`` loads the algorithm lazily (torch and SB3 are only
imported on first use).
"""

from __future__ import annotations

from cpsim._lazy import lazy_exports

_LAZY = {
    "CounterPlay": "cpalgo.counterplay.algorithm",
}

__getattr__, __dir__ = lazy_exports("cpalgo", _LAZY, globals())

__all__ = list(_LAZY)
