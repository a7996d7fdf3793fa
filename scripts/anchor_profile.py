"""An anchor's profile numbers, pooled over its task sets.

    python scripts/anchor_profile.py docs/results/anchor/seed{0,1,2,3}

Each folder holds ``summary_{normal,aggressive,cautious}.csv`` (``cpalgo.evaluate`` outputs of
one task set: 100 tasks per split, 8 regimes, the candidate as its own traffic, one deployment
each; ``scripts/eval_anchor.sh`` writes them). Task sets have equally many tasks, so the pooled value is the mean over sets. Prints,
per split (Interactive / Random): the normal deployment's score, at-fault, non-at-fault and
timeout shares; aggressive − normal completion; cautious against normal at-fault; and, for
the normal ego, the aggressive / normal / cautious traffic regimes' completion, collisions
caused by the co-players (non-at-fault) and co-player harm (other vehicles collided or
off-road per task), with the largest gap between them.
"""
import csv
import os
import sys

REGIMES = ["idm", "selfplay", "bc", "replay", "aggressive", "normal", "cautious", "mix"]
SPLITS = ("interactive", "random")
TRAFFIC = ("aggressive", "normal", "cautious")


def load(folder: str, deployment: str) -> dict | None:
    path = os.path.join(folder, f"summary_{deployment}.csv")
    if not os.path.exists(path):
        return None
    return {(r["split"], r["regime"], r["metric"]): float(r["mean"]) for r in csv.DictReader(open(path))}


def pooled(folders: list[str], deployment: str) -> dict | None:
    tables = [load(f, deployment) for f in folders]
    if any(t is None for t in tables):
        return None
    return {k: sum(t[k] for t in tables) / len(tables) for k in tables[0]}


def over_regimes(t: dict, split: str, metric: str) -> float:
    return sum(t[(split, g, metric)] for g in REGIMES) / len(REGIMES)


def main(folders: list[str]) -> None:
    if not folders:
        raise SystemExit("usage: anchor_profile.py FOLDER... (each with summary_{normal,aggressive,cautious}.csv)")
    n, a, c = (pooled(folders, d) for d in ("normal", "aggressive", "cautious"))
    if n is None:
        raise SystemExit(f"a folder of {folders} has no summary_normal.csv")
    print(f"{len(folders)} task set(s), Interactive / Random")

    def both(fn, fmt="{:.1f}") -> str:
        return " / ".join(fmt.format(fn(s)) for s in SPLITS)

    print("normal score                  ", both(lambda s: over_regimes(n, s, "score")))
    for key in ("completion", "at_fault_collision", "non_at_fault_collision", "timeout", "offroad"):
        print(f"normal {key:<23}", both(lambda s, k=key: 100 * over_regimes(n, s, k)), "%")
    if a is not None:
        print("aggressive - normal           ", both(lambda s: 100 * (over_regimes(a, s, "completion")
                                                            - over_regimes(n, s, "completion")), "{:+.1f}"))
    if c is not None:
        print("cautious at-fault             ", both(lambda s: 100 * over_regimes(c, s, "at_fault_collision")),
              "% (normal", both(lambda s: 100 * over_regimes(n, s, "at_fault_collision")) + ")")
    for key, scale, unit in (("completion", 100, "%"), ("non_at_fault_collision", 100, "%"),
                             ("co_player_harm", 1, "vehicles / task")):
        for s in SPLITS:
            vals = [scale * n[(s, g, key)] for g in TRAFFIC]
            print(f"traffic a/n/c {key:<23} {s:<11}", " / ".join(f"{v:.2f}" for v in vals),
                  unit, f"(largest gap {max(vals) - min(vals):.2f})")


if __name__ == "__main__":
    main(sys.argv[1:])
