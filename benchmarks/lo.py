"""Cost of the local-optimisation step (rlsac.estimation.lo) relative to the sampler's own time, in the same run.

    python benchmarks/lo.py [--task fundamental|line] [--data FILE] [--methods ransac-lo,uniform-lo,rlsac-lo]
                            [--iterations 1000] [--checkpoint CKPT] [--pairs 30] [--threads 1] [--params params.yaml]

Each method runs as ``rlsac evaluate`` would (``rlsac.evaluation.evaluate.make_estimator``, LO options from
params.yaml ``evaluate.<task>.lo``): fundamental pairs one at a time (batch 1, the evaluation's layout),
lines in one batch of ``--pairs`` instances. For every method: wall time per instance, the part spent
inside the LO steps (timed inside ``rlsac.estimation.lo.update_best`` / ``finish``), the sampler's own time (the
rest: minimal sets, solver, scoring, policy) and the ratio LO / sampler; LO calls and non-minimal fits per
instance. CPU only (the LO timers do not synchronise a GPU). No timing is asserted anywhere.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from rlsac.config import read_params, section
from rlsac.evaluation.evaluate import EvalOptions, make_estimator
from rlsac.tasks import task_class

DEFAULT_DATA = {"fundamental": "data/folds/hard/fountain/test.h5", "line": "data/lines/test_o0.5.h5"}
DEFAULT_CKPT = {"fundamental": "checkpoints/folds/hard/fountain/rlsac.pt", "line": "checkpoints/line_o0.5.pt"}
DEFAULT_ITERATIONS = {"fundamental": 1000, "line": 150}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", choices=["fundamental", "line"], default="fundamental")
    ap.add_argument("--data", default=None)
    ap.add_argument("--methods", default="ransac-lo,uniform-lo,rlsac-lo")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--pairs", type=int, default=30, help="fundamental pairs / line instances to time")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--params", default="params.yaml")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    task_name = args.task
    data_path = args.data or DEFAULT_DATA[task_name]
    ckpt = args.checkpoint or DEFAULT_CKPT[task_name]
    iterations = args.iterations or DEFAULT_ITERATIONS[task_name]
    lo_options = section(read_params(args.params), "evaluate", task_name).get("lo") or {}
    mod = task_class(task_name)  # its reader and to_batch
    data, _ = mod.read(data_path)
    n = min(args.pairs, len(next(v for v in data.values() if hasattr(v, "shape"))))
    per_pair = task_name == "fundamental"
    batches = [slice(i, i + 1) for i in range(n)] if per_pair else [slice(0, n)]
    print(f"LO cost: task {task_name}, {data_path}, {n} instances, {iterations} iterations, "
          f"{args.threads} thread(s), lo = {lo_options}")
    print(f"{'method':<12} {'ms/inst':>9} {'LO ms':>8} {'sampler ms':>11} {'LO/sampler':>11} {'calls':>6} {'fits':>6}")
    for method in [m for m in args.methods.split(",") if m]:
        o = EvalOptions(task=task_name, method=method, data=str(data_path), iterations=iterations, lo=lo_options,
                        checkpoint=str(ckpt) if method.startswith("rlsac") else None)
        if method.startswith("rlsac") and not Path(ckpt).is_file():
            print(f"{method:<12} skipped: no checkpoint {ckpt}")
            continue
        _, estimate, _ = make_estimator(o, "cpu")
        g = torch.Generator().manual_seed(0)
        estimate(mod.to_batch(data, batches[0], device="cpu"), g)  # warm-up
        estimate.calls = estimate.fits = 0
        estimate.seconds = 0.0
        total = 0.0
        for idx in batches:
            batch = mod.to_batch(data, idx, device="cpu")
            t0 = time.perf_counter()
            estimate(batch, g)
            total += time.perf_counter() - t0
        s = estimate.summary(n, total)
        lo_ms = 1e3 * s["lo_seconds_per_instance"]
        own_ms = 1e3 * total / n - lo_ms
        print(f"{method:<12} {1e3 * total / n:9.2f} {lo_ms:8.2f} {own_ms:11.2f} {lo_ms / own_ms:11.3f} "
              f"{s['lo_calls_per_instance']:6.2f} {s['lo_fits_per_instance']:6.1f}")


if __name__ == "__main__":
    main()
