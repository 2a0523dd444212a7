"""Speed of the batched 8-point solver / residuals and accuracy of the F baselines on synthetic scenes.

    python benchmarks/fundamental_solvers.py [--pairs 64] [--iterations 1000] [--outliers 0.3] [--noise 0.5]

Synthetic two-view scenes (1000x750 px, f = 800, random 5-20 deg rotation, sideways baseline, N = 150,
uniform outliers in image 2); prints timings and the tutorial metrics (mAA@10 of R, t, max(R, t)).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from rlsac.estimation.baselines import opencv_estimate, ransac
from rlsac.estimation.sampling import gather_points, uniform_minimal_sets
from rlsac.tasks.fundamental import FundamentalTask


def _rot(rng) -> np.ndarray:
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    th = np.radians(rng.uniform(5, 20))
    S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S


def synthetic_batch(B: int, N: int = 150, outlier_rate: float = 0.3, noise: float = 0.5, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    w, h = 1000.0, 750.0
    K = np.array([[800.0, 0, w / 2], [0, 800.0, h / 2], [0, 0, 1]])
    coords, Rs, ts = np.zeros((B, N, 4), np.float32), [], []
    for b in range(B):
        R, t = _rot(rng), np.array([1.0, rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)])
        X = np.stack([rng.uniform(-4, 4, 20 * N), rng.uniform(-3, 3, 20 * N), rng.uniform(5, 10, 20 * N)], 1)
        X2 = X @ R.T + t
        x1, x2 = X @ K.T, X2 @ K.T
        x1, x2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
        ok = (X2[:, 2] > 0) & (x1 >= 0).all(1) & (x1 < [w, h]).all(1) & (x2 >= 0).all(1) & (x2 < [w, h]).all(1)
        pts = np.concatenate([x1, x2], 1)[ok][:N] + rng.normal(scale=noise, size=(N, 4))
        out = rng.choice(N, int(round(N * outlier_rate)), replace=False)
        pts[out, 2:] = rng.uniform([0, 0], [w, h], size=(out.size, 2))
        coords[b] = pts
        Rs.append(R)
        ts.append(t)
    Ks, size = np.repeat(K[None], B, 0), np.tile([w, h], (B, 1))
    return {"coords": torch.from_numpy(coords), "mask": torch.ones(B, N, dtype=torch.bool),
            "features": torch.zeros(B, N, 261), "K1": Ks, "K2": Ks.copy(), "dR": np.stack(Rs), "dT": np.stack(ts),
            "size1": size, "size2": size.copy()}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=64)
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--outliers", type=float, default=0.3)
    ap.add_argument("--noise", type=float, default=0.5)
    args = ap.parse_args()
    batch = synthetic_batch(args.pairs, outlier_rate=args.outliers, noise=args.noise)
    task = FundamentalTask()

    idx = uniform_minimal_sets(batch["mask"], 8, 256, torch.Generator().manual_seed(0))
    pts = gather_points(batch["coords"], idx).flatten(0, 1)
    t0 = time.perf_counter()
    F, valid = task.solve(pts)
    t1 = time.perf_counter()
    task.residuals(F, batch["coords"].repeat_interleave(256, 0))
    t2 = time.perf_counter()
    print(f"8-point: {pts.shape[0]} samples in {t1 - t0:.3f} s ({valid.float().mean():.3f} valid); "
          f"Sampson residuals ({pts.shape[0]} x {batch['coords'].shape[1]}) in {t2 - t1:.3f} s")

    rows = []
    for name in ("ransac", "usac", "usac_accurate", "magsac"):
        t0 = time.perf_counter()
        out = opencv_estimate(FundamentalTask(), batch, name, args.iterations)
        rows.append((f"opencv {name}", time.perf_counter() - t0, task.errors(out["hyp"], out["valid"], out["inliers"],
                                                                              batch)))
    for thr in (4.0, 1.0):
        tk = FundamentalTask(threshold=thr)
        t0 = time.perf_counter()
        out = ransac(tk, batch, args.iterations, torch.Generator().manual_seed(0))
        rows.append((f"ours ransac eps={thr}", time.perf_counter() - t0, tk.errors(out["hyp"], out["valid"],
                                                                                   out["inliers"], batch)))
    print(f"{'method':24s} {'time/pair ms':>12s} {'mAA_R':>6s} {'mAA_t':>6s} {'mAA':>6s} {'med_R':>6s} {'med_t':>6s}")
    for name, dt, e in rows:
        s = task.summarize(e)
        print(f"{name:24s} {1000 * dt / args.pairs:12.2f} {s['mAA_R']:6.3f} {s['mAA_t']:6.3f} {s['mAA']:6.3f} "
              f"{s['median_R']:6.2f} {s['median_t']:6.2f}")


if __name__ == "__main__":
    main()
