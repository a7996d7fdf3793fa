"""Front-ends over :class:`cpsim.Simulator`.

* :class:`~cpsim.envs.selfplay.SelfPlayVecEnv`: SB3 ``VecEnv``, one index per agent slot, and
  :class:`~cpsim.envs.selfplay.SelfPlayVecNormalize` (``VecNormalize`` over active slots).
* :class:`~cpsim.envs.drive.DriveEnv` (``gymnasium.make("cpsim/Drive-v0")``) and
  :class:`~cpsim.envs.drive.DriveVectorEnv` (``gymnasium.make_vec``): one ego per world,
  co-players under a traffic regime.
* :mod:`cpsim.envs.regimes`: traffic regimes (:class:`TrafficDriver`, co-player models
  or checkpoints via :func:`load_policy`), shared with the evaluation.
* :mod:`cpsim.envs.viewer`: ``render_mode="human"``.

Names are imported lazily (the env modules import SB3 and torch).
"""

from __future__ import annotations

from cpsim._lazy import lazy_exports

_LAZY = {
    "SelfPlayVecEnv": "cpsim.envs.selfplay",
    "SelfPlayVecNormalize": "cpsim.envs.selfplay",
    "DriveEnv": "cpsim.envs.drive",
    "DriveVectorEnv": "cpsim.envs.drive",
    "TrafficDriver": "cpsim.envs.regimes",
    "REGIMES": "cpsim.envs.regimes",
    "resolve_regime": "cpsim.envs.regimes",
    "load_policy": "cpsim.envs.regimes",
}

__getattr__, __dir__ = lazy_exports("cpsim.envs", _LAZY, globals())

__all__ = list(_LAZY)
