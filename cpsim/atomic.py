"""Atomic file writes: a reader (or a crash) never sees a half-written file or folder.

Write into a temp file in the target's folder, give it the permissions a plain ``open``
would, then ``os.replace`` it over the target (atomic on POSIX file systems). The one
implementation every writer of the project uses: scenario caches, videos, checkpoints,
results, figures.

* :func:`atomic_path`: a temp path to hand to any writer (``np.savez``, SB3's ``save``,
  imageio); it replaces the target when the block succeeds.
* :func:`write_bytes_atomic`, :func:`write_text_atomic`: the common cases.
* :class:`AtomicDir`: a whole folder, built under a temp name and swapped into place.
"""

from __future__ import annotations

import contextlib
import os
import shutil
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


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` (parents created) through :func:`atomic_path`."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` (parents created) through :func:`atomic_path`."""
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)


class AtomicDir:
    """Build a folder under a hidden temp name, then swap it into place.

    ``with AtomicDir(out) as tmp: ...write into tmp...``. On success the previous folder
    (if any) is replaced; on an exception (or interruption) the temp folder is removed
    and ``out`` is left as it was, so a partial result never looks complete.
    """

    def __init__(self, out: str | os.PathLike):
        self.out = Path(out)
        self.tmp: Path | None = None

    def __enter__(self) -> Path:
        parent = self.out.parent
        parent.mkdir(parents=True, exist_ok=True)
        if self.out.exists() and not self.out.is_dir():
            raise ValueError(f"out: {self.out} exists and is not a folder")
        self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.tmp-", dir=parent))
        os.chmod(self.tmp, default_mode(directory=True))
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self.tmp is not None
        if exc_type is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            return
        old = None
        if self.out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.old-", dir=self.out.parent))
            os.rmdir(old)
            os.replace(self.out, old)
        os.replace(self.tmp, self.out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
