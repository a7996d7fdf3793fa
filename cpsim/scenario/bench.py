"""Scenario benchmarks: ``python -m cpsim.scenario.bench``.

1. Procedural generation: scenarios generated per second for each family (wall clock and
   process CPU time, one process, seeds from the training range), with the mean number of
   agents and road points.
2. WOMD loading (when ``cpsim.scenario.womd`` is present and the data folder exists):
   ``load(json)`` vs ``load(npz cache)`` for each JSON file, best of ``--repeat`` runs,
   the cache written with ``convert_dir`` into a temporary folder.

Options: ``--seconds S`` time budget per family (default 2), ``--families a,b``,
``--womd DIR`` (default ``../shared/data/womd`` next to the repository), ``--repeat K``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from cpsim.scenario import procedural

DEFAULT_WOMD = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "womd"


def bench_generation(families: Sequence[str], seconds: float, first_seed: int = 0) -> list[dict]:
    """Generate scenarios of each family for about ``seconds`` (at least 3 per family)."""
    rows = []
    for family in families:
        procedural.generate(family, 10 ** 6)          # warm-up (imports, allocator)
        count, agents, points = 0, [], []
        wall0, cpu0 = time.perf_counter(), time.process_time()
        while count < 3 or time.perf_counter() - wall0 < seconds:
            s = procedural.generate(family, first_seed + count)
            agents.append(s.num_agents)
            points.append(s.road_points.shape[0])
            count += 1
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        rows.append({"family": family, "scenarios": count, "per_s": count / wall, "ms_wall": 1e3 * wall / count,
                     "ms_cpu": 1e3 * cpu / count, "agents": float(np.mean(agents)),
                     "road_points": float(np.mean(points))})
    return rows


def bench_womd(folder: Path, repeat: int) -> list[dict] | str:
    """Best-of-``repeat`` JSON and (compressed) cache load times per file, or why it was skipped."""
    from cpsim.scenario.womd import bench_load

    if not folder.is_dir() or not any(folder.glob("*.json")):
        return f"skipped: no WOMD JSON files in {folder}"
    return [{**r, "cache_ms": r["npz_ms"], "cache_kb": r["npz_kb"]} for r in bench_load(folder, repeat)]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cpsim.scenario.bench", description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="time budget per family (s)")
    parser.add_argument("--families", default=",".join(procedural.FAMILIES))
    parser.add_argument("--womd", type=Path, default=DEFAULT_WOMD)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    families = [f for f in args.families.split(",") if f]
    for f in families:
        if f not in procedural.FAMILIES:
            parser.error(f"unknown family {f!r}; expected some of {procedural.FAMILIES}")
    print(f"machine: {platform.machine()} {os.cpu_count()} cores, python {platform.python_version()}, "
          f"numpy {np.__version__}")
    print("\nprocedural generation (one process)")
    print(f"{'family':<14} {'scen':>5} {'scen/s':>7} {'ms wall':>8} {'ms cpu':>7} {'agents':>7} {'points':>7}")
    for r in bench_generation(families, args.seconds):
        print(f"{r['family']:<14} {r['scenarios']:5d} {r['per_s']:7.1f} {r['ms_wall']:8.1f} {r['ms_cpu']:7.1f} "
              f"{r['agents']:7.1f} {r['road_points']:7.0f}")
    print(f"\nWOMD JSON vs cache ({args.womd})")
    rows = bench_womd(args.womd, max(1, args.repeat))
    if isinstance(rows, str):
        print(rows)
    else:
        print(f"{'file':<36} {'agents':>6} {'json ms':>8} {'cache ms':>8} {'speed-up':>8} {'json KB':>8} {'cache KB':>8}")
        for r in rows:
            print(f"{r['file']:<36} {r['agents']:6d} {r['json_ms']:8.2f} {r['cache_ms']:8.2f} "
                  f"{r['json_ms'] / max(r['cache_ms'], 1e-9):8.1f} {r['json_kb']:8.0f} {r['cache_kb']:8.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
