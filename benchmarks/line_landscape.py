"""The line generator's calibration landscape (issue #27, item 0): mAA and median error together, and the ceiling.

    python benchmarks/line_landscape.py [--instances 500] [--seeds 123,124] [--maa-tol 0.03] [--median-tol 0.01]
                                        [--confirm-joint 2] [--confirm-low 2] [--confirm-seeds 4] [--grid JSON]
                                        [--out reports/calibration_landscape]

Runs our 150-iteration RANSAC, the oracle and the true line's consensus on every generator setting of the grid
(``rlsac.data.line_calibration``) at the paper's seven outlier rates, ranks the settings by the joint criterion
(mAA within ``--maa-tol`` and median within ``--median-tol`` deg of the paper's RANSAC row at every rate), runs the
best ``--confirm-joint`` settings by joint and the best ``--confirm-low`` by joint over the rates 0.1-0.5 again with
``rlsac calibrate-lines``' protocol (1000 instances, ``--confirm-seeds`` data seeds from 123) and writes
``<out>.md``, ``<out>.csv`` (one row per setting) and ``<out>_rates.csv`` (one row per setting and rate). The
default generator is not changed. Single-threaded: about 4 CPU minutes.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rlsac.experiments import line_calibration as lc  # noqa: E402
from rlsac.io import atomic_path, write_text  # noqa: E402

UNIFORM_BANDS = [0.03, 0.035, 0.04, 0.045, 0.05, 0.06, 0.07, 0.0825, 0.1]
GAUSSIAN_SDS = [0.02, 0.0225, 0.025, 0.0275, 0.03, 0.035, 0.04, 0.05, 0.06]
GRID = [
    {"noise": ["uniform"], "band": UNIFORM_BANDS, "line": ["point_angle", "two_points", "angle_offset"]},
    {"noise": ["gaussian"], "band": GAUSSIAN_SDS, "line": ["point_angle", "two_points", "angle_offset"]},
    {"noise": ["uniform"], "band": UNIFORM_BANDS, "line": ["two_points"], "extent": ["segment"]},
    {"noise": ["gaussian"], "band": GAUSSIAN_SDS, "line": ["two_points"], "extent": ["segment"]},
]


def grid_text(grid: list[dict]) -> str:
    return "; ".join(" × ".join(f"{k} ∈ {{{', '.join(f'{v:g}' if isinstance(v, float) else str(v) for v in vals)}}}"
                                for k, vals in g.items()) for g in grid)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--instances", type=int, default=500, help="instances per rate and seed in the grid")
    ap.add_argument("--seeds", default="123,124", help="data seeds of the grid")
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--maa-tol", type=float, default=0.03)
    ap.add_argument("--median-tol", type=float, default=0.01)
    ap.add_argument("--confirm-joint", type=int, default=2, help="best settings by joint run again (calibrate-lines)")
    ap.add_argument("--confirm-low", type=int, default=2, help="and the best by joint over the rates 0.1-0.5")
    ap.add_argument("--confirm-instances", type=int, default=1000)
    ap.add_argument("--confirm-seeds", type=int, default=4, help="data seeds 123.. of the confirmation")
    ap.add_argument("--grid", help="JSON: a list of {field: [values]} grids [default: the grid above]")
    ap.add_argument("--out", default="reports/calibration_landscape", help="output stem (.md, .csv, _rates.csv)")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    grid = json.loads(args.grid) if args.grid else GRID
    settings = lc.expand(grid)
    seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    out = Path(args.out)
    t0 = time.perf_counter()

    def progress(i, s, row):
        print(f"[{i + 1}/{len(settings)} {time.perf_counter() - t0:6.0f}s] {lc.describe(s):55s} joint "
              f"{row['joint']:6.2f}  oracle@0.7 {row['oracle_mAA_0.7']:.3f}", flush=True)

    summary, per_rate = lc.landscape(settings, maa_tol=args.maa_tol, median_tol=args.median_tol, progress=progress,
                                     n_instances=args.instances, seeds=seeds, iterations=args.iterations)
    confirmed = []
    for i in lc.to_confirm(summary, args.confirm_joint, args.confirm_low):
        c = lc.confirm(settings[i], n_instances=args.confirm_instances, n_seeds=args.confirm_seeds,
                       maa_tol=args.maa_tol, median_tol=args.median_tol, iterations=args.iterations, device="cpu")
        print(f"confirmed {lc.describe(settings[i])}: joint {c['joint']:.2f}, low {c['joint_low']:.2f}", flush=True)
        confirmed.append(c)
    command = "python benchmarks/line_landscape.py" + "".join(
        f" --{k.replace('_', '-')} {shlex.quote(str(v))}" for k, v in vars(args).items()
        if v is not None and v != ap.get_default(k))
    meta = {"command": command, "n_instances": args.instances, "seeds": seeds, "maa_tol": args.maa_tol,
            "median_tol": args.median_tol, "iterations": args.iterations, "grid": grid_text(grid)}
    with atomic_path(out.with_suffix(".csv")) as tmp:
        summary.to_csv(tmp, index=False, float_format="%.4f")
    with atomic_path(out.parent / f"{out.name}_rates.csv") as tmp:
        per_rate.to_csv(tmp, index=False, float_format="%.4f")
    write_text(out.with_suffix(".md"), lc.landscape_markdown(summary, confirmed, meta))
    print(f"wrote {out}.md, {out}.csv, {out}_rates.csv in {time.perf_counter() - t0:.0f}s")


if __name__ == "__main__":
    main()
