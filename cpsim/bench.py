"""Simulator benchmark: ``python -m cpsim.bench``.

Measures, single process, after compilation and a warm-up:

* stepping throughput in agent-steps/s = (live POLICY agents summed over steps) / seconds,
  observations and rewards included, random uniform actions, worlds reset as soon as they
  are done (as a training front-end does), for the procedural pool and the real WOMD files,
  at several batch sizes (policy agents at reset), with the default observation (K = 16,
  M = 64, jerk) and PufferDrive's sizes (K = 63, M = 200, classic dynamics). Both wall-clock
  and process-CPU rates are reported: on a shared machine the CPU rate is the better
  estimate of one idle core;
* snapshot + restore cost per world;
* real-data sanity: every agent on log replay in the WOMD files, the fraction of vehicles
  valid at t0 ever flagged colliding / off-road, at the logged box size and at
  ``box_scale`` = 0.7 (PufferDrive's reference setting).

The last line is ``agent_steps_per_s=<number>``: default configuration, 1,024 policy agents,
procedural pool, CPU, wall clock.
"""

from __future__ import annotations

import argparse
import json
import math
import os
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


def _slots(scenarios: Sequence[Any], cap: int = 64) -> int:
    """Agent slots: every agent valid at t0 of the busiest scenario, at most ``cap``."""
    return int(min(cap, max(int(s.log_valid[:, 0].sum()) for s in scenarios)))


def bench_steps(scenarios: Sequence[Any], policy_agents: int, config: dict, steps: int, device: str = "cpu",
                seed: int = 0, max_agents: int | None = None) -> dict[str, float]:
    """Step throughput for about ``policy_agents`` POLICY agents at reset (default controllers)."""
    import cpsim

    A = max_agents or _slots(scenarios)
    probe = cpsim.Simulator(scenarios, num_worlds=8, max_agents=A, config=config, device=device, seed=seed)
    per_world = float(np.mean([int(((probe._slot_table[g] >= 0) & (probe._ctrl_table[g] == 0)).sum())
                               for g in range(probe.num_scenarios)]))
    W = max(1, int(math.ceil(policy_agents / max(per_world, 1e-9))))
    sim = cpsim.Simulator(probe.model, num_worlds=W, max_agents=A, config=config, device=device, seed=seed)
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, sim.num_actions, size=(steps + 5, W, A)).astype(np.int32)

    def one(i: int) -> int:
        live = int(sim.policy_mask.sum())
        sim.step(actions[i])
        done = sim.world_done.cpu().numpy()
        if done.any():
            sim.reset(worlds=np.flatnonzero(done))
        return live

    for i in range(5):
        one(i)
    if device != "cpu":
        import warp as wp
        wp.synchronize_device(device)
    total = 0
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for i in range(5, steps + 5):
        total += one(i)
    if device != "cpu":
        import warp as wp
        wp.synchronize_device(device)
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
    rows.append({"worlds": "1 -> 6 broadcast", "us_per_call_pair": 1e6 * (time.perf_counter() - t0) / repeat,
                 "us_per_world": 1e6 * (time.perf_counter() - t0) / repeat / 6})
    return rows


def replay_sanity(path: Path, box_scale: float) -> dict[str, Any]:
    """Every agent on log replay for a whole episode; vehicles valid at t0 ever colliding / off-road."""
    import cpsim
    from cpsim.scenario import load

    sc = load(path)
    A = int(sc.log_valid[:, 0].sum())
    cfg = {"default_controller": "replay", "other_controller": "replay", "box_scale": box_scale}
    sim = cpsim.Simulator([sc], num_worlds=1, max_agents=A, config=cfg, seed=0)
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


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cpsim.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024, 4096],
                    help="policy agents at reset (default: 256 1024 4096)")
    ap.add_argument("--steps", type=int, default=60, help="measured steps per case (default 60)")
    ap.add_argument("--pool", type=int, default=32, help="procedural pool size (default 32)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda:N")
    ap.add_argument("--womd-dir", type=Path, default=DEFAULT_WOMD_DIR)
    ap.add_argument("--quick", action="store_true", help="1,024 agents, default config, 30 steps only")
    ap.add_argument("--json", type=Path, default=None, help="write all results to this JSON file")
    args = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from cpsim.scenario import pool

    results: dict[str, Any] = {"device": args.device, "cpus": os.cpu_count(),
                               "load_avg": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
    sources: dict[str, list] = {"procedural": pool(args.pool, 0)}
    womd_files = sorted(args.womd_dir.glob("*.json")) if args.womd_dir.is_dir() else []
    if womd_files and not args.quick:
        from cpsim.scenario import load

        sources["womd"] = [load(p) for p in womd_files]
    sizes = [1024] if args.quick else args.sizes
    steps = 30 if args.quick else args.steps
    configs = {k: v for k, v in CONFIGS.items() if not args.quick or not v}
    rows = []
    headline = None
    for src, scs in sources.items():
        for cname, cfg in configs.items():
            for n in sizes:
                r = bench_steps(scs, n, cfg, steps, device=args.device)
                r.update(source=src, config=cname, policy_agents=n)
                rows.append(r)
                print(f"{src:10s} {cname:32s} {n:6d} agents: {r['agent_steps_per_s_wall']:>12,.0f} /s wall "
                      f"{r['agent_steps_per_s_cpu']:>12,.0f} /s cpu  ({r['worlds']} worlds x {r['slots']} slots, "
                      f"live {r['mean_live_policy']:.0f})", flush=True)
                if src == "procedural" and not cfg and n == 1024:
                    headline = r["agent_steps_per_s_wall"]
    results["steps"] = rows
    print()
    print(_table(rows, ["source", "config", "policy_agents", "worlds", "slots", "mean_live_policy",
                        "ms_per_step", "agent_steps_per_s_wall", "agent_steps_per_s_cpu"]))
    if not args.quick:
        snap = bench_snapshot(sources["procedural"], device=args.device)
        results["snapshot"] = snap
        print()
        print(_table(snap, ["worlds", "us_per_call_pair", "us_per_world"]))
        sanity = [replay_sanity(p, s) for p in womd_files for s in (1.0, 0.7)]
        results["replay_sanity"] = sanity
        if sanity:
            print()
            print(_table(sanity, ["file", "box_scale", "vehicles", "colliding", "offroad", "colliding_frac",
                                  "offroad_frac"]))
    if headline is None:
        r = bench_steps(sources["procedural"], 1024, {}, steps, device=args.device)
        headline = r["agent_steps_per_s_wall"]
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
