"""How far each retry of a search drives from its factual branch: the largest distance between the
focal agent's position in a candidate branch and in the factual branch (same decision, m, over
the decisions where it drives in both), per panel style, over the searches a CounterPlay run
kept beside its checkpoint.

    python docs/results/anchor_failures/branch_spread.py runs/core_shipped/runs/counterplay/seed*/model.searches.npz

Also prints the root depth (decisions between the root and the failure) quartiles.
"""

from __future__ import annotations

import collections
import json
import sys

import numpy as np


def main(paths: list[str]) -> None:
    spread: dict[str, list[float]] = collections.defaultdict(list)
    depths: list[int] = []
    for path in paths:
        data = np.load(path, allow_pickle=True)
        meta = json.loads(str(data["meta"]))
        for i, rec in enumerate(meta["records"]):
            depths.append(rec["failure_step"] - rec["root_step"])
            focal = rec["focal"]
            factual = data[f"r{i}.b0.xy"][:, focal]
            factual_valid = data[f"r{i}.b0.valid"][:, focal]
            for j, branch in enumerate(rec["branches"]):
                if branch["kind"] != "candidate":
                    continue
                xy = data[f"r{i}.b{j}.xy"][:, focal]
                # a branch ends when its last deciding agent does; the focal agent may be
                # removed (goal, collision) earlier: compare the steps it drives in both
                n = min(len(xy), len(factual))
                both = data[f"r{i}.b{j}.valid"][:n, focal] & factual_valid[:n]
                dist = np.linalg.norm(xy[:n] - factual[:n], axis=-1)[both]
                spread[branch["name"]].append(float(dist.max()) if dist.size else 0.0)
    print(f"{len(depths)} searches; root depth quartiles {np.percentile(depths, [25, 50, 75]).tolist()} decisions")
    for name, values in spread.items():
        v = np.asarray(values)
        print(f"{name:>18}: identical to the factual branch {np.mean(v < 1e-3):.0%}, largest deviation "
              f"median {np.median(v):.2f} m, 75th percentile {np.percentile(v, 75):.2f} m, max {v.max():.1f} m")


if __name__ == "__main__":
    main(sys.argv[1:])
