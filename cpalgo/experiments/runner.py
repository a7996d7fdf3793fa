"""Run a grid: every (method, seed) post-training at the same B_post, evaluated under the
grid's deployment conditions, then the tables and plots.

Backends (``backend``):

* ``"ray"``: every run is one Ray task that declares the grid's ``resources``
  (``num_cpus``, ``num_gpus``). With ``address`` (``"auto"``, ``"ray://host:10001"``, ...)
  it joins that cluster; without one Ray starts locally on this machine. Workers write
  their files into ``out`` (a shared folder on a cluster) and also return the small result
  files (``train.json``, ``eval_*.npz``), which the driver writes where they are missing,
  so the tables are complete even when the workers' disks are not the driver's (only
  resuming a killed run needs the shared folder). Cluster nodes need this package
  installed (``pip install counterplay[cluster]``).
* ``"sequential"``: the runs one after another in this process.
* ``"auto"`` (default): Ray when it is installed or an address is given, else sequential.

A grid is resumable: run it again with the same ``out`` and finished runs are skipped,
runs with a checkpoint continue from it, missing evaluations are added. ``out`` keeps the
grid it was made for (``grid.json``); a grid whose runs would differ (anchor, recipe,
budget, settings, evaluation) is refused, while adding methods, seeds, deployment
conditions or task sets is fine. Task sets (``evaluation.seed: [0, 1]``): every run and the
anchor are evaluated on each, each evaluation a file of its own
(:func:`cpalgo.experiments.runs.eval_path`), so growing ``seed: 0`` to ``seed: [0, 1]``
evaluates the trained runs on task set 1 without training them again. The first task set
names the folder's unlabelled files and must stay first.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from cpalgo.experiments.grid import ANCHOR, GridConfig, GridError, RunSpec, load_grid
from cpalgo.experiments.runs import execute_run, run_dir, run_status, write_json_atomic
from cpsim.atomic import write_bytes_atomic

__all__ = ["run_experiment", "ExperimentResult", "BACKENDS", "ray_available"]

BACKENDS = ("auto", "ray", "sequential")
Echo = Callable[[str], None]


def _print(line: str) -> None:
    print(line, flush=True)


def ray_available() -> bool:
    """Whether the optional ``ray`` package (extra ``[cluster]``) is importable."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass
class ExperimentResult:
    """What :func:`run_experiment` did.

    Attributes:
        out: the results folder.
        backend: ``ray`` or ``sequential``.
        runs: run key -> ``done`` / ``skipped`` / ``failed``.
        errors: run key -> one-line error of the failed runs.
        wall_s: seconds of the whole call.
        files: tables and figures written (``results.csv``, ``tables.md``, ``*.png``).
    """

    out: Path
    backend: str
    runs: dict[str, str] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0
    files: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors


def _check_out(grid: GridConfig, out: Path) -> None:
    """``out`` must be new, or hold runs of a grid whose runs are the same."""
    if out.exists() and not out.is_dir():
        raise GridError(f"out: {out} exists and is not a folder")
    from cpsim.atomic import blocking_file

    blocker = blocking_file(out)
    if blocker is not None:
        raise GridError(f"out: {blocker} is a file, so {out} cannot be created")
    saved = out / "grid.json"
    if not saved.is_file():
        if (out / "runs").is_dir() and any((out / "runs").iterdir()):
            raise GridError(f"out: {out} holds runs but no grid.json (the record of the grid that made them); "
                            "use another --out")
        return
    try:
        previous = json.loads(saved.read_text())["fingerprint"]
    except (ValueError, KeyError):
        raise GridError(f"out: {saved} is not a grid record; use another --out") from None
    current = grid.run_fingerprint()
    for key in current:
        # the size may change when the same weights are re-saved; the weights' hash decides
        # (a record older than the hash has none, and keeps resuming)
        if key == "anchor_bytes" or (key == "anchor_weights_sha1" and key not in previous):
            continue
        if previous.get(key) != current[key]:
            before, now = previous.get(key), current[key]
            if (key == "evaluation" and isinstance(before, dict) and before.get("seed") != now.get("seed")
                    and {k: v for k, v in before.items() if k != "seed"} == {k: v for k, v in now.items() if k != "seed"}):
                raise GridError(f"out: {out} holds runs evaluated first on task set {before.get('seed')} "
                                f"(evaluation.seed differs: this grid's first is {now.get('seed')}); list "
                                f"{before.get('seed')} first (more task sets may follow it) or use another --out")
            raise GridError(f"out: {out} holds runs of another grid ({key} differs); use another --out "
                            "or the grid it was made with")


