"""Warm stage commands against cold ones (rlsac.runners.warm; issue #63 item 8).

    python benchmarks/warm_start.py                 # 8 small stage commands each way, one after the other
    python benchmarks/warm_start.py --n 20 --out reports/warm_start.json

A pipeline stage whose work takes a second spends about as long again importing torch, OpenCV, h5py, pandas and
MLflow's SQL store. This runs the same small ``rlsac synth-lines`` command line (logging its MLflow run to a
sqlite store, as a stage does) ``--n`` times started cold (through
the pipeline's guarded start, a shell that execs ``rlsac``) and ``--n`` times warm (forked from one warm process,
whose own start is counted once), in this run, alternating, and prints the time per command each way, their ratio
(cold / warm) and whether every output is the same bytes. ``--out`` writes them as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=8, help="commands each way")
    ap.add_argument("--out", help="write the result as JSON here")
    a = ap.parse_args()
    from rlsac.runners import warm
    from rlsac.runners.dvc_stage import python_bin_env
    from rlsac.runners.stage_task import guard, start_guarded

    tmp_store = tempfile.mkdtemp(prefix="warm-start-")
    # each command logs its MLflow run, as a pipeline stage does (the SQL store's imports are part of a start)
    env = python_bin_env({"OMP_NUM_THREADS": "1", "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_store}/mlflow.db"})
    times: dict[str, list[float]] = {"cold": [], "warm": []}
    outputs: dict[str, list[bytes]] = {"cold": [], "warm": []}
    with tempfile.TemporaryDirectory() as tmp:
        t_first = None
        for i in range(a.n):
            for how in ("cold", "warm"):
                out = Path(tmp) / f"{how}{i}.h5"
                argv = ["/bin/sh", "-c", f"rlsac synth-lines --outlier 0.7 --n-instances 50 --seed 1 --out {out} "
                                         f"--tracking"]
                t0 = time.perf_counter()
                with open(Path(tmp) / f"{how}{i}.log", "wb") as f:
                    kw = dict(cwd=str(ROOT), env=env, stdout=f, stderr=subprocess.STDOUT, close_fds=True)
                    proc = start_guarded(argv, **kw) if how == "cold" else warm.start(argv, guard, start_guarded, **kw)
                    rc = proc.wait()
                dt = time.perf_counter() - t0
                if rc:
                    sys.exit(f"error: {how} command {i} exited {rc}: {(Path(tmp) / f'{how}{i}.log').read_text()}")
                if how == "warm" and i == 0:
                    t_first = dt  # the warm process's own start (its imports) and the first command
                else:
                    times[how].append(dt)
                outputs[how].append(out.read_bytes())
        warm.stop()
    cold = sum(times["cold"]) / len(times["cold"])
    hot = sum(times["warm"]) / max(len(times["warm"]), 1)
    same = all(x == outputs["cold"][0] for x in outputs["cold"] + outputs["warm"])
    import shutil

    shutil.rmtree(tmp_store, ignore_errors=True)
    r = {"command": "rlsac synth-lines --outlier 0.7 --n-instances 50 --seed 1 (an MLflow run to a sqlite store)",
         "n": a.n,
         "cold_s": round(cold, 3), "warm_s": round(hot, 3), "warm_first_s": round(t_first, 3),
         "ratio": round(cold / hot, 2), "saved_per_command_s": round(cold - hot, 3), "same_bytes": same,
         "cpu": os.cpu_count()}
    print(f"cold {cold:.2f} s a command, warm {hot:.2f} s ({r['ratio']}x; the warm process's first: {t_first:.2f} s); "
          f"outputs the same bytes: {same}")
    if a.out:
        Path(a.out).write_text(json.dumps(r, indent=2) + "\n")
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
