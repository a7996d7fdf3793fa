#!/bin/bash
# usage: quick.sh MODEL TAG: self-play goals per style on 256 held-out tasks
m=$1; t=$2
for c in cautious normal aggressive; do
  counterplay outcomes --model $m --condition $c --tasks 256 --threads 1 --out runs/progress/out_${t}_$c.json 2>/dev/null | tail -n 1
done
