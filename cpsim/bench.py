"""Simulator benchmark: ``python -m cpsim.bench``.

Measures, after compilation and a warm-up:

* stepping throughput in agent-steps/s = (live POLICY agents summed over steps) / seconds,
  observations and rewards included, random uniform actions, worlds reset as soon as they
  are done (as a training front-end does), for the procedural pool and real WOMD scenes, at
  1,024 / 4,096 / 16,384 policy agents at reset, with the default observation (K = 16,
  M = 64, jerk) and PufferDrive's sizes (K = 63, M = 200, classic dynamics). Both wall-clock
  and process-CPU rates are reported: on a shared machine the CPU rate is the better
  estimate of one idle core. Agents leave the scene at their goal, a collision or off-road
  (the default ``SimConfig``), so ``mean_live_policy`` is below the agents at reset and the
  rate counts live agents only. No ratio to another simulator is printed: a ratio needs the
  same scenes and the same events (live agents per step) on both sides, which a fixed
  number measured elsewhere does not give (BENCHMARKS.md has same-scene measurements);
* with ``--compare DIR`` (another checkout, e.g. ``git worktree add /tmp/base HEAD~1``):
  the same cases on both trees, each in its own worker process, interleaved over
  ``--rounds`` rounds (alternating which goes first), medians and the ratio new / DIR;
* snapshot + restore cost per world;
* real-data sanity: every agent on log replay in the WOMD files, the fraction of vehicles
  valid at t0 ever flagged colliding / off-road, at the logged box size and at
  ``box_scale`` = 0.7 (PufferDrive's reference setting).

WOMD scenes (``--womd-dir``, default ``../shared/data/womd``; skipped when absent):
``--womd-set pair`` (default) takes the folder's plain ``*.json`` files (the two scenes of
PufferDrive's own comparison), ``train`` / ``valid`` the ``.json.gz`` scenes of that
subfolder (at most ``--womd-max``).

The last line is ``agent_steps_per_s=<number>``: default configuration, 1,024 policy agents,
procedural pool, CPU, wall clock.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

DEFAULT_WOMD_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "womd"
CONFIGS: dict[str, dict[str, Any]] = {
    "default (K16 M64 jerk)": {},
    "pufferdrive (K63 M200 classic)": {"num_partners": 63, "num_road": 200, "dynamics": "classic"},
}
DEFAULT_SIZES = (1024, 4096, 16384)


def _slots(scenarios: Sequence[Any], cap: int = 64) -> int:
    """Agent slots: every agent valid at t0 of the busiest scenario, at most ``cap``."""
    return int(min(cap, max(int(s.log_valid[:, 0].sum()) for s in scenarios)))


def _live_policy(sim: Any) -> int:
    count = getattr(sim, "num_policy_agents", None)
    return int(count()) if count is not None else int(sim.policy_mask.sum())


def bench_steps(scenarios: Sequence[Any] | Any, policy_agents: int, config: dict, steps: int, device: str = "cpu",
                seed: int = 0, max_agents: int | None = None) -> dict[str, float]:
    """Step throughput for about ``policy_agents`` POLICY agents at reset (default controllers).

    ``scenarios``: a list of scenarios or a prebuilt ``cpsim.model.Model`` for ``config``.
    """
    import cpsim
    from cpsim.model import Model

    scs = scenarios.scenarios if isinstance(scenarios, Model) else scenarios
    A = max_agents or _slots(scs)
    probe = cpsim.Simulator(scenarios, num_worlds=1, max_agents=A, config=config, device=device, seed=seed)
    per_world = float(np.mean([int(((probe._slot_table[g] >= 0) & (probe._ctrl_table[g] == 0)).sum())
                               for g in range(probe.num_scenarios)]))
    W = max(1, int(math.ceil(policy_agents / max(per_world, 1e-9))))
    sim = cpsim.Simulator(probe.model, num_worlds=W, max_agents=A, config=config, device=device, seed=seed)
    del probe
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, sim.num_actions, size=(steps + 5, W, A)).astype(np.int32)
    sync = None
    if device != "cpu":
        import warp as wp

        def sync():
            wp.synchronize_device(device)

    def one(i: int) -> int:
        live = _live_policy(sim)
        sim.step(actions[i])
        done = sim.world_done.cpu().numpy()
        if done.any():
            sim.reset(worlds=np.flatnonzero(done))
        return live

    for i in range(5):
        one(i)
    if sync:
        sync()
    total = 0
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i in range(5, steps + 5):
        total += one(i)
    if sync:
        sync()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return {
        "worlds": W, "slots": A, "policy_at_reset": int(round(per_world * W)),
        "mean_live_policy": total / steps, "ms_per_step": 1e3 * wall / steps,
        "agent_steps_per_s_wall": total / wall, "agent_steps_per_s_cpu": total / max(cpu, 1e-9),
        "obs_size": sim.obs_layout.size,
    }


def bench_snapshot(scenarios: Sequence[Any], num_worlds: int = 256, repeat: int = 20,
                   device: str = "cpu") -> list[dict[str, float]]:
    """Cost of snapshot(n worlds) + restore(n worlds), and of a 1 -> 6 broadcast restore."""
    import cpsim

    sim = cpsim.Simulator(scenarios, num_worlds=num_worlds, max_agents=_slots(scenarios), device=device)
    for _ in range(5):
        sim.step(np.zeros((num_worlds, sim.max_agents), np.int32))
    rows = []
    for n in (1, 16, num_worlds):
        worlds = np.arange(n)
        snap = sim.snapshot(worlds)
        t0 = time.perf_counter()
        for _ in range(repeat):
            sim.snapshot(worlds, out=snap)
            sim.restore(snap, worlds)
        dt = (time.perf_counter() - t0) / repeat
        rows.append({"worlds": n, "us_per_call_pair": 1e6 * dt, "us_per_world": 1e6 * dt / n})
    root = sim.snapshot([0])
    t0 = time.perf_counter()
    for _ in range(repeat):
        sim.restore(root, np.arange(1, 7), source=np.zeros(6, np.int64))
    dt = (time.perf_counter() - t0) / repeat
    rows.append({"worlds": "1 -> 6 broadcast", "us_per_call_pair": 1e6 * dt, "us_per_world": 1e6 * dt / 6})
    return rows


def replay_sanity(path: Path, box_scale: float) -> dict[str, Any]:
    """Every agent on log replay for a whole episode; vehicles valid at t0 ever colliding / off-road
    (``track_all``: events between two replayed agents count too)."""
    import cpsim
    from cpsim.scenario import load

    sc = load(path)
    A = int(sc.log_valid[:, 0].sum())
    cfg = {"default_controller": "replay", "other_controller": "replay", "box_scale": box_scale}
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=A, config=cfg, seed=0, track_all=True)
    for _ in range(cfg.get("episode_steps", 91)):
        sim.step(np.zeros((1, A), np.int32))
    idx = sim.agent_index[0].numpy()
    vehicle = np.zeros(A, bool)
    vehicle[idx >= 0] = sc.agent_types[idx[idx >= 0]] == cpsim.AgentType.VEHICLE
    col = sim.metrics["first_collision_step"][0].numpy() >= 0
    off = sim.metrics["first_offroad_step"][0].numpy() >= 0
    n = int(vehicle.sum())
    return {"file": path.name, "box_scale": box_scale, "vehicles": n,
            "colliding": int((col & vehicle).sum()), "offroad": int((off & vehicle).sum()),
            "colliding_frac": float((col & vehicle).sum() / max(n, 1)),
            "offroad_frac": float((off & vehicle).sum() / max(n, 1))}


def _table(rows: list[dict], keys: Sequence[str]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:,.0f}" if abs(v) >= 100 else f"{v:.3g}"
        return str(v)

    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(out)


# ----------------------------------------------------------------------------- sources and workers
def womd_files(womd_dir: Path, womd_set: str, womd_max: int | None) -> list[Path]:
    """WOMD scene files of a set: ``pair`` = the folder's plain ``*.json`` files, ``train`` /
    ``valid`` = that subfolder's ``.json.gz`` (and ``.json``) files; [] when absent."""
    if not womd_dir.is_dir():
        return []
    if womd_set == "pair":
        files = sorted(womd_dir.glob("*.json"))
    else:
        sub = womd_dir / womd_set
        files = sorted(list(sub.glob("*.json.gz")) + list(sub.glob("*.json"))) if sub.is_dir() else []
    return files[:womd_max] if womd_max else files


