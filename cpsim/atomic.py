"""Atomic file writes: a reader (or a crash) never sees a half-written file.

Write into a temp file in the target's folder, give it the permissions a plain ``open``
would, then ``os.replace`` it over the target (atomic on POSIX file systems). Used by
every writer of the project: scenario caches, videos, checkpoints, results, figures.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator


def blocking_file(path: str | os.PathLike) -> Path | None:
    """The existing file among ``path``'s parents that keeps ``path`` from being created
    (its nearest existing ancestor, when that is not a folder), else None."""
    for parent in Path(path).parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def default_mode(directory: bool = False) -> int:
    """Permissions a plain ``open`` / ``mkdir`` would give (mkstemp / mkdtemp use 0600 / 0700)."""
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[str]:
    """Yield a temp file path next to ``path``; when the block succeeds the file replaces
    ``path``, when it raises the temp file is removed and ``path`` is left as it was.

    ``suffix`` lets writers that pick a format by extension (imageio, SB3) see the right one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, default_mode())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
