"""cpalgo: CounterPlay counterfactual post-training on top of sb3-contrib's RecurrentPPO.

``from cpalgo import CounterPlay`` loads the algorithm lazily (torch and SB3 are only
imported on first use).
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "CounterPlay": "cpalgo.counterplay.algorithm",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'cpalgo' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = list(_LAZY)