def _resolve_backend(backend: str, address: str | None) -> str:
    if backend not in BACKENDS:
        raise GridError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        backend = "ray" if (address or ray_available()) else "sequential"
    if backend == "ray" and not ray_available():
        raise GridError("backend: Ray is not installed (pip install 'counterplay[cluster]'), "
                        "or run with --backend sequential")
    if backend == "sequential" and address:
        raise GridError("address: a cluster address needs the Ray backend")
    return backend


class _GridProgress:
    """Grid-level progress lines and ``OUT/progress.json``."""

    def __init__(self, out: Path, total: int, skipped: int, echo: Echo | None) -> None:
        self.out, self.total, self.echo = out, total, echo
        self.finished = skipped
        self.failed = 0
        self.start = time.perf_counter()
        self.durations: list[float] = []

    def report(self, key: str, status: str, seconds: float | None, running: int, left: int | None = None) -> None:
        self.finished += 1
        self.failed += status == "failed"
        if seconds:
            self.durations.append(seconds)
        elapsed = time.perf_counter() - self.start
        left = self.total - self.finished if left is None else left
        eta = ""
        if self.durations and left:
            parallel = max(running, 1)
            eta = f", eta ~{left * (sum(self.durations) / len(self.durations)) / parallel / 60:.0f} min"
        line = (f"[grid] {self.finished}/{self.total} runs finished ({key}: {status}), {running} running, "
                f"{max(left - running, 0)} queued, {self.failed} failed, {elapsed / 60:.1f} min{eta}")
        write_json_atomic(self.out / "progress.json", {"finished": self.finished, "total": self.total,
                                                       "failed": self.failed, "running": running,
                                                       "elapsed_s": round(elapsed, 1), "last": key})
        if self.echo is not None:
            self.echo(line)


def _store_payload(out: Path, payload: Mapping[str, Any]) -> None:
    """Write the result files a worker returned where they are missing (another machine)."""
    for rel, data in payload.get("files", {}).items():
        target = out / rel
        if not target.is_file():
            write_bytes_atomic(target, data)


def _ray_execute(grid: GridConfig, spec: RunSpec, out: str, echo: bool) -> dict[str, Any]:
    """The Ray task body (module level, so that workers import it by name)."""
    return execute_run(grid, spec, out, _print if echo else None)


