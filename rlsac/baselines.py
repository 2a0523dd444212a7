"""Baselines at the same iteration budgets as RLSAC.

``ransac``: our own batched RANSAC for any task (uniform minimal sets, inlier count, refinement on
the best hypothesis' inliers). ``oracle``: the refinement on the true inliers, the best any sampler
followed by that refinement can do (synthetic data only). OpenCV's RANSAC / USAC / MAGSAC++ for
fundamental matrices follow.
"""

from __future__ import annotations

import torch

from rlsac.errors import RlsacError
from rlsac.lo import Best, LOConf, active, finish, update_best
from rlsac.sampling import gather_points, uniform_minimal_sets
from rlsac.tasks import Task


@torch.no_grad()
def ransac(task: Task, batch: dict, iterations: int, generator: torch.Generator | None = None,
           chunk: int = 256, lo: LOConf | None = None) -> dict[str, torch.Tensor]:
    """Plain RANSAC over a batch of instances; with ``lo`` enabled, LO-RANSAC (``rlsac.lo``).

    batch: coords (B, N, d), mask (B, N) -> hyp (B, *H) refined, valid (B,), inliers (B, N),
    best_count (B,) inlier count of the best minimal-set hypothesis. With LO on, the best so far is
    chosen by ``lo.score`` and locally optimised whenever a chunk of ``chunk`` hypotheses improves it
    (once per chunk and instance at most), and the output adds lo_calls, lo_fits (B,), lo_seconds.
    """
    coords, mask = batch["coords"], batch["mask"]
    B, N, _ = coords.shape
    best = Best.empty(B, coords.device)
    for start in range(0, iterations, chunk):
        k = min(chunk, iterations - start)
        idx = uniform_minimal_sets(mask, task.sample_size, k, generator)  # (B, k, m)
        pts = gather_points(coords, idx).flatten(0, 1)  # (B k, m, d)
        hyps, valid = task.solve(pts)
        rep = coords.repeat_interleave(k, 0)
        res = task.residuals(hyps, rep).view(B, k, N)
        count = ((res <= task.threshold) & mask[:, None]).sum(-1)
        count = count.masked_fill(~valid.view(B, k), -1)
        best = update_best(task, lo, coords, mask, best, hyps.view(B, k, *hyps.shape[1:]), count, res, generator)
    if active(lo):
        return finish(task, lo, coords, mask, best, generator)
    return finalize(task, coords, mask, best.hyp, best.count >= task.sample_size)


@torch.no_grad()
def oracle(task: Task, batch: dict) -> dict[str, torch.Tensor]:
    """The task's refinement on the ground-truth inliers: an upper bound for sample consensus.

    batch: coords (B, N, d), mask (B, N), inlier_mask (B, N) true inliers -> hyp, valid, inliers,
    best_count as ``ransac``. Rows with fewer true inliers than the refinement needs are invalid.
    """
    coords, mask = batch["coords"], batch["mask"]
    if "inlier_mask" not in batch:
        raise RlsacError("the oracle needs the true inlier mask (synthetic data only)")
    truth = torch.as_tensor(batch["inlier_mask"], dtype=torch.bool, device=coords.device) & mask
    hyp, valid = task.refine(coords, truth)
    inl = (task.residuals(hyp, coords) <= task.threshold) & mask & valid[:, None]
    return {"hyp": hyp, "valid": valid, "inliers": inl, "best_count": inl.sum(-1)}


def finalize(task: Task, coords, mask, hyp, valid) -> dict[str, torch.Tensor]:
    """Refine ``hyp`` on its inliers; keep the unrefined hypothesis where refinement fails."""
    inl = (task.residuals(hyp, coords) <= task.threshold) & mask & valid[:, None]
    ref, ok = task.refine(coords, inl)
    ok = ok & valid
    hyp = torch.where(ok.view(-1, *[1] * (hyp.dim() - 1)), ref, hyp)
    inl = (task.residuals(hyp, coords) <= task.threshold) & mask & valid[:, None]
    return {"hyp": hyp, "valid": valid, "inliers": inl, "best_count": inl.sum(-1)}


