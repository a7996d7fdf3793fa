"""Per-regime table of evaluator summary.csv files (long format: policy, split, regime, metric,
mean, ...), no pandas: ``python docs/results/pairs/regimes.py SUMMARY.csv [...]``.

Prints score and completion / at-fault / off-road / timeout in percent for each split and
traffic regime, and their mean over the regimes."""
import csv
import sys
from collections import defaultdict

METRICS = ("score", "completion", "at_fault_collision", "offroad", "timeout")

for path in sys.argv[1:]:
    table: dict = defaultdict(dict)
    with open(path) as f:
        for row in csv.DictReader(f):
            if row["metric"] in METRICS:
                value = float(row["mean"])
                table[(row["split"], row["regime"])][row["metric"]] = value if row["metric"] == "score" else 100 * value
    print(path)
    print(f"{'split':<12} {'regime':<22}" + "".join(f"{m[:10]:>11}" for m in METRICS))
    for split in sorted({s for s, _ in table}):
        keys = sorted(k for k in table if k[0] == split and k[1] != "mean")
        for key in keys:
            print(f"{split:<12} {key[1]:<22}" + "".join(f"{table[key].get(m, float('nan')):11.1f}" for m in METRICS))
        means = [sum(table[k].get(m, 0.0) for k in keys) / len(keys) for m in METRICS]
        print(f"{split:<12} {'MEAN':<22}" + "".join(f"{v:11.1f}" for v in means))
