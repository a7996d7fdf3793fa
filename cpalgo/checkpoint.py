"""Atomic checkpoints: a crash mid-``learn`` never leaves a half-written model file.

SB3's ``save`` writes the zip in place; we write to a temp file in the same folder and
``os.replace`` it over the target, which is atomic on POSIX file systems.
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path
from typing import Any, Mapping

from stable_baselines3.common.callbacks import BaseCallback

from cpsim.atomic import atomic_path


def saved_data_keys(path: str | os.PathLike | io.BufferedIOBase) -> set[str] | None:
    """Names of the attributes an SB3 checkpoint saved (the keys of its ``data`` entry), or
    None when ``path`` (``.zip`` appended when missing, as SB3 does; or an open binary file,
    read from its start and left where it was) is not such a file.

    A setting that a checkpoint lacks was added after it was written: its loader can then
    restore the behaviour of that time instead of the new default.
    """
    import json

    if hasattr(path, "seek"):  # a checkpoint in memory, as SB3's load also takes
        position = path.tell()
        try:
            path.seek(0)
            with zipfile.ZipFile(path) as archive:
                return set(json.loads(archive.read("data")))
        except (zipfile.BadZipFile, KeyError, ValueError):
            return None
        finally:
            path.seek(position)
    candidates = [Path(path)] if Path(path).suffix == ".zip" else [Path(path), Path(str(path) + ".zip")]
    for candidate in candidates:
        if candidate.is_file():
            try:
                with zipfile.ZipFile(candidate) as archive:
                    return set(json.loads(archive.read("data")))
            except (zipfile.BadZipFile, KeyError, ValueError):
                return None
    return None


def save_model_atomic(model: Any, path: str | os.PathLike, extra_files: Mapping[str, bytes] | None = None) -> Path:
    """Save an SB3 model to ``path`` (``.zip`` appended when missing) atomically.

    ``extra_files``: name -> bytes, written into the same zip before it replaces ``path``,
    so they always belong to these weights (SB3's loaders ignore entries they do not know).
    """
    path = Path(path)
    if path.suffix != ".zip":
        path = path.with_suffix(path.suffix + ".zip") if path.suffix else path.with_suffix(".zip")
    with atomic_path(path, suffix=".zip.tmp") as tmp:  # a suffix, so SB3 appends no ".zip"
        model.save(tmp)
        if extra_files:
            with zipfile.ZipFile(tmp, "a", compression=zipfile.ZIP_DEFLATED) as archive:
                for name, data in extra_files.items():
                    archive.writestr(name, data)
    return path


class AtomicCheckpointCallback(BaseCallback):
    """Every ``save_freq`` calls to ``env.step`` (one call = ``num_envs`` transitions), save
    the model atomically to ``path`` (one file, overwritten: always the latest good one)."""

    def __init__(self, save_freq: int, path: str | os.PathLike, verbose: int = 0):
        super().__init__(verbose)
        if save_freq < 1:
            raise ValueError(f"save_freq: must be >= 1, got {save_freq}")
        self.save_freq = int(save_freq)
        self.path = Path(path)

    def _on_step(self) -> bool:
        if self.n_calls % self.save_freq == 0:
            saved = save_model_atomic(self.model, self.path)
            if self.verbose:
                print(f"checkpoint: {saved} at {self.num_timesteps} timesteps")
        return True
