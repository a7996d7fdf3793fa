"""One run of a grid: post-train a method from the anchor to the grid's budget, with
resumable checkpoints, then evaluate it under its deployment conditions.

Files of a run (``OUT/runs/<method>/seed<k>/``), every one written atomically:

* ``checkpoint.zip``: the latest resumable state, every ``checkpoint_every`` generations:
  the model with its optimiser and, inside the same zip (``counterplay_state.json``), the
  budget totals, step counters and method counters, so one rename replaces weights and
  counters together and a kill at any moment leaves a matching pair.
  ``checkpoint.json`` is a readable copy of those counters, written after the zip. A killed
  run restarts from the zip (RNG streams, CounterPlay's searches queued for the next
  generation and PPO-Opponent's older checkpoints are not kept: the continuation is a
  faithful run, not a bit-identical one).
* ``progress.json``: generation, B_post and timing after every generation.
* ``model.zip`` + ``train.json``: the trained model and its summary (budget, counters, wall
  time); ``train.json`` marks the training as finished.
* ``eval_<deployment>.npz``: the evaluator's per task-regime columns
  (:class:`cpalgo.evaluate.runner.EvalResult`), one file per deployment condition, on the
  grid's first task set (``evaluation.seed``); ``eval_<deployment>.taskset<k>.npz`` on each
  further task set k (:func:`eval_path`). Each is a file of its own, so a resumed grid
  evaluates only the missing ones, and a task set added to the grid later is evaluated
  without training again.

The anchor's evaluations live in ``OUT/anchor/eval_<deployment>.npz`` (and ``.taskset<k>``).
"""

from __future__ import annotations

import io
import json
import os
import sys
import time
import traceback
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cpalgo.experiments.grid import ANCHOR, GridConfig, RunSpec
from cpsim.atomic import write_bytes_atomic

__all__ = ["run_dir", "eval_path", "run_status", "execute_run", "train_run", "evaluate_columns", "load_columns",
           "budget_state", "restore_budget_state", "save_checkpoint", "read_checkpoint", "CHECKPOINT_STATE",
           "write_bytes_atomic", "write_json_atomic"]

Echo = Callable[[str], None]


def _echo(line: str) -> None:
    print(line, flush=True)


# ----------------------------------------------------------------------------- files
def write_json_atomic(path: str | os.PathLike, doc: Any) -> None:
    write_bytes_atomic(path, (json.dumps(doc, indent=2, default=_json_default) + "\n").encode())


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (set, tuple)):
        return list(o)
    return str(o)


def run_dir(out: str | os.PathLike, spec: RunSpec) -> Path:
    """Folder of a run (``OUT/runs/<method>/seed<k>``; the anchor's: ``OUT/anchor``)."""
    out = Path(out)
    return out / ANCHOR if spec.method == ANCHOR else out / "runs" / spec.method / f"seed{spec.seed}"


def eval_path(grid: GridConfig, folder: str | os.PathLike, deployment: str, task_set: int | None = None) -> Path:
    """A run folder's evaluation file under ``deployment`` on ``task_set`` (default: the
    grid's first): ``eval_<deployment>.npz`` for the first task set, which is the name a
    grid of one task set has always used, ``eval_<deployment>.taskset<k>.npz`` for another."""
    sets = grid.evaluation.task_sets
    if task_set is None or int(task_set) == sets[0]:
        return Path(folder) / f"eval_{deployment}.npz"
    return Path(folder) / f"eval_{deployment}.taskset{int(task_set)}.npz"


def _evaluations(grid: GridConfig, spec: RunSpec) -> list[tuple[int, str]]:
    """(task set, deployment) of every evaluation of a run, task sets outermost."""
    return [(t, d) for t in grid.evaluation.task_sets for d in grid.evaluation.deployments_of(spec.method)]


