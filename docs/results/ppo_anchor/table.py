"""Item-3 numbers of the anchor issue for each candidate, per task set and pooled.

    python docs/results/ppo_anchor/table.py

Reads ``summary_{normal,aggressive}[_seed1].csv`` (``cpalgo.evaluate`` outputs: 100 tasks per
split, 8 regimes, the candidate as its own traffic; ``--seed 0`` and ``--seed 1``, for the
shipped anchor also ``--seed 2`` and ``--seed 3``) from the candidate folders below and prints,
per split (Interactive / Random), the normal-deployment score, at-fault and timeout shares and
the aggressive-minus-normal completion gap, per task set and pooled over the first two sets
(and, where there are more, over all of them).
"""
import csv
import os

HERE = os.path.dirname(os.path.abspath(__file__))
TV5 = os.path.join(HERE, "..", "teacher_v5")
# candidate -> per task set, (folder, file-name suffix) of its summary_{deployment}{suffix}.csv
CANDIDATES = {
    "I9F (shipped)": [(os.path.join(TV5, "I9F"), ""), (os.path.join(TV5, "I9F_seed1"), ""),
                      (os.path.join(TV5, "I9F_seed2"), ""), (os.path.join(TV5, "I9F_seed3"), "")],
    # the same anchor on the tasks the evaluator has kept since the eleventh sitting (scenes
    # whose ego log reaches its goal; docs/results/README.md, "Tasks no log completes")
    "I9F (shipped), log-feasible tasks": [(os.path.join(HERE, "..", "feasible_tasks", f"I9F_seed{s}"), "")
                                          for s in range(4)],
    **{name: [(os.path.join(HERE, name), ""), (os.path.join(HERE, name), "_seed1")]
       for name in ("C75", "C150", "P150", "W50", "C75_D2", "T_c2.0", "T_c0.5", "G_I9F_n2.0",
                    "G_C150_a1.3")},
}
REGIMES = ["idm", "selfplay", "bc", "replay", "aggressive", "normal", "cautious", "mix"]
SPLITS = ("interactive", "random")


def load(folder, suffix, dep):
    path = os.path.join(folder, f"summary_{dep}{suffix}.csv")
    if not os.path.exists(path):
        return None
    return {(r["split"], r["regime"], r["metric"]): float(r["mean"]) for r in csv.DictReader(open(path))}


def mean(t, split, metric):
    return 100 * sum(t[(split, g, metric)] for g in REGIMES) / len(REGIMES)


def row(normal, aggressive):
    cells = []
    for key in ("score", "at_fault_collision", "timeout"):
        scale = 0.01 if key == "score" else 1
        cells.append(" / ".join(f"{scale * mean(normal, s, key):.1f}" for s in SPLITS))
    cells.append(" / ".join(f"{mean(aggressive, s, 'completion') - mean(normal, s, 'completion'):+.1f}"
                            for s in SPLITS) if aggressive else "-")
    return cells


print("| candidate | task set | normal score | at-fault % | timeout % | aggressive − normal completion |")
print("|---|---|---|---|---|---|")
for name, folders in CANDIDATES.items():
    sets = []
    for task_set, (folder, suffix) in enumerate(folders):
        n, a = load(folder, suffix, "normal"), load(folder, suffix, "aggressive")
        if n is None:
            continue
        sets.append((n, a))
        print(f"| {name} | {task_set + 1} | " + " | ".join(row(n, a)) + " |")
    for count, label in ((2, "pooled"), (4, "pooled 1-4")):
        if len(sets) >= count and all(a for _, a in sets[:count]) and (count == 2 or len(sets) == 4):
            pooled_n = {k: sum(n[k] for n, _ in sets[:count]) / count for k in sets[0][0]}
            pooled_a = {k: sum(a[k] for _, a in sets[:count]) / count for k in sets[0][1]}
            print(f"| {name} | {label} | " + " | ".join(row(pooled_n, pooled_a)) + " |")