def load_sources(pool_size: int, womd_dir: Path, womd_set: str, womd_max: int | None,
                 with_womd: bool = True) -> dict[str, list]:
    """{"procedural": pool(pool_size, 0), "womd": the WOMD set (when present and loadable)}."""
    from cpsim.scenario import load, pool

    sources: dict[str, list] = {"procedural": pool(pool_size, 0)}
    files = womd_files(womd_dir, womd_set, womd_max) if with_womd else []
    if files:
        try:
            sources["womd"] = [load(p) for p in files]
        except Exception as exc:  # e.g. a checkout without .json.gz support
            print(f"# WOMD set {womd_set!r} skipped: {type(exc).__name__}: {exc}", file=sys.stderr)
    return sources


class CaseRunner:
    """Runs benchmark cases on the ``cpsim`` importable in this process, one Model per
    (source, config) built once."""

    def __init__(self, sources: dict[str, list], device: str = "cpu"):
        self.sources = sources
        self.device = device
        self._models: dict[tuple[str, str], Any] = {}

    def run(self, source: str, config: str, n: int, steps: int) -> dict[str, Any]:
        from cpsim.config import SimConfig
        from cpsim.model import Model

        key = (source, config)
        if key not in self._models:
            self._models[key] = Model(self.sources[source], SimConfig.from_dict(CONFIGS[config]), self.device)
        r = bench_steps(self._models[key], n, CONFIGS[config], steps, device=self.device)
        r.update(source=source, config=config, policy_agents=n)
        return r