def _readable(path: Path) -> bool:
    """An evaluation file that exists and opens (a truncated one is redone, not trusted)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return "score" in data.files
    except (OSError, ValueError, zipfile.BadZipFile, EOFError):
        return False


def run_status(grid: GridConfig, out: str | os.PathLike, spec: RunSpec) -> str:
    """``done`` (trained and every evaluation written), ``evaluate`` (trained, evaluations
    missing or unreadable), ``resume`` (a checkpoint to continue from) or ``new``.

    A run whose ``train.json`` and evaluations are all there is done even without its
    ``model.zip``: a clone that keeps only the small records (weights are not committed)
    resumes a grid without training its finished runs again."""
    folder = run_dir(out, spec)
    evals_done = all(_readable(eval_path(grid, folder, d, t)) for t, d in _evaluations(grid, spec))
    if spec.method == ANCHOR:
        return "done" if evals_done else "evaluate"
    trained = (folder / "train.json").is_file()
    if trained and evals_done:
        return "done"
    if trained and (folder / "model.zip").is_file():
        return "evaluate"
    if (folder / "checkpoint.zip").is_file():
        return "resume"
    return "new"


# ----------------------------------------------------------------------------- budget state
def _totals_attributes(model: Any) -> list[str]:
    return sorted(k for k, v in vars(model).items() if k.endswith("_totals") and isinstance(v, dict))


def budget_state(model: Any) -> dict[str, Any]:
    """What a checkpoint needs besides the weights: budget totals, counters, method counts."""
    b = model.budget
    return {
        "budget": {k: int(getattr(b, k)) for k in ("main", "factual", "candidate", "verification", "generations")},
        "num_timesteps": int(model.num_timesteps),
        "n_updates": int(getattr(model, "_n_updates", 0)),
        "totals": {name: dict(getattr(model, name)) for name in _totals_attributes(model)},
    }


#: The checkpoint's counters, inside checkpoint.zip (SB3's loaders ignore the entry).
CHECKPOINT_STATE = "counterplay_state.json"


def save_checkpoint(model: Any, folder: str | os.PathLike, **extra: Any) -> Path:
    """``folder/checkpoint.zip``: the model and its :func:`budget_state` (plus ``extra``) in
    one zip, replaced by one rename; then ``checkpoint.json``, a readable copy of the state
    (:func:`read_checkpoint` does not need it). Returns the zip's path."""
    from cpalgo.checkpoint import save_model_atomic

    folder = Path(folder)
    state = {**budget_state(model), **extra}
    data = (json.dumps(state, indent=2, default=_json_default) + "\n").encode()
    path = save_model_atomic(model, folder / "checkpoint.zip", extra_files={CHECKPOINT_STATE: data})
    write_bytes_atomic(folder / "checkpoint.json", data)
    return path


def read_checkpoint(folder: str | os.PathLike) -> dict[str, Any] | None:
    """The state saved with ``folder/checkpoint.zip``, or None when there is no zip.

    Raises ``ValueError`` (or ``OSError`` / ``zipfile.BadZipFile``) when the zip does not
    open, or holds no intact ``policy.pth``, or when its counters cannot be trusted: a zip
    written before the state went inside it is paired with ``checkpoint.json`` only when
    both record the same ``num_timesteps`` (a kill between their two renames left new
    weights beside old counters otherwise).
    """
    folder = Path(folder)
    zip_path, json_path = folder / "checkpoint.zip", folder / "checkpoint.json"
    if not zip_path.is_file():
        return None
    with zipfile.ZipFile(zip_path) as archive:
        names = archive.namelist()
        if "policy.pth" not in names or archive.testzip() is not None:
            raise zipfile.BadZipFile("no intact policy.pth")
        if CHECKPOINT_STATE in names:
            return json.loads(archive.read(CHECKPOINT_STATE))
        saved = json.loads(archive.read("data")).get("num_timesteps") if "data" in names else None
    if not json_path.is_file():
        raise ValueError(f"{json_path.name} is missing and the zip holds no counters")
    state = json.loads(json_path.read_text())
    if not isinstance(state, dict) or saved is None or state.get("num_timesteps") != saved:
        got = state.get("num_timesteps") if isinstance(state, dict) else None
        raise ValueError(f"{json_path.name} is from another save than the weights "
                         f"({got} against {saved} timesteps)")
    return state


def restore_budget_state(model: Any, state: dict[str, Any]) -> None:
    """Inverse of :func:`budget_state` (on a model whose weights were just loaded)."""
    for k, v in state["budget"].items():
        setattr(model.budget, k, int(v))
    model.num_timesteps = int(state["num_timesteps"])
    model._n_updates = int(state.get("n_updates", 0))
    for name, totals in state.get("totals", {}).items():
        setattr(model, name, dict(totals))


