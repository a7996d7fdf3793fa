#!/bin/bash
# Evaluate an anchor candidate on one task set under several deployment profiles.
# usage: [SEED=S] scripts/eval_anchor.sh MODEL OUTDIR DEPLOY...   (e.g. normal aggressive cautious)
# The candidate is its own traffic, 100 held-out procedural tasks per split, all 8 regimes; SEED picks
# the task set (default 0). Each summary.csv is also copied to OUTDIR/summary_DEPLOY.csv, the name
# scripts/anchor_profile.py reads.
model=$1; out=$2; shift 2
mkdir -p "$out"
for d in "$@"; do
  python -m cpalgo.evaluate --policy anchor=$model --traffic-policy $model --split both --n 100 --seed "${SEED:-0}" \
    --deploy $d --no-plots --no-progress --out $out/procedural_$d > $out/eval_$d.log 2>&1 \
    && cp $out/procedural_$d/summary.csv $out/summary_$d.csv
done
