"""``counterplay pool``: generate and summarise a procedural scenario pool."""

from __future__ import annotations

import argparse
import time

from cpalgo.common.checks import UsageError

__all__ = ["cmd_pool"]


def cmd_pool(args: argparse.Namespace) -> int:
    from cpsim.scenario import FAMILIES, pool

    families = args.families or None
    if families:
        unknown = sorted(set(families) - set(FAMILIES))
        if unknown:
            raise UsageError(f"--families: unknown {unknown}; accepted: {list(FAMILIES)}")
    t0 = time.perf_counter()
    scenarios = pool(args.n, args.seed, families=families)
    dt = time.perf_counter() - t0
    by_family: dict[str, list] = {}
    for s in scenarios:
        by_family.setdefault(s.family, []).append(s)
    print(f"{len(scenarios)} scenarios generated in {dt:.2f} s ({len(scenarios) / dt:.0f}/s), seed {args.seed}")
    print(f"{'family':<14}{'count':>6}{'agents':>8}{'controllable':>14}{'roads':>7}{'ego goal m':>12}")
    for fam, group in sorted(by_family.items()):
        sums = [s.summary() for s in group]

        def mean(key: str, sums: list = sums) -> float:
            return sum(x[key] for x in sums) / len(sums)

        print(f"{fam:<14}{len(group):>6}{mean('agents'):>8.1f}{mean('controllable'):>14.1f}"
              f"{mean('roads'):>7.0f}{mean('ego_goal_distance_m'):>12.1f}")
    return 0