# ----------------------------------------------------------------------------- training
def make_env(grid: GridConfig, recipe: Any, seed: int) -> Any:
    """The recipe's self-play env (plus the grid's ``env`` overrides), ``VecMonitor``-wrapped."""
    from stable_baselines3.common.vec_env import VecMonitor

    import cpsim
    from cpalgo.recipes import import_string

    if recipe.normalize is not None:
        raise ValueError(f"recipe: normalize in {recipe.path}: grid runs train on raw observations")
    kwargs = {**recipe.env_kwargs, **dict(grid.env)}
    kwargs.setdefault("seed", seed)
    kwargs.setdefault("device", grid.device)
    env = cpsim.SelfPlayVecEnv(num_worlds=grid.worlds or recipe.num_worlds, **kwargs)
    wrappers = [(import_string(name), kw) for name, kw in recipe.vec_env_wrappers]
    if not any(isinstance(cls, type) and issubclass(cls, VecMonitor) for cls, _ in wrappers):
        env = VecMonitor(env)
    for cls, kw in wrappers:
        env = cls(env, **kw)
    return env


def build_run_model(grid: GridConfig, method: str, seed: int, *, budget: int | None = None) -> Any:
    """The run's model, anchor weights loaded (see :func:`cpalgo.methods.build_method`)."""
    from cpalgo.methods import build_method
    from cpalgo.recipes import load_recipe

    recipe = load_recipe(grid.recipe)
    env = make_env(grid, recipe, seed)
    return build_method(method, grid.anchor, env, policy=recipe.policy,
                        algo_kwargs={**recipe.algo_kwargs, **dict(grid.overrides)},
                        settings=grid.method_settings.get(method, {}), budget=budget or grid.budget,
                        seed=seed, device=grid.device)


def _progress_callback(grid: GridConfig, spec: RunSpec, folder: Path, echo: Echo | None, start_wall: float,
                       wall_before: float) -> Any:
    from stable_baselines3.common.callbacks import BaseCallback

    class RunProgress(BaseCallback):
        """Per generation: a progress line and ``progress.json``; resumable checkpoints."""

        def __init__(self) -> None:
            super().__init__()
            self.saved_at = -1
            self.last = time.perf_counter()

        def _on_step(self) -> bool:
            return True

        def _on_rollout_start(self) -> None:
            gens = int(self.model.budget.generations)
            if gens > 0 and gens % grid.checkpoint_every == 0 and gens != self.saved_at:
                save_checkpoint(self.model, folder, wall_s=wall_before + time.perf_counter() - start_wall)
                self.saved_at = gens

        def _on_rollout_end(self) -> None:
            now = time.perf_counter()
            b = self.model.budget
            wall = wall_before + now - start_wall
            doc = {"run": spec.key, "generation": int(b.generations), "b_post": int(b.total),
                   "budget": grid.budget, "fraction": b.total / grid.budget, "wall_s": round(wall, 1),
                   "generation_s": round(now - self.last, 2)}
            write_json_atomic(folder / "progress.json", doc)
            if echo is not None:
                rate = b.total / max(wall, 1e-9)
                eta = max(grid.budget - b.total, 0) / max(rate, 1e-9)
                echo(f"[{spec.key}] generation {b.generations}: B_post {b.total:,}/{grid.budget:,} "
                     f"({100 * b.total / grid.budget:.0f}%), {now - self.last:.1f} s, eta {eta / 60:.1f} min")
            self.last = now

    return RunProgress()


def _readable_checkpoint(folder: Path, spec: RunSpec, echo: Echo | None) -> dict[str, Any] | None:
    """The budget state of the run's checkpoint (:func:`read_checkpoint`), or None when there
    is none. A checkpoint that does not open (a truncated zip, broken counters) or whose
    counters belong to another save is moved aside as ``checkpoint.corrupt.*`` and the run
    starts over from the anchor, with a line that says so."""
    zip_path, json_path = folder / "checkpoint.zip", folder / "checkpoint.json"
    try:
        return read_checkpoint(folder)
    except (ValueError, OSError, KeyError, zipfile.BadZipFile) as exc:
        for path in (zip_path, json_path):
            if path.is_file():
                path.replace(path.with_name(f"checkpoint.corrupt{path.suffix}"))
        if echo is not None:
            echo(f"[{spec.key}] checkpoint {zip_path} does not open ({exc}); moved aside, starting over")
        return None


