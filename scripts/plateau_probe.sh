#!/bin/bash
# The plateau probe: a post-trained candidate (PPO-Continue at B_post = 1 % of the anchor's
# transitions) on the anchor's task sets, beside the anchor, in the same traffic.
# usage: [SETS="0 1 2 3"] scripts/plateau_probe.sh ANCHOR CANDIDATE OUTDIR
# Normal deployment, 100 held-out procedural tasks per split, all 8 regimes, the ANCHOR as every
# policy regime's co-player (the traffic the anchor's own profile is measured in, by
# scripts/eval_anchor.sh); writes OUTDIR/setS/summary_normal.csv per task set S. Then
#   python scripts/anchor_profile.py OUTDIR/set{0,1,2,3}
# prints the candidate's pooled numbers, to set against the anchor's.
set -e
anchor=$1; candidate=$2; out=$3
if [ -z "$out" ]; then echo "usage: scripts/plateau_probe.sh ANCHOR CANDIDATE OUTDIR" >&2; exit 2; fi
for s in ${SETS:-0 1 2 3}; do
  mkdir -p "$out/set$s"
  python -m cpalgo.evaluate --policy candidate="$candidate" --traffic-policy "$anchor" --split both --n 100 \
    --seed "$s" --deploy normal --no-plots --no-progress --out "$out/set$s/procedural_normal" > "$out/set$s/eval_normal.log" 2>&1
  cp "$out/set$s/procedural_normal/summary.csv" "$out/set$s/summary_normal.csv"
done