def _worker_main(args: argparse.Namespace) -> int:
    """``--worker``: answer one JSON case per stdin line with one JSON result line."""
    import warp as wp

    wp.config.quiet = True
    runner = CaseRunner(load_sources(args.pool, args.womd_dir, args.womd_set, args.womd_max), args.device)
    print(json.dumps({"ready": sorted(runner.sources)}), flush=True)
    for line in sys.stdin:
        case = json.loads(line)
        if case.get("source") not in runner.sources:
            print(json.dumps({"skipped": True}), flush=True)
            continue
        print(json.dumps(runner.run(case["source"], case["config"], case["n"], case["steps"]), default=float),
              flush=True)
    return 0


class Worker:
    """A ``--worker`` process running this file against the ``cpsim`` of ``tree``."""

    def __init__(self, tree: Path, args: argparse.Namespace):
        code = ("import runpy, sys; sys.path.insert(0, sys.argv[1]); sys.argv = [sys.argv[2]] + sys.argv[3:]; "
                "runpy.run_path(sys.argv[0], run_name='__main__')")
        cmd = [sys.executable, "-c", code, str(tree), str(Path(__file__).resolve()), "--worker",
               "--pool", str(args.pool), "--womd-dir", str(args.womd_dir), "--womd-set", args.womd_set,
               "--device", args.device]
        if args.womd_max:
            cmd += ["--womd-max", str(args.womd_max)]
        self.tree = tree
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=str(tree))
        self.sources = self._read()["ready"]

    def _read(self) -> dict:
        while True:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError(f"benchmark worker for {self.tree} exited (status {self.proc.wait()})")
            line = line.strip()
            if line.startswith("{"):
                return json.loads(line)

    def run(self, source: str, config: str, n: int, steps: int) -> dict[str, Any]:
        self.proc.stdin.write(json.dumps({"source": source, "config": config, "n": n, "steps": steps}) + "\n")
        self.proc.stdin.flush()
        return self._read()

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        self.proc.wait()


