"""One tensor-to-NumPy conversion for the whole code base (cpsim and cpalgo)."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["to_numpy"]


def to_numpy(x: Any) -> np.ndarray:
    """Torch tensor (any device) or array-like -> NumPy array (a view of CPU memory when
    possible: callers copy what they keep)."""
    if hasattr(x, "detach"):
        return x.detach().cpu().numpy()
    return np.asarray(x)
