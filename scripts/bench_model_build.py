"""Time building a simulator's static model (cpsim.model.Model, host arrays and upload) for
the anchor run's segment pool: the WOMD training scenes and a procedural training pool.

usage: python scripts/bench_model_build.py [--womd DIR] [--pool N] [--repeat R] [--dynamics D]
Prints one JSON line: best-of-R seconds per pool, and the procedural pool's drawing time.
"""

from __future__ import annotations

import argparse
import json
import time

from cpsim.config import SimConfig
from cpsim.model import Model
from cpsim.scenario import load_dir, train_pool


def best_of(repeat: int, fn) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--womd", default="../shared/data/womd/train")
    ap.add_argument("--pool", type=int, default=512)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--dynamics", default="classic")
    args = ap.parse_args()
    cfg = SimConfig(dynamics=args.dynamics)
    womd = list(load_dir(args.womd)[0])
    t = time.perf_counter()
    procedural = list(train_pool(args.pool, 1))
    draw_s = time.perf_counter() - t
    out = {"dynamics": args.dynamics, f"womd_{len(womd)}_s": best_of(args.repeat, lambda: Model(womd, cfg)),
           f"procedural_{args.pool}_s": best_of(args.repeat, lambda: Model(procedural, cfg)),
           f"draw_procedural_{args.pool}_s": draw_s}
    print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in out.items()}))


if __name__ == "__main__":
    main()
