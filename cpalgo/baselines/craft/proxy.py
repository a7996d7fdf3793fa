"""CRAFT-dagger's traffic proxy: other vehicles hold their last action, then it decays.

An action of the discrete set has two control components (jerk model: longitudinal and
lateral jerk; classic model: acceleration and steering angle, :func:`action_grid`). For
``k`` decisions after the root the proxy gives every co-player

* its last action unchanged while ``k < hold``;
* afterwards the action whose components are nearest to the last action's components
  scaled by ``decay ** (k - hold + 1)`` (each component rounded to the nearest level of its
  table), so the controls shrink geometrically to the neutral (zero, zero) action and stay
  there.
"""

from __future__ import annotations

import numpy as np

from cpalgo.baselines.continuations import action_grid

__all__ = ["hold_then_decay"]


def hold_then_decay(last_actions: np.ndarray, k: int, hold: int, decay: float, dynamics: str = "jerk") -> np.ndarray:
    """Proxy actions ``k`` decisions after the root.

    Args:
        last_actions: (n,) int action indices each co-player took before the root.
        k: decisions since the root (0 at the root's decision).
        hold: decisions the last action is held (>= 0).
        decay: per-decision factor of the components after the hold, in [0, 1).
        dynamics: ``jerk`` or ``classic`` (the action set).
    Returns:
        (n,) int64 action indices.
    """
    first, second = action_grid(dynamics)
    a = np.asarray(last_actions, np.int64).reshape(-1)
    if a.size and (a.min() < 0 or a.max() >= first.size * second.size):
        raise ValueError(f"last_actions: indices must lie in [0, {first.size * second.size})")
    if int(k) < int(hold):
        return a.copy()
    scale = float(decay) ** (int(k) - int(hold) + 1)
    v1 = first[a // second.size] * scale
    v2 = second[a % second.size] * scale
    i = np.abs(v1[:, None] - first[None, :]).argmin(1)
    j = np.abs(v2[:, None] - second[None, :]).argmin(1)
    return (i * second.size + j).astype(np.int64)
