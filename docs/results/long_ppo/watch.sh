#!/bin/bash
# evaluate every EVERY-th snapshot of DIR (normal + aggressive, 100 tasks per split, candidate as its own traffic)
dir=$1; every=${2:-2}
while true; do
  for ck in $dir/ck_*.zip; do
    [ -e "$ck" ] || continue
    k=$(basename $ck .zip | cut -d_ -f2); k=$((10#$k))
    [ $((k % every)) -eq 0 ] || continue
    out=$dir/ev_$(basename $ck .zip)
    [ -e $out/done ] && continue
    mkdir -p $out
    OMP_NUM_THREADS=1 bash docs/results/anchor_fast/eval.sh $ck $out normal aggressive && touch $out/done
  done
  sleep 60
done
