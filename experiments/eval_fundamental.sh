#!/usr/bin/env bash
# Table 2 and the iterations figure (what the DVC stages do): every method at every budget on the test split.
# Usage: bash experiments/eval_fundamental.sh [ITERS ...]   (default: 10 25 50 100 250 500 1000)
set -euo pipefail
iters=("$@")
[ ${#iters[@]} -eq 0 ] && iters=(10 25 50 100 250 500 1000)
for it in "${iters[@]}"; do
  for m in opencv_ransac usac usac_accurate magsac ransac; do
    rlsac evaluate --task fundamental --method "$m" --data data/fundamental/test.h5 --iterations "$it" \
      --out-dir "reports/eval/fundamental/$m/i$it" --device cpu
  done
  rlsac evaluate --task fundamental --method rlsac --checkpoint checkpoints/fundamental.pt \
    --data data/fundamental/test.h5 --iterations "$it" --batch-size 8 --out-dir "reports/eval/fundamental/rlsac/i$it" \
    --device cpu
done
