#!/usr/bin/env bash
# The paper profile through `dvc repro`, as three lanes that run side by side on a 2-core machine.
#
# `dvc repro` runs stages one after another, but it releases the repository lock while a stage's
# command runs, so several `dvc repro` processes on disjoint stages share the machine safely
# (`--wait-for-lock` queues their short dvc.lock updates). Each lane is one `dvc repro` over its
# stages (and whatever they depend on); `final` builds the tables and figures once all are done.
# The line models are split in two lanes (rates 0.1-0.3 and 0.4-0.7): with a single lines lane the
# fold lanes finish first and one core sits idle for the last hour.
#
#   bash experiments/repro_paper.sh                 # all lanes in parallel, then final
#   bash experiments/repro_paper.sh lines_low       # one lane: lines_low | lines_high |
#                                                   #   folds_a | folds_b | essential | final
#   bash experiments/repro_paper.sh --list          # "lane stage" per line (a foreach group = all its items)
#
# Logs and wall times go to logs/repro_<lane>.log. OMP_NUM_THREADS=1 keeps each stage on one core.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
DVC="${DVC:-dvc}"
mkdir -p logs

line_stages() {  # the line stages of the given outlier rates
  local r s out=""
  for r in "$@"; do
    for s in lines_data train_lines eval_lines_ransac eval_lines_ours eval_lines_oracle eval_lines_generalisation; do
      out="$out $s@$r"
    done
  done
  echo "$out"
}

ALL_STAGES=$($DVC stage list --name-only)
fold_stages() {  # every leave-one-building-out stage of the given folds (data, models, evaluations; both regimes)
  local f
  for f in "$@"; do grep -E "^fold_[a-z_]+@((easy|hard)-)?$f(-|$)" <<<"$ALL_STAGES"; done | tr '\n' ' '
}

declare -A STAGES=(
  [lines_low]="calibrate_lines $(line_stages 0.1 0.2 0.3)"
  [lines_high]="$(line_stages 0.4 0.5 0.6 0.7)"
  [folds_a]="import_scenes $(fold_stages castle fountain)"
  [folds_b]="$(fold_stages herzjesu entry)"
  [essential]="$(grep -E '^essential_' <<<"$ALL_STAGES" | tr '\n' ' ')"
  [final]="tables figures"
)
lane() {
  local name=$1 t0 t1
  t0=$(date +%s)
  echo "== $name: start $(date -Is)" | tee -a "logs/repro_$name.log"
  # shellcheck disable=SC2086
  $DVC --wait-for-lock repro ${STAGES[$name]} >>"logs/repro_$name.log" 2>&1
  t1=$(date +%s)
  echo "== $name: done $(date -Is), wall $((t1 - t0)) s" | tee -a "logs/repro_$name.log"
}

if [ "${1:-}" = "--list" ]; then
  for name in lines_low lines_high folds_a folds_b essential final; do
    for stage in ${STAGES[$name]}; do echo "$name $stage"; done
  done
  exit 0
fi
if [ $# -gt 0 ]; then
  for name in "$@"; do lane "$name"; done
  exit 0
fi
start=$(date +%s)
pids=()
for name in lines_low lines_high folds_a folds_b essential; do
  lane "$name" & pids+=($!)
done
failed=0
for pid in "${pids[@]}"; do wait "$pid" || failed=1; done
if [ "$failed" -ne 0 ]; then
  echo "== a lane failed, see logs/repro_*.log; tables and figures not rebuilt" >&2
  exit 1
fi
lane final
echo "== paper profile: wall $(( $(date +%s) - start )) s"
