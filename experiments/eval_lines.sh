#!/usr/bin/env bash
# Table 1 evaluations (what the DVC stages do): RANSAC, Ours (model of the rate), Ours-0.5, 150 iterations.
# Usage: bash experiments/eval_lines.sh RATE [RATE ...]
set -euo pipefail
for r in "$@"; do
  rlsac evaluate --task line --method ransac --data "data/lines/test_o$r.h5" --out-dir "reports/eval/lines/ransac/o$r" --device cpu
  rlsac evaluate --task line --method rlsac --checkpoint "checkpoints/line_o$r.pt" --data "data/lines/test_o$r.h5" \
    --out-dir "reports/eval/lines/ours/o$r" --device cpu
  rlsac evaluate --task line --method rlsac --checkpoint checkpoints/line_o0.5.pt --data "data/lines/test_o$r.h5" \
    --out-dir "reports/eval/lines/ours-0.5/o$r" --device cpu
done
