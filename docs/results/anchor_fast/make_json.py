"""Write zoo/anchor_fast.json from the compress report and the evaluator summaries."""
import csv
import json
import os

R = "runs/anchor_fast"
REG = ["idm","selfplay","bc","replay","aggressive","normal","cautious","mix"]
MET = ["score","completion","at_fault_collision","non_at_fault_collision","offroad","timeout","co_player_harm"]
def block(path):
    t = {}
    for r in csv.DictReader(open(path)):
        t[(r["split"], r["regime"], r["metric"])] = float(r["mean"])
    out = {}
    for split in ("interactive", "random"):
        if (split, "idm", "score") not in t:
            continue
        e = {m: round(sum(t[(split, g, m)] for g in REG) / len(REG), 4) for m in MET}
        e["completion_by_regime"] = {g: t[(split, g, "completion")] for g in REG}
        out[split] = e
    return out
def deploys(d):
    return {dep: block(f"{d}/procedural_{dep}/summary.csv") for dep in ("normal","aggressive","cautious")
            if os.path.exists(f"{d}/procedural_{dep}/summary.csv")}
rep = json.load(open(f"{R}/r128.json"))
doc = {
  "description": "The shipped anchor (zoo/anchor.zip) compressed into the LinearEncoder network (cpalgo.encoders: "
                 "128 features in front of the LSTM and the critic): its input layers factorised at rank 128 on "
                 "observations it sees, then 20 DAgger rounds of distillation on its action probabilities and values "
                 "(cpalgo.compress). Post-train it with zoo/counterplay_fast.yml.",
  "commands": [rep["command"],
               "python -m cpalgo.evaluate --policy anchor=zoo/anchor_fast.zip --traffic-policy zoo/anchor_fast.zip "
               "--split both --n 100 --deploy DEPLOY --no-plots"],
  "machine": "2 CPU cores (AMD EPYC, AVX2), no GPU, torch 2.13 CPU (2 threads), Warp 1.19 CPU; a second job "
             "(an evaluation or a test run) shared the cores part of the time",
  "wall_s": rep["wall_s"],
  "fit": rep["fit"],
  "distillation": {"config": rep["config"], "rounds": rep["rounds"]},
  "evaluator": {"command": "python -m cpalgo.evaluate --policy anchor=zoo/anchor_fast.zip --traffic-policy "
                           "zoo/anchor_fast.zip --split both --n 100 --deploy DEPLOY --no-plots (procedural pool, "
                           "all 8 regimes)", "deploy": deploys(f"{R}/ev20")},
  "flat_anchor_evaluator": {k: v for k, v in json.load(open("zoo/anchor.json"))["evaluator"]["deploy"].items()},
  "candidates": {
    "round_7_of_20": {"normal": block(f"{R}/ev7/procedural_normal/summary.csv")},
    "plus_10_rounds_lr_1e-4_256_worlds": {"command": "counterplay compress-anchor --anchor zoo/anchor.zip --init "
        "runs/anchor_fast/r128.zip --out runs/anchor_fast/r128b.zip --features-dim 128 --rounds 10 --worlds 256 "
        "--epochs 3 --learning-rate 1e-4 --add-womd ../shared/data/womd/train --threads 1 --seed 1",
        "final_rollout_kl": json.load(open(f"{R}/r128b.json"))["rounds"][-1]["kl"],
        "evaluator": deploys(f"{R}/ev30")},
  },
}
if os.path.exists(f"{R}/r192.json"):
    r192 = json.load(open(f"{R}/r192.json"))
    doc["candidates"]["features_dim_192"] = {
        "command": r192["command"], "wall_s": r192["wall_s"], "fit": r192["fit"],
        "final_rollout_kl": r192["rounds"][-1]["kl"], "final_agreement": r192["rounds"][-1]["agreement"],
        "evaluator": deploys(f"{R}/ev192"),
        "learn_benchmark_64x8x32": json.load(open(f"{R}/bench_r192_64x8x32.json"))}
if os.path.exists(f"{R}/womd/procedural_normal/summary.csv"):
    doc["evaluator_womd_valid"] = {"normal": block(f"{R}/womd/procedural_normal/summary.csv")}
doc["outcomes_by_condition"] = {
    "command": "counterplay outcomes --model zoo/anchor_fast.zip --condition C --tasks 256 --threads 1",
    **{c: json.load(open(f"{R}/outcomes_{c}.json"))["outcomes"] for c in ("cautious", "normal", "aggressive")
       if os.path.exists(f"{R}/outcomes_{c}.json")}}
for f in ("bench_anchor_fast_16x8x64", "bench_anchor_fast_64x8x32", "bench_anchor_16x8x64", "bench_anchor_64x8x32"):
    if os.path.exists(f"{R}/{f}.json"):
        doc.setdefault("learn_benchmark", {})[f] = json.load(open(f"{R}/{f}.json"))
json.dump(doc, open("zoo/anchor_fast.json", "w"), indent=1)
print("ok", list(doc))
