#!/usr/bin/env bash
# The paper profile through `dvc repro`, as two lanes that can run side by side on a 2-core machine.
#
# `dvc repro` runs stages one after another, but it releases the repository lock while a stage's
# command runs, so two `dvc repro` processes on disjoint stages share the machine safely
# (`--wait-for-lock` queues their short dvc.lock updates). Each lane is one `dvc repro` over its
# stages (and whatever they depend on); `final` builds the tables and figures once both are done.
#
#   bash experiments/repro_paper.sh            # both lanes in parallel, then final
#   bash experiments/repro_paper.sh lines      # one lane: lines | fundamental | final
#
# Logs and wall times go to logs/repro_<lane>.log. OMP_NUM_THREADS=1 keeps each stage on one core.
set -euo pipefail
cd "$(dirname "$0")/.."
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
DVC="${DVC:-dvc}"
mkdir -p logs

declare -A STAGES=(
  [lines]="lines_data train_lines eval_lines_ransac eval_lines_ours eval_lines_oracle eval_lines_generalisation"
  [fundamental]="import_scenes prepare_fundamental train_fundamental eval_fundamental eval_fundamental_rlsac ablation_data ablation_train ablation_eval"
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

if [ $# -gt 0 ]; then
  for name in "$@"; do lane "$name"; done
  exit 0
fi
start=$(date +%s)
lane lines & p1=$!
lane fundamental & p2=$!
wait $p1
wait $p2
lane final
echo "== paper profile: wall $(( $(date +%s) - start )) s"
