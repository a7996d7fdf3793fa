set -x
for a in zoo/anchor_fast.zip zoo/anchor.zip; do
  n=$(basename $a .zip)
  python -m cpalgo.bench --anchor $a --worlds 16 --agents 8 --n-steps 64 --batch-size 4096 --epochs 3 --generations 3 --threads 2 --out runs/anchor_fast/bench_${n}_16x8x64.json
  python -m cpalgo.bench --anchor $a --worlds 64 --agents 8 --n-steps 32 --batch-size 2048 --epochs 3 --generations 3 --threads 2 --out runs/anchor_fast/bench_${n}_64x8x32.json
done
