#!/bin/bash
# usage: [SEED=S] eval.sh MODEL OUTDIR DEPLOY... (the candidate as its own traffic, 100 tasks per split;
# SEED picks the task set, default 0; each summary.csv is also copied to OUTDIR/summary_DEPLOY.csv, the
# name docs/results/parked_fix/item3.py reads)
model=$1; out=$2; shift 2
mkdir -p "$out"
for d in "$@"; do
  python -m cpalgo.evaluate --policy anchor=$model --traffic-policy $model --split both --n 100 --seed "${SEED:-0}" \
    --deploy $d --no-plots --no-progress --out $out/procedural_$d > $out/eval_$d.log 2>&1 \
    && cp $out/procedural_$d/summary.csv $out/summary_$d.csv
done