def _run_ray(grid: GridConfig, pending: list[RunSpec], out: Path, address: str | None, progress: _GridProgress,
             echo: Echo | None, result: ExperimentResult) -> None:
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": echo is not None,
                                  "ignore_reinit_error": True}
        if address:
            kwargs["address"] = address
        ray.init(**kwargs)
    try:
        res = grid.resources
        options: dict[str, Any] = {"num_cpus": res.get("num_cpus", 1), "num_gpus": res.get("num_gpus", 0),
                                   "max_retries": 0}
        if res.get("memory"):
            options["memory"] = res["memory"]
        task = ray.remote(_ray_execute).options(**options)
        refs = {task.remote(grid, spec, str(out), echo is not None): spec for spec in pending}
        # how many run at once: the cluster's CPUs (or GPUs) over what each task declares
        total = ray.cluster_resources()
        slots = int(total.get("CPU", 1) // max(options["num_cpus"], 1e-9)) if options["num_cpus"] else len(refs)
        if options["num_gpus"]:
            slots = min(slots, int(total.get("GPU", 0) // options["num_gpus"]))
        slots = max(slots, 1)
        if echo is not None:
            echo(f"[grid] {len(refs)} Ray tasks submitted ({options['num_cpus']:g} CPU, "
                 f"{options['num_gpus']:g} GPU each) to {address or 'a local Ray instance'}")
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=1)
            for ref in ready:
                spec = refs.pop(ref)
                try:
                    payload = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - a crashed worker fails its run only
                    payload = {"run": spec.key, "status": "failed", "files": {},
                               "error": f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"}
                _store_payload(out, payload)
                _record(result, payload)
                progress.report(spec.key, payload["status"], payload.get("seconds"), min(len(refs), slots),
                                len(refs))
    finally:
        if started_here:
            ray.shutdown()


def _record(result: ExperimentResult, payload: Mapping[str, Any]) -> None:
    result.runs[payload["run"]] = payload["status"]
    if payload["status"] == "failed":
        result.errors[payload["run"]] = payload.get("error") or "failed"


def run_experiment(config: str | os.PathLike | Mapping[str, Any] | GridConfig, out: str | os.PathLike, *,
                   address: str | None = None, backend: str = "auto", progress: bool = True,
                   tables: bool = True, echo: Echo | None = _print) -> ExperimentResult:
    """Run (or resume) every run of a grid and write its tables (see the module docstring).

    Args:
        config: grid file path (``zoo/experiments/...`` works anywhere), mapping or
            :class:`GridConfig`.
        out: results folder (created; reused to resume).
        address: Ray cluster address (``auto``, ``ray://...``); None starts Ray locally.
        backend: ``auto``, ``ray`` or ``sequential``.
        progress: print per-run and grid progress lines.
        tables: write ``results.csv``, ``tables.md`` and the plots at the end.
    Raises :class:`cpalgo.experiments.grid.GridError` (a ``ValueError``, one line naming the
    key) for a bad grid, backend or ``out`` before any run starts. Failed runs do not stop
    the others; they are listed in the result (and their traceback is in ``error.txt``).
    """
    grid = config if isinstance(config, GridConfig) else load_grid(config)
    out = Path(out)
    backend = _resolve_backend(backend, address)
    _check_out(grid, out)
    echo = echo if progress else None
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "grid.json", {"grid": grid.as_dict(), "fingerprint": grid.run_fingerprint()})
    if isinstance(config, (str, os.PathLike)):
        from cpalgo.experiments.grid import resolve_grid_path

        write_bytes_atomic(out / "grid.yml", Path(resolve_grid_path(config)).read_bytes())
    result = ExperimentResult(out=out, backend=backend)
    specs = grid.runs()
    pending, skipped = [], 0
    for spec in specs:
        status = run_status(grid, out, spec)
        if status == "done":
            result.runs[spec.key] = "skipped"
            skipped += 1
        else:
            pending.append(spec)
    grid_progress = _GridProgress(out, len(specs), skipped, echo)
    if echo is not None:
        states = {s.key: run_status(grid, out, s) for s in pending}
        resumed = sum(v == "resume" for v in states.values())
        sets = grid.evaluation.task_sets
        on_sets = f" on task sets {', '.join(map(str, sets))}" if len(sets) > 1 else ""
        echo(f"[grid] {grid.name}: {len(specs) - 1} runs ({len(grid.methods)} methods x {len(grid.seeds)} seeds) "
             f"+ the anchor's evaluations at B_post {grid.budget:,}{on_sets}; {skipped} already done, "
             f"{resumed} to resume, backend {backend}")
    if pending:
        if backend == "ray":
            _run_ray(grid, pending, out, address, grid_progress, echo, result)
        else:
            for spec in pending:
                payload = execute_run(grid, spec, out, echo)
                _record(result, payload)
                grid_progress.report(spec.key, payload["status"], payload.get("seconds"), 0)
    if tables:
        from cpalgo.experiments.tables import write_tables

        result.files = write_tables(out, grid)
    result.wall_s = time.perf_counter() - t0
    if echo is not None:
        echo(f"[grid] finished in {result.wall_s / 60:.1f} min: {sum(v != 'failed' for v in result.runs.values())}"
             f"/{len(specs)} ok; tables in {out / 'tables.md'}")
        for key, err in result.errors.items():
            echo(f"[grid] {key} failed: {err}")
    return result


def runs_of(grid: GridConfig, out: str | os.PathLike) -> dict[str, str]:
    """Run key -> status (``done``, ``evaluate``, ``resume``, ``new``) of every run of a grid."""
    return {spec.key: run_status(grid, out, spec) for spec in grid.runs()}


__all__ += ["runs_of", "run_dir", "ANCHOR"]
