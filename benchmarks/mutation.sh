#!/usr/bin/env bash
# Mutation testing of the learning core (issue #13) with mutmut 3: every mutant of rlsac/rl/sac.py,
# rlsac/rl/policy.py and rlsac/rl/rollout.py (SAC update, replay buffer, training loop, EdgeConv networks,
# test-time rollout) against the fast learning-core tests. Not part of CI.
#
#   .venv/bin/pip install 'mutmut>=3.8'      # once; deliberately not a project dependency
#   OMP_NUM_THREADS=1 bash benchmarks/mutation.sh [MAX_CHILDREN [MUTANT_PATTERN ...]]
#   e.g. bash benchmarks/mutation.sh 2 'rlsac.rl.sac*' 'rlsac.rl.rollout*'     (default: 2 workers, every mutant)
#   SAMPLE=300 SEED=0 bash benchmarks/mutation.sh 2   # a uniform random sample of 300 of the mutants
#
# Runs in a temporary copy of the repository (the working tree is never touched; MUTATION_DIR keeps
# it elsewhere, and an existing one resumes). Prints mutmut's per-mutant results and the kill rate
# per file; the slower tests (tests/test_learning.py, whose 400-step learning test and training runs
# also kill mutants here, test_train.py, and test_speed_equivalence.py except its fast select_lazily
# test) are left out to keep it to about an hour on 2 cores. benchmarks/mutation_faults.py runs the
# issue's hand-made faults against all of them.
set -euo pipefail
main() {  # the whole script is parsed before it runs: editing this file during a run is safe
ROOT=$(cd "$(dirname "$0")/.." && pwd)
MUTMUT=${MUTMUT:-$ROOT/.venv/bin/mutmut}
PY=${PYTHON:-$ROOT/.venv/bin/python}
WORK=${MUTATION_DIR:-$(mktemp -d /tmp/rlsac-mutation.XXXXXX)}
CHILDREN=${1:-2}
shift || true
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}

mkdir -p "$WORK/tests"
rm -rf "$WORK/rlsac"
cp -r "$ROOT/rlsac" "$WORK/rlsac"
find "$WORK/rlsac" -name __pycache__ -prune -exec rm -rf {} +
cp "$ROOT"/tests/{conftest.py,test_sac.py,test_policy.py,test_env.py,test_speed_equivalence.py} "$WORK/tests/"
cat > "$WORK/setup.cfg" <<'EOF'
[mutmut]
source_paths = rlsac
only_mutate =
    rlsac/rl/sac.py
    rlsac/rl/policy.py
    rlsac/rl/rollout.py
pytest_add_cli_args_test_selection =
    tests/test_sac.py
    tests/test_policy.py
    tests/test_env.py
    tests/test_speed_equivalence.py::test_select_lazily_is_env_select
pytest_add_cli_args =
    -p
    no:cacheprovider
process_isolation = forkserver
EOF
echo "mutation run in $WORK"
cd "$WORK"
if [ -n "${SAMPLE:-}" ] && [ $# -eq 0 ]; then  # generate the mutants, then draw the sample's names
  "$PY" - "$SAMPLE" "${SEED:-0}" > sample.txt <<'PY'
import json, os, random, sys
from pathlib import Path
from mutmut.__main__ import create_mutants
from mutmut.utils.file_utils import copy_also_copy_files, copy_src_dir, setup_source_paths
os.makedirs("mutants", exist_ok=True)
with open(os.devnull, "w") as null:  # mutmut prints progress: keep sample.txt to the names
    out, sys.stdout = sys.stdout, null
    copy_src_dir(); copy_also_copy_files(); setup_source_paths()
    create_mutants(2)
    sys.stdout = out
names = sorted(k for f in ("sac", "policy", "rollout")
               for k in json.loads(Path(f"mutants/rlsac/{f}.py.meta").read_text())["exit_code_by_key"])
print("\n".join(random.Random(int(sys.argv[2])).sample(names, min(int(sys.argv[1]), len(names)))))
PY
  mapfile -t picked < sample.txt
  set -- "${picked[@]}"
  echo "sampled $# mutants (seed ${SEED:-0}) into $WORK/sample.txt"
fi
"$MUTMUT" run --max-children "$CHILDREN" "$@" || true
"$MUTMUT" results --all true > results.txt 2>&1 || "$MUTMUT" results > results.txt 2>&1 || true
"$PY" - <<'EOF'
import collections, re
rows = collections.defaultdict(collections.Counter)
for line in open("results.txt"):
    m = re.match(r"\s*(rlsac\.\w+)\.\S+: (.+)$", line)
    if m:
        rows[m.group(1)][m.group(2).strip()] += 1
total = collections.Counter()
for mod, c in sorted(rows.items()):
    total.update(c)
    n = max(1, sum(c.values()) - c["not checked"])
    print(f"{mod:16s} {n:5d} mutants  killed {c['killed']:5d} ({c['killed'] / n:.0%})  " + ", ".join(
        f"{k} {v}" for k, v in sorted(c.items()) if k != "killed"))
n = sum(total.values()) - total["not checked"]
if n:
    print(f"{'all checked':16s} {n:5d} mutants  killed {total['killed']:5d} ({total['killed'] / n:.0%})")
EOF
echo "survivors: cd $WORK && $MUTMUT show <name>   (listed in $WORK/results.txt)"
}
main "$@"
exit
