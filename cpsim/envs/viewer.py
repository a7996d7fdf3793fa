"""``render_mode="human"``: a matplotlib window that shows the frames the envs render.

Shared by :class:`cpsim.envs.drive.DriveEnv`, :class:`~cpsim.envs.drive.DriveVectorEnv` and
:class:`cpsim.envs.selfplay.SelfPlayVecEnv`. matplotlib is the ``plot`` extra. With a
non-interactive backend (no display, ``MPLBACKEND=Agg``) frames are drawn but no window
opens, so human-mode code also runs headless (tests, CI).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

_NON_INTERACTIVE = {"agg", "cairo", "pdf", "pgf", "ps", "svg", "template"}


class HumanViewer:
    """Shows RGB frames in one window, at most ``fps`` frames per second."""

    def __init__(self, title: str = "cpsim", fps: float = 10.0):
        try:
            import matplotlib
            import matplotlib.pyplot as plt
        except ImportError:
            raise ImportError("render_mode='human' needs matplotlib: pip install 'counterplay[plot]'") from None
        self._plt = plt
        backend = str(matplotlib.get_backend()).lower()
        self.interactive = backend not in _NON_INTERACTIVE and not backend.startswith("module://")
        self.title = title
        self.period = 1.0 / fps if fps and fps > 0 else 0.0
        self._fig: Any = None
        self._image: Any = None
        self._last = 0.0

    def show(self, frame: np.ndarray) -> None:
        if self._fig is None:
            self._fig, ax = self._plt.subplots(num=self.title)
            ax.set_axis_off()
            self._fig.tight_layout(pad=0)
            self._image = ax.imshow(frame)
            if self.interactive:
                self._plt.show(block=False)
        else:
            self._image.set_data(frame)
        self._fig.canvas.draw_idle()
        if self.interactive:
            self._fig.canvas.flush_events()
            wait = self.period - (time.perf_counter() - self._last)
            if wait > 0:
                self._plt.pause(wait)
            self._last = time.perf_counter()

    def close(self) -> None:
        if self._fig is not None:
            self._plt.close(self._fig)
            self._fig = self._image = None


def tile(frames: list[np.ndarray], columns: int | None = None) -> np.ndarray:
    """Frames of one size tiled into one image, row by row (black padding)."""
    n = len(frames)
    cols = columns or int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / cols))
    h, w, c = frames[0].shape
    out = np.zeros((rows * h, cols * w, c), frames[0].dtype)
    for k, f in enumerate(frames):
        r, q = divmod(k, cols)
        out[r * h:(r + 1) * h, q * w:(q + 1) * w] = f
    return out


__all__ = ["HumanViewer", "tile"]
