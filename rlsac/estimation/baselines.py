"""Baselines at the same iteration budgets as RLSAC.

``ransac``: our own batched RANSAC for any task (uniform minimal sets, inlier count, refinement on
the best hypothesis' inliers). ``oracle``: the refinement on the true inliers, the best any sampler
followed by that refinement can do (synthetic data only). OpenCV's RANSAC / USAC / MAGSAC++ for
fundamental matrices follow, then the peers of issue #29 (DEGENSAC, PoseLib) through the same loop.
"""

from __future__ import annotations

import torch

from rlsac.errors import RlsacError
from rlsac.estimation.lo import Best, LOConf, active, finish, score_sets, update_best
from rlsac.estimation.sampling import gather_points, uniform_minimal_sets, weighted_minimal_sets
from rlsac.tasks import Task


@torch.no_grad()
def ransac(task: Task, batch: dict, iterations: int, generator: torch.Generator | None = None,
           chunk: int = 256, lo: LOConf | None = None, logits: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Plain RANSAC over a batch of instances; with ``lo`` enabled, LO-RANSAC (``rlsac.estimation.lo``); with ``logits``
    (B, N), every minimal set drawn from softmax(logits) over the valid points instead of uniformly (NG-RANSAC's
    learned sampler, ``rlsac.rl.ngransac``: the same budget, scoring, LO and final refit).

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
        idx = (uniform_minimal_sets(mask, task.sample_size, k, generator) if logits is None
               else weighted_minimal_sets(logits, mask, task.sample_size, k, generator))  # (B, k, m)
        hyps, valid, res, count = score_sets(task, gather_points(coords, idx), coords, mask)  # (B, k, ...)
        best = update_best(task, lo, coords, mask, best, hyps, count.masked_fill(~valid, -1), res, generator)
    out = finish(task, lo, coords, mask, best, generator) if active(lo) else finalize(
        task, coords, mask, best.hyp, best.count >= task.sample_size)
    out["hypotheses"] = torch.full((B,), iterations, dtype=torch.long, device=coords.device)  # every set is scored
    return out


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
    """Refine ``hyp`` on its inliers (unless the task's ``refit_output`` is off); keep the unrefined
    hypothesis where refinement fails."""
    inl = (task.residuals(hyp, coords) <= task.threshold) & mask & valid[:, None]
    if getattr(task, "refit_output", True):
        ref, ok = task.refine(coords, inl)
        ok = ok & valid
        hyp = torch.where(ok.view(-1, *[1] * (hyp.dim() - 1)), ref, hyp)
        inl = (task.residuals(hyp, coords) <= task.threshold) & mask & valid[:, None]
    return {"hyp": hyp, "valid": valid, "inliers": inl, "best_count": inl.sum(-1)}


# OpenCV's robust estimators by method flag; the task's ``opencv_fit`` calls its own OpenCV function
# (findFundamentalMat, findEssentialMat) with the flag. The confidence is the CVPR 2020 RANSAC tutorial's
# (github.com/ducha-aiki/ransac-tutorial-2020-data, create_F_submission.py: 0.999; maxiter 100k there, we pass
# ``iterations``); each task gives its threshold (``opencv_threshold``).
OPENCV_CONFIDENCE = 0.999
OPENCV_FLAGS = {"ransac": "RANSAC", "usac": "USAC_DEFAULT", "usac_accurate": "USAC_ACCURATE",
                "magsac": "USAC_MAGSAC", "prosac": "USAC_PROSAC"}
# The no-LO arm (issue #26): USAC's sampler and score without local optimisation and without the final polisher
# (cv2.UsacParams: LOCAL_OPTIM_NULL, NONE_POLISHER), beside our samplers that have neither: method -> (sampler,
# score) as in the presets of the same name
OPENCV_NOLO = {"usac-nolo": ("SAMPLING_UNIFORM", "SCORE_METHOD_MSAC"),
               "magsac-nolo": ("SAMPLING_UNIFORM", "SCORE_METHOD_MAGSAC"),
               "prosac-nolo": ("SAMPLING_PROSAC", "SCORE_METHOD_MSAC")}


def usac_params(method: str, threshold: float, confidence: float, iterations: int, seed: int):
    """cv2.UsacParams of a no-LO method (``OPENCV_NOLO``): its sampler and score, no LO, no polisher, seeded."""
    import cv2

    sampler, score = OPENCV_NOLO[method]
    p = cv2.UsacParams()
    p.sampler, p.score = getattr(cv2, sampler), getattr(cv2, score)
    p.loMethod, p.final_polisher = cv2.LOCAL_OPTIM_NULL, cv2.NONE_POLISHER
    p.threshold, p.confidence, p.maxIterations = float(threshold), float(confidence), int(iterations)
    p.randomGeneratorState, p.isParallel = int(seed), False
    return p


def opencv_estimate(task: Task, batch: dict, method: str, iterations: int, threshold: float | None = None,
                    confidence: float | None = None, seed: int = 0, quality=None) -> dict:
    """OpenCV's robust estimator of ``task`` (its ``opencv_fit``) per batch row on its valid points.

    batch: coords (B, N, d), mask (B, N) -> hyp np (B, *H) (zero where invalid), valid np bool (B,),
    inliers np bool (B, N). method: ransac | usac | usac_accurate | magsac | prosac (cv2.RANSAC,
    USAC_DEFAULT, USAC_ACCURATE, USAC_MAGSAC, USAC_PROSAC), maxIters = iterations. prosac needs the
    points ordered best first: ``quality`` (B, N), lower = better (the task's ``match_quality``), puts
    them in ascending order, ties in the seeded random order.

    Seeding: the method presets are only reachable through the flag API, whose RNG state is fixed, so
    ``seed`` permutes the points before the call (which changes every random draw) and the inlier mask
    is permuted back. Rows with fewer points than the task's minimal set or no result are invalid.
    """
    import cv2
    import numpy as np

    if method not in OPENCV_FLAGS and method not in OPENCV_NOLO:
        raise RlsacError(f"unknown OpenCV method {method!r} (known: {', '.join([*OPENCV_FLAGS, *OPENCV_NOLO])})")
    if not hasattr(task, "opencv_fit"):
        raise RlsacError(f"task '{task.name}' has no OpenCV estimator")
    thr = task.opencv_threshold if threshold is None else float(threshold)
    conf = OPENCV_CONFIDENCE if confidence is None else float(confidence)
    # a preset flag, or the no-LO arm's UsacParams (seeded by ``seed``; the permutation below changes its draws too)
    flag = getattr(cv2, OPENCV_FLAGS[method]) if method in OPENCV_FLAGS else usac_params(method, thr, conf, iterations,
                                                                                          seed)
    order = None
    if method.startswith("prosac"):
        if quality is None:
            raise RlsacError("prosac needs the matches' quality to order them (quality=task.match_quality(batch))")
        quality = _numpy(quality)
        order = lambda b, idx: idx[np.argsort(quality[b, idx], kind="stable")]  # noqa: E731
    return fit_rows(task, batch, seed, lambda pts, rng: task.opencv_fit(pts, flag, thr, conf, int(iterations)),
                    conf, int(iterations), order)


def fit_rows(task: Task, batch: dict, seed: int, fit, confidence: float, iterations: int, order=None) -> dict:
    """A per-pair library estimator over a batch: each row's valid points in a seeded random order (``order(b, idx)``
    may reorder them, e.g. PROSAC's best first), ``fit(pts (n, d) float64, rng)`` -> None or (hyp, inliers (n,)[,
    hypotheses or None]), the inliers permuted back. A library whose RNG state is fixed per call (OpenCV's flag API)
    draws differently for a different ``seed`` this way.

    -> hyp np (B, *H) (zero where invalid), valid np bool (B,), inliers np bool (B, N), hypotheses np int (B,): the
    count the library reports, else its stopping rule's bound (``stop_bound`` at ``confidence``, ``iterations``);
    rows with fewer points than the minimal set or no result are invalid (their count is ``iterations``)."""
    import numpy as np

    coords, mask = _numpy(batch["coords"]), _numpy(batch["mask"]).astype(bool)
    B, N = mask.shape
    hyp, valid, inliers = np.zeros((B, *task.hypothesis_shape)), np.zeros(B, dtype=bool), np.zeros((B, N), dtype=bool)
    hypotheses = np.full(B, int(iterations), dtype=np.int64)
    rng = np.random.default_rng(seed)
    for b in range(B):
        idx = np.flatnonzero(mask[b])
        if idx.size < task.sample_size:
            continue
        idx = idx[rng.permutation(idx.size)]
        if order is not None:
            idx = order(b, idx)
        out = fit(np.ascontiguousarray(coords[b, idx], dtype=np.float64), rng)
        if out is None:
            continue
        hyp[b], valid[b] = out[0], True
        inliers[b, idx] = out[1]
        reported = out[2] if len(out) > 2 else None
        hypotheses[b] = reported if reported is not None else stop_bound(
            int(np.count_nonzero(out[1])), idx.size, task.sample_size, confidence, int(iterations))
    return {"hyp": hyp, "valid": valid, "inliers": inliers, "hypotheses": hypotheses}


def stop_bound(n_inliers: int, n_points: int, m: int, confidence: float, iterations: int) -> int:
    """Hypotheses RANSAC's stopping rule allows at the final inlier ratio w = n_inliers / n_points:
    min(iterations, ceil(log(1 - p) / log(1 - w^m))). OpenCV does not report how many hypotheses it scored;
    its RANSAC-family stop is this bound (SPRT and LO change it), so this is what the tables report for it."""
    import math

    w = n_inliers / max(n_points, 1)
    if w <= 0.0 or confidence <= 0.0:
        return iterations
    miss = 1.0 - w**m
    if miss <= 0.0:
        return 1
    if miss >= 1.0:  # w^m below double precision (a handful of inliers): the rule never stops
        return iterations
    return int(min(iterations, max(1, math.ceil(math.log(1.0 - confidence) / math.log(miss)))))


def _numpy(x):
    import numpy as np

    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


# Peers (issue #29): robust estimators researchers use, called through the task's ``<method>_fit`` (DEGENSAC:
# pydegensac, F only; PoseLib: F and the calibrated relative pose). Each runs its own LO and final refinement (the
# "own LO+polish" arm, as OpenCV's USAC presets), with the OpenCV rows' threshold and stopping confidence.
PEERS = ("degensac", "poselib")


def peer_estimate(task: Task, batch: dict, method: str, iterations: int, threshold: float | None = None,
                  confidence: float | None = None, seed: int = 0) -> dict:
    """A peer estimator (``PEERS``) of ``task`` per batch row on its valid points.

    batch: coords (B, N, d), mask (B, N) -> hyp np (B, *H), valid np bool (B,), inliers np bool (B, N), hypotheses
    np int (B,) (the count the library reports, else its stopping rule's bound). ``seed`` permutes the points and
    seeds the library's RNG per row (``fit_rows``), so the same seed gives the same results.
    """
    if method not in PEERS:
        raise RlsacError(f"unknown peer method {method!r} (known: {', '.join(PEERS)})")
    fit = getattr(task, f"{method}_fit", None)
    if fit is None:
        raise RlsacError(f"task '{task.name}' has no {method} estimator")
    thr = task.opencv_threshold if threshold is None else float(threshold)
    conf = OPENCV_CONFIDENCE if confidence is None else float(confidence)
    return fit_rows(task, batch, seed, lambda pts, rng: fit(pts, thr, conf, int(iterations),
                                                            int(rng.integers(0, 2**31 - 1))), conf, int(iterations))