def _median_row(rows: list[dict]) -> dict[str, Any]:
    out = dict(rows[0])
    for k in ("mean_live_policy", "ms_per_step", "agent_steps_per_s_wall", "agent_steps_per_s_cpu"):
        out[k] = float(statistics.median(r[k] for r in rows))
    out["rounds"] = len(rows)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cpsim.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=list(DEFAULT_SIZES),
                    help="policy agents at reset (default: 1024 4096 16384)")
    ap.add_argument("--steps", type=int, default=60, help="measured steps per case (default 60)")
    ap.add_argument("--pool", type=int, default=32, help="procedural pool size (default 32)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda:N")
    ap.add_argument("--womd-dir", type=Path, default=DEFAULT_WOMD_DIR)
    ap.add_argument("--womd-set", default="pair", choices=["pair", "train", "valid"],
                    help="WOMD scenes: pair (the folder's plain .json files, default), train, valid")
    ap.add_argument("--womd-max", type=int, default=None, help="at most this many WOMD scenes")
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS), metavar="CONFIG",
                    help=f"configurations (default: all of {list(CONFIGS)})")
    ap.add_argument("--compare", type=Path, default=None,
                    help="another checkout: run every case on both, interleaved, and report new / base")
    ap.add_argument("--rounds", type=int, default=3, help="rounds per case with --compare (default 3)")
    ap.add_argument("--quick", action="store_true", help="1,024 agents, default config, 30 steps only")
    ap.add_argument("--no-extras", action="store_true", help="skip the snapshot and replay-sanity tables")
    ap.add_argument("--json", type=Path, default=None, help="write all results to this JSON file")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return _worker_main(args)
    import warp as wp

    wp.config.quiet = True
    results: dict[str, Any] = {"device": args.device, "cpus": os.cpu_count(), "argv": sys.argv[1:],
                               "load_avg_start": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
    sizes = [1024] if args.quick else args.sizes
    steps = 30 if args.quick else args.steps
    configs = [c for c in args.configs if not args.quick or not CONFIGS[c]]
    here = Path(__file__).resolve().parents[1]
    if args.compare is not None:
        new, base = Worker(here, args), Worker(args.compare.resolve(), args)
        names = [s for s in new.sources if s in base.sources]
    else:
        sources = load_sources(args.pool, args.womd_dir, args.womd_set, args.womd_max, with_womd=not args.quick)
        runner = CaseRunner(sources, args.device)
        names = list(sources)
    rows, base_rows = [], []
    headline = None
    for src in names:
        for cname in configs:
            for n in sizes:
                if args.compare is None:
                    r = runner.run(src, cname, n, steps)
                    rows.append(r)
                    print(f"{src:10s} {cname:32s} {n:6d} agents: {r['agent_steps_per_s_wall']:>12,.0f} /s wall "
                          f"{r['agent_steps_per_s_cpu']:>12,.0f} /s cpu  ({r['worlds']} worlds x {r['slots']} slots, "
                          f"live {r['mean_live_policy']:.0f})", flush=True)
                else:
                    got: dict[str, list] = {"new": [], "base": []}
                    for k in range(args.rounds):
                        order = (("new", new), ("base", base)) if k % 2 == 0 else (("base", base), ("new", new))
                        for label, worker in order:
                            got[label].append(worker.run(src, cname, n, steps))
                    r, b = _median_row(got["new"]), _median_row(got["base"])
                    r["base_agent_steps_per_s_cpu"] = b["agent_steps_per_s_cpu"]
                    r["base_agent_steps_per_s_wall"] = b["agent_steps_per_s_wall"]
                    r["ratio_cpu"] = r["agent_steps_per_s_cpu"] / b["agent_steps_per_s_cpu"]
                    r["ratio_wall"] = r["agent_steps_per_s_wall"] / b["agent_steps_per_s_wall"]
                    r["all_new"], r["all_base"] = got["new"], got["base"]
                    rows.append(r)
                    base_rows.append(b)
                    print(f"{src:10s} {cname:32s} {n:6d} agents: new {r['agent_steps_per_s_cpu']:>10,.0f} /s cpu "
                          f"{r['agent_steps_per_s_wall']:>10,.0f} wall | base {b['agent_steps_per_s_cpu']:>10,.0f} cpu "
                          f"{b['agent_steps_per_s_wall']:>10,.0f} wall | x{r['ratio_cpu']:.2f} cpu "
                          f"x{r['ratio_wall']:.2f} wall", flush=True)
                if src == "procedural" and not CONFIGS[cname] and n == 1024:
                    headline = r["agent_steps_per_s_wall"]
    if args.compare is not None:
        new.close()
        base.close()
    results["steps"] = rows
    results["load_avg_end"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    print()
    keys = ["source", "config", "policy_agents", "worlds", "slots", "mean_live_policy", "ms_per_step",
            "agent_steps_per_s_wall", "agent_steps_per_s_cpu"]
    if args.compare is not None:
        keys += ["base_agent_steps_per_s_cpu", "ratio_cpu", "ratio_wall"]
    print(_table(rows, keys))
    print()
    print("agent-steps/s count live policy agents (mean_live_policy per step); no ratio to another simulator "
          "is given, as one needs the same scenes and the same live agents on both sides (BENCHMARKS.md)")
    if not args.quick and not args.no_extras:
        from cpsim.scenario import pool

        snap = bench_snapshot(pool(args.pool, 0), device=args.device)
        results["snapshot"] = snap
        print()
        print(_table(snap, ["worlds", "us_per_call_pair", "us_per_world"]))
        files = womd_files(args.womd_dir, "pair", None)
        sanity = [replay_sanity(p, s) for p in files for s in (1.0, 0.7)]
        results["replay_sanity"] = sanity
        if sanity:
            print()
            print(_table(sanity, ["file", "box_scale", "vehicles", "colliding", "offroad", "colliding_frac",
                                  "offroad_frac"]))
    if headline is None:
        from cpsim.scenario import pool

        headline = bench_steps(pool(args.pool, 0), 1024, {}, steps, device=args.device)["agent_steps_per_s_wall"]
    results["agent_steps_per_s"] = headline
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=args.json.parent, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            json.dump(results, f, indent=1, default=str)
        os.replace(tmp, args.json)
    print(f"agent_steps_per_s={headline:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
