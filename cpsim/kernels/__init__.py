"""Warp kernels of the simulator, grouped by stage; all belong to one Warp module.

* :mod:`~cpsim.kernels.geometry`: SAT, segment tests, grid and lane queries, collision
  cases / fault (Warp functions + NumPy references).
* :mod:`~cpsim.kernels.dynamics`: jerk and classic models, the motion kernel.
* :mod:`~cpsim.kernels.controllers`: IDM along logged paths.
* :mod:`~cpsim.kernels.reward`: conditioned reward terms.
* :mod:`~cpsim.kernels.metrics`: events, outcomes, removal, metrics; per-world bookkeeping.
* :mod:`~cpsim.kernels.observation`: the observation kernel.
* :mod:`~cpsim.kernels.snapshot`: reset and world copies (snapshot / restore).

Each kernel's docstring ends with ``Reads:`` / ``Writes:`` lines: the fields of its
:class:`cpsim.state.State` argument it reads and writes (through the ``@wp.func`` helpers it
calls too; ``*`` every field, ``-`` none) and those of its :class:`cpsim.state.StepScratch`
argument (``scratch.present``: per-step scratch, written and read within one step), the
order constraints between the launches of a step at a glance.
``tests/cpsim/test_kernel_contracts.py`` derives both lists from the source and fails when a
docstring falls behind.

Each kernel has a launcher beside it (``launch_*`` in its module, see
:mod:`cpsim.kernels.common`): the kernel's arguments by name, written arrays passed as
``outputs=``, the written State / StepScratch fields in its ``Writes:`` line, and
``record=True`` for the Simulator's recorded launches. The Simulator never calls
``wp.launch`` itself.

Importing this package registers every kernel; :func:`load` compiles (or loads from the
kernel cache) the module for a device up front.
"""

from __future__ import annotations

import warp as wp

from cpsim.kernels import controllers, dynamics, geometry, metrics, observation, reward, snapshot  # noqa: F401
from cpsim.kernels.common import KERNEL_MODULE

_loaded: set[str] = set()


def load(device: str = "cpu") -> None:
    """Compile or load every simulator kernel for ``device`` (once per process)."""
    key = str(device)
    if key in _loaded:
        return
    wp.init()
    wp.load_module(KERNEL_MODULE, device=device)
    _loaded.add(key)


__all__ = ["load", "KERNEL_MODULE"]
