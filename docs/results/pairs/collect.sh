#!/bin/bash
# usage: collect.sh NAME...: copy runs/pairs/NAME.json, evaluator summaries and self-play outcomes here
for n in "$@"; do
  mkdir -p docs/results/pairs/$n
  cp runs/pairs/$n.json docs/results/pairs/$n/ 2>/dev/null
  for d in normal aggressive; do
    [ -f runs/pairs/ev$n/procedural_$d/summary.csv ] && cp runs/pairs/ev$n/procedural_$d/summary.csv docs/results/pairs/$n/summary_$d.csv
  done
  for c in cautious normal aggressive; do
    [ -f runs/progress/out_${n}_$c.json ] && cp runs/progress/out_${n}_$c.json docs/results/pairs/$n/
  done
done
