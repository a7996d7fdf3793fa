"""Issue-12 item-3 numbers from eval dirs: python summ.py DIR"""
import csv
import os
import sys

d = sys.argv[1]
def load(dep):
    p = os.path.join(d, f"procedural_{dep}", "summary.csv")
    if not os.path.exists(p):
        return None
    out = {}
    for r in csv.DictReader(open(p)):
        out[(r["split"], r["regime"], r["metric"])] = float(r["mean"])
    return out
res = {dep: load(dep) for dep in ("normal", "aggressive", "cautious")}
regimes = ["idm","selfplay","bc","replay","aggressive","normal","cautious","mix"]
def mean(t, split, metric): return sum(t[(split, g, metric)] for g in regimes) / len(regimes)
for split in ("interactive", "random"):
    n = res["normal"]
    if n is None:
        continue
    print(split, "normal: score %.1f completion %.1f at-fault %.1f offroad %.1f timeout %.1f" % (
        mean(n, split, "score"), 100*mean(n, split, "completion"), 100*mean(n, split, "at_fault_collision"),
        100*mean(n, split, "offroad"), 100*mean(n, split, "timeout")))
    if res["aggressive"]:
        print("   aggressive - normal completion %+.1f" % (100*(mean(res["aggressive"], split, "completion") - mean(n, split, "completion"))))
    if res["cautious"]:
        print("   cautious at-fault %.1f vs normal %.1f" % (100*mean(res["cautious"], split, "at_fault_collision"), 100*mean(n, split, "at_fault_collision")))
    print("   traffic a/n/c completion %.0f/%.0f/%.0f" % tuple(100*n[(split, g, "completion")] for g in ("aggressive","normal","cautious")))
