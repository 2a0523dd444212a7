"""The hand-made faults of issue #13, each injected into a temporary copy of the package, with the tests
that must catch it. Not part of CI (it runs the learning tests once per fault: a few minutes).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mutation_faults.py [NAME ...]
    FAULT_TESTS="tests/test_sac.py tests/test_policy.py" ... # only these test files (faster)

Prints one line per fault: caught (with the failing tests) or MISSED; exits 1 if any fault is missed
or no longer applies (its original text is gone from the source: update the fault). The working tree
is never modified: the copy lives in a temporary directory and is imported first (cwd on sys.path).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FAST = ["tests/test_sac.py", "tests/test_policy.py"]
ALL = [*FAST, "tests/test_learning.py"]

# name: (file, original text, faulty text, test files to run)
FAULTS = {
    "actor loss sign flipped": (
        "rlsac/rl/sac.py", "actor_loss = (p * (alpha * logp - qmin)).sum(-1).mean()",
        "actor_loss = -(p * (alpha * logp - qmin)).sum(-1).mean()", ALL),
    "critic target ignores done": (
        "rlsac/rl/sac.py", "target = reward + c.gamma * (1.0 - done) * v2", "target = reward + c.gamma * v2", ALL),
    "temperature loss sign flipped": (
        "rlsac/rl/sac.py", "alpha_loss = (self.log_alpha.exp() * (entropy - target_h)).mean()",
        "alpha_loss = -(self.log_alpha.exp() * (entropy - target_h)).mean()", ALL),
    "stored next state = current state": (
        "rlsac/rl/sac.py", "buffer.add(inst[act], mem[act], env.memory()[act],",
        "buffer.add(inst[act], mem[act], mem[act],", ALL),
    "no Polyak update of the target critics": (
        "rlsac/rl/sac.py", "tp.lerp_(p_, c.tau)", "pass", ALL),
    "EdgeConv ignores neighbours (training forward)": (
        "rlsac/rl/policy.py", "nb = _NeighbourMax.apply(b, flat, k).view(R, N, -1)", "nb = b.view(R, N, -1)", ALL),
    "EdgeConv ignores neighbours (rollout forward_memory)": (
        "rlsac/rl/policy.py", "a.view(b.shape).add_(nb)", "a.view(b.shape).add_(b)", ALL),
    "EdgeConv ignores neighbours (EdgeConv.forward, reference path)": (
        "rlsac/rl/policy.py", "nb = b.reshape(R * N, -1).index_select(0, flat).view(R, N, k, -1).amax(dim=2)",
        "nb = b", ALL),
    "test time: max sampling replaced by probabilistic": (
        "rlsac/rl/rollout.py", "env.step(select_lazily(env, logits, sample=sampling == \"prob\"))",
        "env.step(select_lazily(env, logits, sample=True))", ALL),
    "test time: memory channels zeroed": (
        "rlsac/rl/rollout.py", "logits = actor.forward_memory(prepared, env.memory())",
        "logits = actor.forward_memory(prepared, torch.zeros_like(env.memory()))", ALL),
    "test time: uniform sets instead of the policy": (
        "rlsac/rl/rollout.py", "env.step(select_lazily(env, logits, sample=sampling == \"prob\"))",
        "env.step(env.select(env.action, random=True))", ALL),
    "best-validation selection keeps the worst": (
        "rlsac/evaluation/train.py", 'if conf.selection != "last" and score > best["score"]:',
        'if conf.selection != "last" and (score < best["score"] or best["score"] < 0):', ALL),
    "best-validation selection keeps the latest": (
        "rlsac/evaluation/train.py", 'if conf.selection != "last" and score > best["score"]:',
        'if conf.selection != "last":', ALL),
}


def run_fault(name: str, work: Path) -> tuple[str, list[str]]:
    path, old, new, tests = FAULTS[name]
    tests = os.environ.get("FAULT_TESTS", "").split() or tests
    src = work / path
    text = (ROOT / path).read_text()
    if text.count(old) != 1:
        return "NOT APPLICABLE (original text not found once)", []
    src.write_text(text.replace(old, new))
    try:
        r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *tests],
                           cwd=work, capture_output=True, text=True)
    finally:
        src.write_text(text)
    failed = re.findall(r"^FAILED (\S+)", r.stdout, flags=re.M) + re.findall(r"^ERROR (\S+)", r.stdout, flags=re.M)
    return ("caught" if r.returncode != 0 else "MISSED"), failed


def main(names: list[str]) -> int:
    bad = 0
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for item in ("rlsac", "tests", "pyproject.toml", "params.yaml", "dvc.yaml"):
            p = ROOT / item
            (shutil.copytree if p.is_dir() else shutil.copy)(p, work / item)
        for name in names or FAULTS:
            verdict, failed = run_fault(name, work)
            bad += verdict != "caught"
            print(f"{verdict:8s} {name}: {', '.join(failed) or '-'}", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
