"""Where an evaluated policy fails: failure classes per scenario family and per traffic regime.

    python scripts/failure_table.py RUN/seed0/procedural_normal RUN/seed1/procedural_normal ...

Reads the evaluator's ``tasks.csv`` (one row per task-regime) of every folder given (task sets
are pooled) and prints two Markdown tables per split, in % of task-regimes: the family (the
procedural scenario id's prefix, e.g. ``intersection``) and the regime against completion,
at-fault collision, non-at-fault collision, off-road and timeout.
"""
from __future__ import annotations

import csv
import os
import sys
from collections import defaultdict

CLASSES = ("goal", "at_fault_collision", "non_at_fault_collision", "offroad", "timeout")


def read_rows(folders: list[str]) -> list[dict[str, str]]:
    rows: list[dict[str, str]] = []
    for folder in folders:
        path = os.path.join(folder, "tasks.csv")
        if not os.path.isfile(path):
            raise SystemExit(f"{path}: no such file (give folders the evaluator wrote)")
        with open(path, newline="") as fh:
            rows.extend(csv.DictReader(fh))
    return rows


def table(rows: list[dict[str, str]], key) -> str:
    groups: dict[str, list[dict[str, str]]] = defaultdict(list)
    for row in rows:
        groups[key(row)].append(row)
    lines = ["| | task-regimes | completion | at-fault coll. | other coll. | off-road | timeout |",
             "|---|---|---|---|---|---|---|"]
    for name in sorted(groups):
        group = groups[name]
        rates = [100 * sum(float(r[c]) for r in group) / len(group) for c in CLASSES]
        lines.append(f"| {name} | {len(group)} | " + " | ".join(f"{v:.1f}" for v in rates) + " |")
    return "\n".join(lines)


def main(folders: list[str]) -> None:
    if not folders:
        raise SystemExit(__doc__)
    rows = read_rows(folders)
    for split in sorted({r["split"] for r in rows}):
        part = [r for r in rows if r["split"] == split]
        print(f"### {split}: by family\n\n{table(part, lambda r: r['scenario_id'].rsplit('-', 1)[0])}\n")
        print(f"### {split}: by regime\n\n{table(part, lambda r: r['regime'])}\n")


if __name__ == "__main__":
    main(sys.argv[1:])