# OpenCV defaults from the CVPR 2020 RANSAC tutorial's starter pack (github.com/ducha-aiki/ransac-tutorial-2020-data,
# create_F_submission.py / eval_F_submission.py argparse defaults for ~1000 px PhotoTourism images): inlier
# threshold 0.75 px, confidence 0.999 (maxiter 100k there; we pass ``iterations`` instead). The tutorial tunes only
# the threshold (grid 0.1..1.0 px) and gives no per-method value, so all four methods share these defaults.
OPENCV_F_THRESHOLD = 0.75
OPENCV_F_CONFIDENCE = 0.999
OPENCV_F_METHODS = {"ransac": "FM_RANSAC", "usac": "USAC_DEFAULT", "usac_accurate": "USAC_ACCURATE",
                    "magsac": "USAC_MAGSAC", "prosac": "USAC_PROSAC"}


def opencv_fundamental(batch: dict, method: str, iterations: int, threshold: float | None = None,
                       confidence: float | None = None, seed: int = 0, quality=None) -> dict:
    """OpenCV robust F estimation per batch row on its valid (mask) correspondences.

    batch: coords (B, N, 4) pixels, mask (B, N) -> hyp np (B, 3, 3) unit Frobenius norm (zero where
    invalid), valid np bool (B,), inliers np bool (B, N). method: ransac | usac | usac_accurate |
    magsac | prosac (cv2.FM_RANSAC, USAC_DEFAULT, USAC_ACCURATE, USAC_MAGSAC, USAC_PROSAC), maxIters = iterations.
    prosac needs the correspondences ordered best first: ``quality`` (B, N), lower = better (the task's
    ``match_quality``, the SNN ratio), puts them in ascending order, ties in the seeded random order.

    Seeding: the method presets are only reachable through the flag API, whose RNG state is fixed, so
    ``seed`` permutes the correspondences before the call (which changes every random draw) and the
    inlier mask is permuted back. Rows with < 8 correspondences, a None result or a non-finite F are
    invalid; OpenCV's stacked (3k, 3) output keeps its first F.
    """
    import cv2
    import numpy as np

    from rlsac.errors import RlsacError

    if method not in OPENCV_F_METHODS:
        raise RlsacError(f"unknown OpenCV method {method!r} (known: {', '.join(OPENCV_F_METHODS)})")
    flag = getattr(cv2, OPENCV_F_METHODS[method])
    thr = OPENCV_F_THRESHOLD if threshold is None else float(threshold)
    conf = OPENCV_F_CONFIDENCE if confidence is None else float(confidence)
    coords = batch["coords"]
    coords = coords.detach().cpu().numpy() if isinstance(coords, torch.Tensor) else np.asarray(coords)
    mask = batch["mask"]
    mask = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    B, N = mask.shape
    hyp = np.zeros((B, 3, 3))
    valid = np.zeros(B, dtype=bool)
    inliers = np.zeros((B, N), dtype=bool)
    rng = np.random.default_rng(seed)
    if method == "prosac" and quality is None:
        raise RlsacError("prosac needs the matches' quality to order them (quality=task.match_quality(batch))")
    if quality is not None:
        quality = quality.detach().cpu().numpy() if isinstance(quality, torch.Tensor) else np.asarray(quality)
    for b in range(B):
        idx = np.flatnonzero(mask[b])
        if idx.size < 8:
            continue
        idx = idx[rng.permutation(idx.size)]
        if method == "prosac":
            idx = idx[np.argsort(quality[b, idx], kind="stable")]
        pts = coords[b, idx].astype(np.float64)
        try:
            F, inl = cv2.findFundamentalMat(np.ascontiguousarray(pts[:, :2]), np.ascontiguousarray(pts[:, 2:4]),
                                            flag, thr, conf, int(iterations))
        except cv2.error:
            continue
        if F is None or F.size < 9 or inl is None:
            continue
        F = np.asarray(F, np.float64)[:3, :3]
        norm = np.linalg.norm(F)
        if not np.isfinite(F).all() or norm == 0:
            continue
        hyp[b] = F / norm
        valid[b] = True
        inliers[b, idx] = np.asarray(inl).ravel().astype(bool)
    return {"hyp": hyp, "valid": valid, "inliers": inliers}
