"""What the commands share to check their input before any work: :class:`UsageError`
(one line, exit status 2), argument types for whole numbers, output paths that can be
written, ``--add-womd`` folders that load, torch's thread count, and :func:`brief` error
messages.

``cpalgo.cli`` and the commands that live beside their library code (``compress-anchor``
in :mod:`cpalgo.anchor.compress`) import them from here, so no library module imports the
command-line module.
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Any

__all__ = ["UsageError", "whole_number", "positive_int", "non_negative_int", "check_out_path",
           "load_womd_option", "set_threads", "brief"]


class UsageError(Exception):
    """A wrong argument, or a file that is missing or does not fit: one line, exit status 2."""


def whole_number(text: str, minimum: int) -> int:
    """``text`` as a whole number >= ``minimum`` (``200000`` and ``2e5`` both read);
    ``argparse.ArgumentTypeError`` otherwise."""
    try:
        value = float(text)  # accepts 200000 and 2e5
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if not math.isfinite(value) or not value.is_integer():
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}")
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {text}")
    return int(value)


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1."""
    return whole_number(text, 1)


def non_negative_int(text: str) -> int:
    """argparse type: a whole number >= 0."""
    return whole_number(text, 0)


def check_out_path(path: str | os.PathLike, argument: str, *, folder: bool) -> Path:
    """``UsageError`` naming ``argument`` when ``path`` cannot be written: one of its parents
    is a file, or the path itself is a file where a folder goes (``folder``) or the reverse.
    Commands call it before any work, so a bad ``--out`` costs nothing."""
    out = Path(path)
    if out.exists():
        if folder and not out.is_dir():
            raise UsageError(f"{argument}: {str(out)!r} is a file, not a folder")
        if not folder and out.is_dir():
            raise UsageError(f"{argument}: {str(out)!r} is a folder, not a file")
        return out
    from cpsim.atomic import blocking_file

    blocker = blocking_file(out)
    if blocker is not None:
        raise UsageError(f"{argument}: {str(blocker)!r} is a file, so {str(out)!r} cannot be created")
    return out


def load_womd_option(folder: str) -> list[Any]:
    """The scenes of an ``--add-womd`` folder; a load failure is a ``UsageError`` naming it."""
    from cpsim import scenario as scen_mod

    if not os.path.isdir(folder):
        raise UsageError(f"--add-womd: no such folder {folder!r}")
    try:
        return list(scen_mod.load_dir(folder)[0])
    except Exception as exc:  # noqa: BLE001 - reported with the folder name
        raise UsageError(f"--add-womd: {folder}: {exc}") from None


def set_threads(threads: int | None) -> None:
    """``torch.set_num_threads(threads)`` when ``threads`` is given (torch's default otherwise)."""
    import torch

    if threads:
        torch.set_num_threads(threads)


def brief(exc: BaseException, lines: int = 2) -> str:
    """The first non-empty lines of an exception's message (torch's state-dict mismatch
    lists every tensor)."""
    return " ".join([line.strip() for line in str(exc).splitlines() if line.strip()][:lines])
