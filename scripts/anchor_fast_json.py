"""Write zoo/anchor_fast.json for the compressed shipped anchor (J16's conversion).

    python scripts/anchor_fast_json.py

Reads the compress report ``runs/anchor_fast_J16/r128.json`` (written by ``counterplay
compress-anchor``; not kept in the tree: the record carries its contents), the evaluator
summaries of the compressed anchor in ``docs/results/anchor/fast_seed0/summary_{deployment}.csv``
(task set 0, the same tasks as ``zoo/anchor_imitation.json``'s ``evaluator.seed0``; ``scripts/eval_anchor.sh``),
and the previous zoo/anchor_fast.json (I9F's conversion), which becomes
``previous_anchor_fast``. The learn benchmark is carried over: it was measured with an
earlier conversion's weights, and the network and settings are the same. Written through a
temporary file and a rename; refuses to run twice.
"""
from __future__ import annotations

import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from anchor_json import load_folder, write_json  # noqa: E402  (the evaluator summary reader of zoo/anchor_imitation.json)

ROOT = os.path.join(HERE, "..")
ANCHOR_FAST_JSON = os.path.join(ROOT, "zoo", "anchor_fast.json")
REPORT = os.path.join(ROOT, "runs", "anchor_fast_J16", "r128.json")


def main() -> None:
    previous = json.load(open(ANCHOR_FAST_JSON))
    if "J16" in previous["description"]:
        raise SystemExit(f"{ANCHOR_FAST_JSON} already describes J16's conversion")
    report = json.load(open(REPORT))
    flat = json.load(open(os.path.join(ROOT, "zoo", "anchor_imitation.json")))["evaluator"]["seed0"]
    command = report["command"].split("bin/", 1)[-1].replace("runs/anchor_fast_J16/r128.zip", "zoo/anchor_fast.zip")
    doc = {
        "description": (
            "The shipped anchor (zoo/anchor_imitation.zip: candidate J16, shipped since 2026-12-03) "
            "compressed into the LinearEncoder network (cpalgo.encoders: 128 features in front of the LSTM and "
            "the critic): its input layers factorised at rank 128 on observations it sees, then 20 DAgger rounds "
            "of distillation on its action probabilities and values (cpalgo.compress). Post-train it with "
            "zoo/counterplay_fast.yml."),
        "commands": [command,
                     "python -m cpalgo.evaluate --policy anchor=zoo/anchor_fast.zip --traffic-policy zoo/anchor_fast.zip "
                     "--split both --n 100 --seed 0 --deploy DEPLOY --no-plots"],
        "machine": "2 CPU cores (AMD EPYC, AVX2), no GPU, torch 2.13 CPU (2 threads), Warp 1.19 CPU",
        "wall_s": report["wall_s"],
        "fit": report["fit"],
        "distillation": {"config": report["config"], "rounds": report["rounds"]},
        "evaluator": {
            "command": ("python -m cpalgo.evaluate --policy anchor=zoo/anchor_fast.zip --traffic-policy "
                        "zoo/anchor_fast.zip --split both --n 100 --seed 0 --deploy DEPLOY --no-plots (procedural "
                        "pool, all 8 regimes; task set 0, as zoo/anchor_imitation.json's evaluator.seed0)"),
            "deploy": load_folder(os.path.join(ROOT, "docs", "results", "anchor", "fast_seed0"),
                                  ("interactive", "random"))},
        "flat_anchor_evaluator": flat,
        "learn_benchmark": {**previous["learn_benchmark"],
                            "note_J16": ("measured with an earlier conversion's weights (the compressed anchor of "
                                         "2026-12-02, as the note above says); the network and settings are the "
                                         "same, and throughput does not depend on the weights")},
        "previous_anchor_fast": previous,
    }
    write_json(ANCHOR_FAST_JSON, doc)
    print("wrote", os.path.normpath(ANCHOR_FAST_JSON))


if __name__ == "__main__":
    main()
