"""Completion, timeouts and at-fault collisions per scene family, from evaluator task rows.

    python docs/results/parked_fix/families.py runs/tv10/evJ16/s0 runs/tv10/evJ16/s1 ...

Each folder holds ``procedural_{normal,aggressive,cautious}/tasks.csv`` (``cpalgo.evaluate
--out``); rows of all folders and all 8 regimes are pooled per split, family and deployment.
"""
import collections
import csv
import os
import sys

counts = collections.defaultdict(lambda: [0, 0, 0, 0])   # task-regimes, goal, timeout, at-fault
for folder in sys.argv[1:]:
    for dep in ("normal", "aggressive", "cautious"):
        path = os.path.join(folder, f"procedural_{dep}", "tasks.csv")
        if not os.path.exists(path):
            continue
        for r in csv.DictReader(open(path)):
            c = counts[(r["split"], r["scenario_id"].split("-")[0], dep)]
            c[0] += 1
            c[1] += int(r["goal"])
            c[2] += int(r["timeout"])
            c[3] += int(r["at_fault_collision"])
print("split | family | deployment | task-regimes | completion % | timeout % | at-fault %")
for key in sorted(counts):
    n, goal, timeout, fault = counts[key]
    print(" | ".join(key) + f" | {n} | {100 * goal / n:.1f} | {100 * timeout / n:.1f} | {100 * fault / n:.1f}")
