"""Why completed retries are not admissible: a breakdown over the searches a CounterPlay run kept.

    python docs/results/anchor_failures/admission.py runs/root_depth/runs/cp-fixed-30/seed0/model.searches.npz ...

For every candidate branch that completed its task it reports whether it was admissible, and
if not, whether the factual branch of the same search also completed (then the retry has to
outrank it: earlier arrival, fewer events) or the candidate harmed another vehicle (the
remaining cases: the search's per-vehicle test).
"""

from __future__ import annotations

import json
import sys

import numpy as np


def main(paths: list[str]) -> None:
    for path in paths:
        meta = json.loads(str(np.load(path, allow_pickle=True)["meta"]))
        searches = completed = admissible = factual_goal = other = 0
        for rec in meta["records"]:
            searches += 1
            branches = rec["branches"]
            factual = next(b for b in branches if b["kind"] == "factual")
            for b in branches:
                if b["kind"] != "candidate" or b["outcome"] != "goal":
                    continue
                completed += 1
                if b["admissible"]:
                    admissible += 1
                elif factual["outcome"] == "goal":
                    factual_goal += 1
                else:
                    other += 1
        print(f"{path}: {searches} searches, {completed} completed candidates: {admissible} admissible, "
              f"{factual_goal} rejected where the factual rerun also completed (not outranked), "
              f"{other} rejected otherwise (harm to another vehicle)")


if __name__ == "__main__":
    main(sys.argv[1:])
