#!/usr/bin/env bash
# Table 1 by hand (what the DVC stages do): data, one model per outlier rate.
# Usage: bash experiments/run_lines.sh RATE [RATE ...]   (RESUME=1 continues from checkpoints/*.state.pt;
# STEPS=N overrides params.yaml train.line.sac.total_steps)
set -euo pipefail
for r in "$@"; do
  # data: sizes and seeds from params.yaml `lines` (rlsac lines-data, as the DVC stage does)
  if [ ! -f "data/lines/train_o$r.h5" ] || [ ! -f "data/lines/val_o$r.h5" ] || [ ! -f "data/lines/test_o$r.h5" ]; then
    rlsac lines-data --rate "$r" --no-tracking
  fi
  extra=()
  [ -n "${STEPS:-}" ] && extra+=(--set "sac.total_steps=$STEPS")
  [ "${RESUME:-0}" = 1 ] && [ -f "checkpoints/line_o$r.state.pt" ] && extra+=(--resume)
  rlsac train --task line --data "data/lines/train_o$r.h5" --val-data "data/lines/val_o$r.h5" \
    --out "checkpoints/line_o$r.pt" --device cpu --set run_name="train line o$r" "${extra[@]}"
done
