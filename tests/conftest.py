"""Shared pytest setup.

Warms the Warp kernel cache once, in the controlling process, before any (xdist) worker
starts: the simulator's kernels compile in one module (several seconds the first time),
after which every process loads them from the cache in milliseconds.
"""

from __future__ import annotations

import os
import sys

# the repository root on sys.path so ``tests.cpsim.scenes`` imports without installation
_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)


def pytest_configure(config) -> None:
    if hasattr(config, "workerinput"):  # an xdist worker: the controller already warmed it
        return
    try:
        import warp as wp

        wp.config.quiet = True
        import cpsim.kernels

        cpsim.kernels.load("cpu")
    except Exception as exc:  # never block collection; the failing tests will say why
        sys.stderr.write(f"[conftest] could not warm the Warp kernel cache: {exc}\n")
