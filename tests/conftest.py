"""Shared pytest setup.

Warms the Warp kernel cache once, in the controlling process, before any (xdist) worker
starts: the simulator's kernels compile in one module (several seconds the first time),
after which every process loads them from the cache in milliseconds.

Fixture :func:`_one_torch_thread`: modules that train tiny networks opt in with
``pytestmark = pytest.mark.usefixtures("_one_torch_thread")``.
"""

from __future__ import annotations

import os
import sys

import pytest

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


@pytest.fixture
def _one_torch_thread():
    """One torch intra-op thread for the test, the previous count restored after it: tiny
    networks on a shared 2-core machine run several times faster than with two threads
    contending (and leave the other core to other work)."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
