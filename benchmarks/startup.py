"""Start-up cost of an ``rlsac`` command, and what MLflow tracking adds to it.

    python benchmarks/startup.py [--repeats 5]

Runs, in a temporary working directory (its own ``mlflow.db``), ``--repeats`` times each:
``rlsac --help``; ``rlsac synth-lines --n-instances 10`` with ``--no-tracking`` and with tracking (the
first tracked run also creates the store); and ``python -c "import mlflow"`` alone. Prints the median wall
times and the ratios tracked / untracked and (tracked - untracked) / import-only. Nothing is asserted:
the numbers depend on the load of the machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BIN = Path(sys.executable).parent


def timed(argv: list[str], cwd: str, env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, cwd=cwd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rlsac = str(BIN / "rlsac")
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp}/mlflow.db", "OMP_NUM_THREADS": "1"}
        synth = [rlsac, "synth-lines", "--n-instances", "10", "--out", "l.h5"]
        first = timed(synth, tmp, env)  # creates the store (schema migrations): reported separately
        cases = {
            "rlsac --help": [rlsac, "--help"],
            "synth-lines --no-tracking": [*synth, "--no-tracking"],
            "synth-lines (tracked)": synth,
            "import mlflow": [sys.executable, "-c", "import mlflow"],
        }
        med = {name: statistics.median(timed(argv, tmp, env) for _ in range(args.repeats))
               for name, argv in cases.items()}
    print(f"first tracked run (creates mlflow.db): {first:.2f} s")
    for name, t in med.items():
        print(f"{name:28s} median {t:.2f} s over {args.repeats}")
    extra = med["synth-lines (tracked)"] - med["synth-lines --no-tracking"]
    print(f"ratio tracked / untracked: {med['synth-lines (tracked)'] / med['synth-lines --no-tracking']:.2f}")
    print(f"tracking adds {extra:.2f} s per command, {extra / med['import mlflow']:.2f}x a bare `import mlflow`")


if __name__ == "__main__":
    main()
