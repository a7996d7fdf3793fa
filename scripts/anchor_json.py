"""Write zoo/anchor_imitation.json for the shipped anchor (candidate J16 of its last stage).

    python scripts/anchor_json.py [RECORD]

Reads the previous anchor record (RECORD, default zoo/anchor_imitation.json; it becomes
``previous_anchor``: the anchor before, I9F, and nested in it the anchors before that), the
evaluator summaries in ``docs/results/anchor/seed{0,1,2,3}/`` and ``womd_valid/``
(``summary_{deployment}.csv``, written by ``scripts/eval_anchor.sh``), the self-play outcomes
``outcomes_{condition}.json`` (``counterplay outcomes``) and the training record ``train.json``
there, and writes the new record through a temporary file and a rename. The previous record is
zoo/anchor_imitation.json as it was before this anchor shipped (``git show
64e2feb:cpalgo/shipped/anchor_imitation.json``); ``scripts/anchor_json_8sets.py`` then adds task sets 4-7.
"""
from __future__ import annotations

import json
import os
import sys

from anchor_profile import REGIMES, load  # the same summary_{deployment}.csv reader, beside this script

from cpsim.atomic import atomic_path

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
#: the evaluator summaries, outcomes and training record of the shipped anchor
HERE = os.path.join(ROOT, "docs", "results", "anchor")
ANCHOR_JSON = sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "zoo", "anchor_imitation.json")
DEPLOYMENTS = ("normal", "aggressive", "cautious")
METRICS = ("score", "completion", "at_fault_collision", "non_at_fault_collision", "offroad", "timeout",
           "co_player_harm")


def write_json(path: str, record: dict) -> None:
    """Write ``record`` as indented JSON through a temporary file and a rename."""
    with atomic_path(path) as tmp, open(tmp, "w") as fh:
        json.dump(record, fh, indent=1)
        fh.write("\n")


def split_block(rows: dict, split: str) -> dict:
    out = {m: round(sum(rows[(split, g, m)] for g in REGIMES) / len(REGIMES), 4) for m in METRICS}
    for m in ("completion", "non_at_fault_collision", "co_player_harm"):
        out[f"{m}_by_regime"] = {g: round(rows[(split, g, m)], 4) for g in REGIMES}
    return out


def load_folder(folder: str, splits: tuple[str, ...]) -> dict:
    return {dep: {s: split_block(load(folder, dep), s) for s in splits} for dep in DEPLOYMENTS}


def pool(blocks: list[dict]) -> dict:
    def mean(values):
        if isinstance(values[0], dict):
            return {k: mean([v[k] for v in values]) for k in values[0]}
        return round(sum(values) / len(values), 4)
    return mean(blocks)


def main() -> None:
    previous = json.load(open(ANCHOR_JSON))
    if "imitation_parked_fixed_v6" in previous["wall_s"]:
        raise SystemExit(f"{ANCHOR_JSON} already describes J16; restore I9F's record first "
                         "(git checkout cpalgo/shipped/anchor_imitation.json at the commit before)")
    train = json.load(open(os.path.join(HERE, "train.json")))
    sets = {f"seed{s}": load_folder(os.path.join(HERE, f"seed{s}"), ("interactive", "random")) for s in range(4)}
    sets["pooled"] = pool([sets[f"seed{s}"] for s in range(4)])
    womd = load_folder(os.path.join(HERE, "womd_valid"), ("interactive", "random"))
    outcomes = {c: json.load(open(os.path.join(HERE, f"outcomes_{c}.json")))["outcomes"] for c in DEPLOYMENTS}
    p = sets["pooled"]
    sep = {s: round(100 * (p["aggressive"][s]["completion"] - p["normal"][s]["completion"]), 1)
           for s in ("interactive", "random")}
    # as run: --init zoo/anchor_imitation.zip (then I9F) --out runs/tv10/J16.zip; written as a chain that
    # starts from the file the previous command wrote
    command = (train["command"].split("bin/", 1)[-1]  # drop the interpreter's path
               .replace("--init zoo/anchor_imitation.zip", "--init runs/tv5/I9F.zip")
               .replace("--out runs/tv10/J16.zip", "--out zoo/anchor_imitation.zip"))
    earlier = [c.replace("--out zoo/anchor_imitation.zip", "--out runs/tv5/I9F.zip") for c in previous["commands"]]
    anchor = {
        "description": (
            "Reward-conditioned, style-responsive anchor (shipped 2026-12-03): the "
            "previous anchor (I9F, under previous_anchor; same network: RecurrentPPO MlpLstmPolicy, "
            "LSTM 128, actor and critic MLPs [128, 128]) plus stage 12: 4 DAgger rounds of imitation "
            "with paired style labels (beta 0.02, 8 epochs) of reactive teacher v6 on the training pool "
            "whose parked family was corrected (its ego logs now reach their goals: oncoming rivals "
            "leave the bypass as the ego arrives, the task ends past the last parked vehicle), plus the "
            "40 WOMD training scenes. Candidate J16 of two seeds (J16, J17) of that stage, chosen on the "
            "four task sets below (docs/anchor.md)."),
        "commands": earlier + [command],
        "machine": "2 CPU cores (AMD EPYC), two training jobs at once, no GPU, torch 2.13 CPU (one thread each), Warp 1.19 CPU",
        "wall_s": {**previous["wall_s"], "imitation_parked_fixed_v6": train["wall_s"]},
        "timesteps": previous["timesteps"],
        "imitation_rounds": train["imitation_rounds"],
        "held_out": previous["held_out"],
        "outcomes_by_condition": outcomes,
        "evaluator": {
            "note": ("Four task sets (--seed 0, 1, 2, 3), 100 tasks per split each, 8 regimes, the anchor "
                     "as its own traffic, on the corrected procedural evaluation pool; 'pooled' is their "
                     "mean (400 tasks per split). Item 3 of the anchor issue (Interactive / Random): "
                     f"score {p['normal']['interactive']['score']:.1f} / {p['normal']['random']['score']:.1f} "
                     f"(>= 50), at-fault {100 * p['normal']['interactive']['at_fault_collision']:.1f} / "
                     f"{100 * p['normal']['random']['at_fault_collision']:.1f} % (<= 10), timeout "
                     f"{100 * p['normal']['interactive']['timeout']:.1f} / {100 * p['normal']['random']['timeout']:.1f} % "
                     f"(largest failure class, >= 15), aggressive - normal completion {sep['interactive']:+.1f} / "
                     f"{sep['random']:+.1f} (>= +10), cautious at-fault "
                     f"{100 * p['cautious']['interactive']['at_fault_collision']:.1f} / "
                     f"{100 * p['cautious']['random']['at_fault_collision']:.1f} % (<= normal's)."),
            "command": ("python -m cpalgo.evaluate --policy anchor=zoo/anchor_imitation.zip --traffic-policy zoo/anchor_imitation.zip "
                        "--split both --n 100 --seed SEED --deploy DEPLOY --no-plots"),
            **sets,
        },
        "evaluator_womd_valid": {
            "command": ("python -m cpalgo.evaluate --policy anchor=zoo/anchor_imitation.zip --traffic-policy zoo/anchor_imitation.zip "
                        "--pool ../shared/data/womd/valid --n 100 --deploy DEPLOY --no-plots"),
            "coplayers": "vehicles (every vehicle present at t0 except the ego)",
            "deploy": womd,
        },
        "previous_anchor": previous,
    }
    write_json(ANCHOR_JSON, anchor)
    print("wrote", os.path.normpath(ANCHOR_JSON))


if __name__ == "__main__":
    main()