def train_run(grid: GridConfig, spec: RunSpec, out: str | os.PathLike, echo: Echo | None = _echo) -> dict[str, Any]:
    """Post-train one (method, seed) to the grid's budget (resuming from its checkpoint when
    there is one); writes ``model.zip`` and ``train.json`` and returns the summary."""
    import torch

    from cpalgo.checkpoint import save_model_atomic

    folder = run_dir(out, spec)
    folder.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(grid.torch_threads)
    model = build_run_model(grid, spec.method, int(spec.seed))
    wall_before = 0.0
    resumed_from = None
    state = _readable_checkpoint(folder, spec, echo)
    if state is not None:
        model.set_parameters(str(folder / "checkpoint.zip"), exact_match=True, device=grid.device)
        if hasattr(model, "apply_legacy_settings"):  # a checkpoint older than a setting keeps its behaviour
            model.apply_legacy_settings(str(folder / "checkpoint.zip"))
        restore_budget_state(model, state)
        wall_before = float(state.get("wall_s", 0.0))
        resumed_from = int(model.budget.total)
        if echo is not None:
            echo(f"[{spec.key}] resuming at B_post {model.budget.total:,} (generation {model.budget.generations})")
    start = time.perf_counter()
    remaining = grid.budget - int(model.budget.total)
    if remaining > 0:
        callback = _progress_callback(grid, spec, folder, echo, start, wall_before)
        model.learn(remaining, callback=callback, reset_num_timesteps=resumed_from is None, progress_bar=False)
    wall = wall_before + time.perf_counter() - start
    save_model_atomic(model, folder / "model.zip")
    from cpalgo.viz import write_search_files  # CounterPlay's kept searches and a verified one's figure

    search_files = write_search_files(model, folder / "model.zip")
    summary = {
        "method": spec.method, "seed": spec.seed, "budget": grid.budget,
        "b_post": int(model.budget.total), "budget_totals": model.budget.as_dict(),
        "generations": int(model.budget.generations), "wall_s": round(wall, 1),
        "resumed_from": resumed_from,
        "totals": {name: dict(getattr(model, name)) for name in _totals_attributes(model)},
        "torch_threads": grid.torch_threads, "device": grid.device, "search_files": search_files,
    }
    write_json_atomic(folder / "train.json", summary)
    if echo is not None:
        echo(f"[{spec.key}] trained: B_post {model.budget.total:,} in {model.budget.generations} generations, "
             f"{wall / 60:.1f} min")
    model.env.close()
    return summary


# ----------------------------------------------------------------------------- evaluation
_EVALUATORS: dict[tuple, Any] = {}
_TASKS: dict[tuple, Any] = {}


def _tasks(grid: GridConfig, task_set: int) -> list[Any]:
    """The tasks of one task set, built once per process (a procedural pool takes tens of
    seconds; the evaluators of every deployment condition share them)."""
    from cpalgo.evaluate.runner import make_tasks

    e = grid.evaluation
    key = (e.pool, e.split_arg, e.tasks, task_set, e.pool_size)
    if key not in _TASKS:
        while len(_TASKS) >= 4:
            _TASKS.pop(next(iter(_TASKS)))
        _TASKS[key] = make_tasks(e.pool, e.split_arg, e.tasks, seed=task_set, pool_size=e.pool_size)
    return _TASKS[key]


def _evaluator(grid: GridConfig, deployment: str, task_set: int | None = None) -> Any:
    """One evaluator per (evaluation settings, deployment, task set) per process (the
    co-player models are built once and reused by every run this process evaluates; the
    simulator's memory keeps three at most, the tasks are kept apart by :func:`_tasks`)."""
    from cpalgo.evaluate.runner import EvalConfig, Evaluator

    e = grid.evaluation
    task_set = e.task_sets[0] if task_set is None else int(task_set)
    key = (json.dumps(grid.run_fingerprint()["evaluation"], sort_keys=True), grid.anchor, deployment,
           grid.torch_threads, grid.device, task_set)
    if key not in _EVALUATORS:
        tasks = _tasks(grid, task_set)
        config = EvalConfig(deploy_condition=deployment, max_worlds=e.max_worlds, max_agents=e.max_agents,
                            seed=task_set, device=grid.device, progress=False, torch_threads=grid.torch_threads,
                            coplayers=e.coplayers)
        # every run starts from the anchor: its action set gives the evaluation's dynamics
        ev = Evaluator(tasks, e.regimes, traffic_policy=e.traffic_policy or grid.anchor, bc_policy=e.bc_policy,
                       ppo_policy=e.ppo_policy, config=config, sim_config=dict(e.sim_config) if e.sim_config else None,
                       policies={"anchor": grid.anchor})
        while len(_EVALUATORS) >= 3:
            _EVALUATORS.pop(next(iter(_EVALUATORS)))
        _EVALUATORS[key] = ev
    return _EVALUATORS[key]


