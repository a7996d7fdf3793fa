"""Ship the latest checkpoint of a self-play anchor run (``counterplay export-anchor``).

A run folder's ``checkpoint.zip`` (:mod:`cpalgo.anchor.selfplay`) is written to be resumed:
besides the weights it holds Adam's moments, every RNG state and the curve so far
(``resume_state``), the budget's per-generation log and the logging windows of the last
episodes. :func:`export_anchor` writes the same policy without them, as a ``CounterPlay``
checkpoint that :func:`cpalgo.evaluate.runner.load_model` loads and that post-training
(``set_parameters(..., exact_match=True)``) and ``counterplay train-anchor --init`` start
from, and optionally a JSON record of where it came from.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import platform
import zipfile
from pathlib import Path
from typing import Any

from cpalgo.anchor.selfplay import CHECKPOINT_FILE, COMMANDS_FILE, CURVE_FILE, RUN_FILE

__all__ = ["export_anchor", "HELD_OUT_ROWS"]

#: evaluated curve rows the record keeps (the last ones)
HELD_OUT_ROWS = 3
#: what the exported file leaves out of the run's checkpoint (the record lists it)
DROPPED = ("policy.optimizer state (Adam's moments and step counts; its settings stay)",
           "resume_state (segment, wall time, every RNG state, the curve rows)",
           "budget.history (one entry per generation; the budget's totals stay)",
           "ep_info_buffer, ep_success_buffer, _last_episode_starts (the last rollout's logging windows)")


def export_anchor(run_dir: str | os.PathLike, out: str | os.PathLike,
                  json_path: str | os.PathLike | None = None) -> dict[str, Any]:
    """Write the latest checkpoint of the self-play run in ``run_dir`` to ``out`` as a
    shippable anchor, and its provenance record to ``json_path`` (when given).

    The exported zip holds the policy's weights unchanged and everything loading and
    post-training read (settings, spaces, ``num_timesteps``, the schedules, the budget's
    totals), but not what only a resumed piece needs (:data:`DROPPED`): Adam's moments (a
    later run starts them afresh; the optimiser's settings stay, so ``set_parameters`` with
    ``exact_match=True`` still finds it), ``resume_state``, the budget's per-generation
    history and the logging windows. Entries are deflated. The checkpoint is read once (a
    running piece may replace it meanwhile: the record describes the bytes read), and both
    files are written atomically; ``out`` may not be the run's own checkpoint.

    Returns the record, a plain JSON dict:

    * ``run_dir``: the folder as given.
    * ``source``: the run's checkpoint read: ``path``, ``bytes``, ``sha256``.
    * ``anchor``: the exported file: ``path``, ``bytes``, ``sha256``.
    * ``dropped``: what the export left out (:data:`DROPPED`).
    * ``recipe``: ``path`` (the recipe the run was started with, from ``run.json``), ``copy``
      (the run folder's ``recipe.yml``) and ``text`` (that copy's text; None when missing).
    * ``settings``, ``changes``: ``run.json``'s run settings and the changes later pieces
      made (each with the segment and transition count it holds from).
    * ``commands``: the lines of ``commands.txt`` (every piece's command line, in order).
    * ``num_timesteps``: counted (live) transitions trained.
    * ``segments``: segments trained.
    * ``training_wall_s``: training wall time in seconds (the curve's last ``wall_s``; the
      held-out evaluations and env builds beside it are not counted).
    * ``network``: ``policy_class`` (module and name), ``policy_kwargs``, ``dynamics`` (the
      recipe's), ``actions`` (action count), ``observation_size``, ``parameters``.
    * ``machine``: where the export ran: ``cpu_count`` (``os.cpu_count()``), ``processor``
      and ``machine`` (``platform``; ``processor`` is often empty on Linux), ``cpu_model``
      (``/proc/cpuinfo``'s model name; None elsewhere), ``platform``, ``python``, ``torch``,
      ``stable_baselines3``. ``trained_with``: the run checkpoint's ``system_info.txt`` (OS and
      library versions of the process that wrote it).
    * ``curve``: ``path`` (``curve.csv``), ``rows`` (segments in the checkpoint's curve),
      ``last_row`` (the exported weights' segment: transitions, wall time, training columns
      and, when evaluated, held-out columns), ``last_row_evaluated`` (whether it has the
      held-out columns: a running piece writes a checkpoint before its evaluation comes back)
      and ``last_evaluated`` (the last :data:`HELD_OUT_ROWS` rows with held-out columns).
      The rows are the checkpoint's own (``curve.csv`` is rewritten from them); NaN is null.

    Raises ``ValueError`` naming ``run_dir`` (not a run folder, or its checkpoint does not
    load), ``out`` or ``json_path`` (a folder, not ``.zip``, the run's own checkpoint, the
    same file twice) before anything is written.
    """
    import torch as th

    from cpalgo.counterplay.algorithm import CounterPlay
    from cpsim.atomic import atomic_path, blocking_file, write_text_atomic

    run = Path(run_dir)
    if not run.is_dir():
        raise ValueError(f"run_dir: no such folder {str(run)!r}")
    missing = [name for name in (CHECKPOINT_FILE, RUN_FILE) if not (run / name).is_file()]
    if missing:
        raise ValueError(f"run_dir: {str(run)!r} holds no {' and no '.join(missing)} "
                         f"(not a train-anchor --run-dir folder?)")
    out = Path(out)
    targets = [("out", out)] + ([("json_path", Path(json_path))] if json_path is not None else [])
    for name, path in targets:
        if path.is_dir():
            raise ValueError(f"{name}: {str(path)!r} is a folder, not a file")
        blocker = blocking_file(path)
        if blocker is not None:
            raise ValueError(f"{name}: {str(blocker)!r} is a file, so {str(path)!r} cannot be created")
        if path.exists() and path.resolve() == (run / CHECKPOINT_FILE).resolve():
            raise ValueError(f"{name}: {str(path)!r} is the run's own checkpoint; export to another file")
    if out.suffix != ".zip":
        raise ValueError(f"out: {str(out)!r} must end in .zip (an SB3 checkpoint)")
    if json_path is not None and Path(json_path).resolve() == out.resolve():
        raise ValueError(f"json_path: {str(json_path)!r} is the same file as the exported anchor")
    try:
        doc = json.loads((run / RUN_FILE).read_text())
        settings = doc["settings"]
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"run_dir: {str(run / RUN_FILE)!r} is not a run's settings ({exc})") from None

    raw = (run / CHECKPOINT_FILE).read_bytes()  # one version, whatever a running piece does meanwhile
    try:
        with zipfile.ZipFile(io.BytesIO(raw)) as archive:
            names = set(archive.namelist())
            trained_with = archive.read("system_info.txt").decode() if "system_info.txt" in names else None
        model = CounterPlay.load(io.BytesIO(raw), device="cpu")  # old settings' defaults applied as from a path
    except Exception as exc:  # noqa: BLE001 - reported with the file name
        raise ValueError(f"run_dir: {str(run / CHECKPOINT_FILE)!r} does not load as a CounterPlay checkpoint "
                         f"({type(exc).__name__}: {exc})") from None
    state = getattr(model, "resume_state", None)
    if not isinstance(state, dict) or "rows" not in state:
        raise ValueError(f"run_dir: {str(run / CHECKPOINT_FILE)!r} holds no resume state "
                         f"(not a train-anchor --run-dir checkpoint)")

    # what only a resumed piece needs
    del model.resume_state
    model.policy.optimizer.state.clear()  # Adam restarts its moments; lr, betas, eps stay
    if hasattr(model, "budget"):
        model.budget.history = []
    model.ep_info_buffer = model.ep_success_buffer = None  # SB3's learn() makes new ones
    model._last_episode_starts = model._last_obs = model._last_original_obs = None

    rows = [dict(r) for r in state["rows"]]
    evaluated = [r for r in rows if "normal_goal" in r]
    recipe_copy = run / "recipe.yml"
    recipe_text = recipe_copy.read_text() if recipe_copy.is_file() else None
    dynamics = None
    if recipe_text is not None:
        from cpalgo.recipes import load_recipe

        try:
            dynamics = load_recipe(recipe_copy).env_kwargs.get("dynamics")
        except Exception as exc:  # noqa: BLE001 - reported with the file name
            raise ValueError(f"run_dir: {str(recipe_copy)!r} does not load as a recipe ({exc})") from None
    commands = (run / COMMANDS_FILE).read_text().splitlines() if (run / COMMANDS_FILE).is_file() else []
    policy = model.policy
    try:
        import stable_baselines3

        sb3_version = stable_baselines3.__version__
    except (ImportError, AttributeError):
        sb3_version = None
    record = {
        "run_dir": str(run_dir),
        "source": {"path": str(run / CHECKPOINT_FILE), "bytes": len(raw), "sha256": hashlib.sha256(raw).hexdigest()},
        "anchor": None,  # below, once written
        "dropped": list(DROPPED),
        "recipe": {"path": settings.get("recipe"), "copy": str(recipe_copy), "text": recipe_text},
        "settings": settings,
        "changes": doc.get("changes", []),
        "commands": commands,
        "num_timesteps": int(model.num_timesteps),
        "segments": int(state.get("segment", len(rows))),
        "training_wall_s": float(rows[-1]["wall_s"]) if rows else float(state.get("wall_s", 0.0)),
        "network": {
            "policy_class": f"{type(policy).__module__}.{type(policy).__qualname__}",
            "policy_kwargs": model.policy_kwargs,
            "dynamics": dynamics,
            "actions": int(model.action_space.n) if hasattr(model.action_space, "n") else None,
            "observation_size": int(math.prod(model.observation_space.shape)),
            "parameters": int(sum(p.numel() for p in policy.parameters())),
        },
        "machine": {"cpu_count": os.cpu_count(), "processor": platform.processor(), "cpu_model": _cpu_model(),
                    "machine": platform.machine(), "platform": platform.platform(), "python": platform.python_version(),
                    "torch": th.__version__, "stable_baselines3": sb3_version},
        "trained_with": trained_with,
        "curve": {"path": str(run / CURVE_FILE), "rows": len(rows), "last_row": rows[-1] if rows else None,
                  "last_row_evaluated": bool(rows) and "normal_goal" in rows[-1],
                  "last_evaluated": evaluated[-HELD_OUT_ROWS:]},
    }
    record = _plain(record)  # everything that may fail ran before the anchor is written

    with atomic_path(out, suffix=".zip.tmp") as tmp:  # a suffix, so SB3 appends no ".zip"
        model.save(tmp)
        with zipfile.ZipFile(tmp) as archive:
            entries = [(info.filename, archive.read(info)) for info in archive.infolist()]
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as archive:
            for name, data in entries:
                archive.writestr(name, data)
    written = out.read_bytes()
    record["anchor"] = {"path": str(out), "bytes": len(written), "sha256": hashlib.sha256(written).hexdigest()}
    if json_path is not None:
        write_text_atomic(json_path, json.dumps(record, indent=2, allow_nan=False) + "\n")
    return record


def _cpu_model() -> str | None:
    """The CPU's model name from ``/proc/cpuinfo`` (Linux), else None."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                if key.strip() == "model name":
                    return value.strip()
    except OSError:
        pass
    return None


def _plain(value: Any) -> Any:
    """``value`` as plain JSON types: NumPy scalars as Python numbers, NaN and infinities as
    None, tuples as lists, anything else unknown as its ``str``."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:  # a NumPy / torch scalar
        value = value.item()
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return str(value)
