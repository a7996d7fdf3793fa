"""Front-ends over :class:`cpsim.Simulator`.

* :class:`~cpsim.envs.selfplay.SelfPlayVecEnv`: SB3 ``VecEnv``, one index per agent slot.
* :class:`~cpsim.envs.drive.DriveEnv` (``gymnasium.make("cpsim/Drive-v0")``) and
  :class:`~cpsim.envs.drive.DriveVectorEnv` (``gymnasium.make_vec``): one ego per world,
  co-players under a traffic regime.
* :mod:`cpsim.envs.regimes`: traffic regimes (:class:`TrafficDriver`), shared with the
  evaluation.

Names are imported lazily (the env modules import SB3 and torch).
"""

from __future__ import annotations

import importlib
from typing import Any

_LAZY = {
    "SelfPlayVecEnv": "cpsim.envs.selfplay",
    "DriveEnv": "cpsim.envs.drive",
    "DriveVectorEnv": "cpsim.envs.drive",
    "TrafficDriver": "cpsim.envs.regimes",
    "REGIMES": "cpsim.envs.regimes",
    "resolve_regime": "cpsim.envs.regimes",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'cpsim.envs' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = list(_LAZY)