def evaluate_columns(grid: GridConfig, policy: Any, deployment: str, label: str,
                     task_set: int | None = None) -> dict[str, np.ndarray]:
    """Per task-regime columns of ``policy`` (model or checkpoint path) under ``deployment``
    on ``task_set`` (default: the grid's first)."""
    result = _evaluator(grid, deployment, task_set).run(policy, label)
    return {k: np.asarray(v) for k, v in result.columns.items()}


def _npz_bytes(columns: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **columns)
    return buf.getvalue()


def load_columns(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The evaluator columns of an ``eval_<deployment>.npz``; ``ValueError`` naming the file
    when it does not open (rerunning the grid evaluates it again)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (OSError, zipfile.BadZipFile, EOFError) as exc:
        raise ValueError(f"{path}: unreadable evaluation file ({exc}); rerun the grid to evaluate it again") from None


# ----------------------------------------------------------------------------- one task
def execute_run(grid: GridConfig, spec: RunSpec, out: str | os.PathLike, echo: Echo | None = _echo) -> dict[str, Any]:
    """Everything one grid task does: train (or resume) unless trained, then every missing
    evaluation. Returns ``{"run", "status", "files": {relative path: bytes}, "error"}``:
    the small result files, so that a driver on another machine can write them too."""
    import torch

    folder = run_dir(out, spec)
    folder.mkdir(parents=True, exist_ok=True)
    payload: dict[str, Any] = {"run": spec.key, "status": "done", "files": {}, "error": None}
    t0 = time.perf_counter()
    try:
        torch.set_num_threads(grid.torch_threads)
        status = run_status(grid, out, spec)
        if status == "done":
            payload["status"] = "skipped"
            return payload
        model: Any = None
        if spec.method != ANCHOR and status in ("new", "resume"):
            # they evaluated another model (every task set and deployment, those of the grid or not)
            for path in folder.glob("eval_*.npz"):
                path.unlink(missing_ok=True)
            train_run(grid, spec, out, echo)
        if spec.method != ANCHOR:
            model = str(folder / "model.zip")
            payload["files"][str(Path("runs") / spec.method / f"seed{spec.seed}" / "train.json")] = \
                (folder / "train.json").read_bytes()
        else:
            model = grid.anchor
        several = len(grid.evaluation.task_sets) > 1
        for task_set, deployment in _evaluations(grid, spec):
            target = eval_path(grid, folder, deployment, task_set)
            if not _readable(target):
                te = time.perf_counter()
                columns = evaluate_columns(grid, model, deployment, spec.method, task_set)
                write_bytes_atomic(target, _npz_bytes(columns))
                if echo is not None:
                    where = f" on task set {task_set}" if several else ""
                    echo(f"[{spec.key}] evaluated under {deployment}{where}: mean score "
                         f"{float(np.mean(columns['score'])):.1f} over {columns['score'].size} task-regimes "
                         f"({time.perf_counter() - te:.0f} s)")
            rel = target.relative_to(Path(out))
            payload["files"][str(rel)] = target.read_bytes()
        (folder / "error.txt").unlink(missing_ok=True)  # an earlier failure's traceback no longer applies
    except Exception as exc:  # noqa: BLE001 - one failed run must not stop the grid
        payload["status"] = "failed"
        payload["error"] = f"{type(exc).__name__}: {exc}"
        write_bytes_atomic(folder / "error.txt", traceback.format_exc().encode())
        if echo is not None:
            echo(f"[{spec.key}] FAILED: {payload['error']} (traceback in {folder / 'error.txt'})")
    payload["seconds"] = round(time.perf_counter() - t0, 1)
    sys.stdout.flush()
    return payload
