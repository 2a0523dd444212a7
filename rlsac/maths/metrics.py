"""Angular errors and mean Average Accuracy (mAA).

mAA(errors, limit, n) = mean over the n thresholds limit/n, 2 limit/n, ..., limit of the fraction of
errors at or below each threshold (Barath et al. 2022; the CVPR 2020 RANSAC tutorial). Failed
estimates carry an infinite (or maximal) error and so count as misses at every threshold.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def thresholds(limit: float, n: int = 10) -> np.ndarray:
    return limit * np.arange(1, n + 1) / n


def accuracy_per_instance(errors: np.ndarray, limit: float, n: int = 10) -> np.ndarray:
    """(M,) errors -> (M,) fraction of the n thresholds each error meets; mAA is its mean."""
    errors = np.asarray(errors, dtype=np.float64).ravel()
    errors = np.where(np.isnan(errors), np.inf, errors)
    return (errors[:, None] <= thresholds(limit, n)[None, :]).mean(axis=1)


def mAA(errors: np.ndarray, limit: float, n: int = 10) -> float:
    acc = accuracy_per_instance(errors, limit, n)
    return float(acc.mean()) if acc.size else float("nan")


def paired_bootstrap_maa(errors_a, errors_b, limit: float, n_boot: int = 2000, seed: int = 0,
                         level: float = 0.95) -> tuple[float, float, float]:
    """mAA(a) - mAA(b) on the same instances, with a paired percentile bootstrap interval.

    errors_a, errors_b: (M,) errors of two methods on the same M instances (NaN = failure).
    Returns (difference, low, high); resampling instances, not errors, keeps the pairing, which is
    what makes small differences between methods on one test set measurable.
    """
    a = np.asarray(errors_a, dtype=np.float64).ravel()
    b = np.asarray(errors_b, dtype=np.float64).ravel()
    if a.size != b.size or a.size == 0:
        raise ValueError(f"paired bootstrap needs two non-empty error lists of one length, got {a.size} and {b.size}")
    acc_a, acc_b = accuracy_per_instance(a, limit), accuracy_per_instance(b, limit)
    diff = acc_a - acc_b
    idx = np.random.default_rng(seed).integers(0, a.size, size=(n_boot, a.size))
    boot = diff[idx].mean(axis=1)
    tail = 100 * (1 - level) / 2
    # the difference of the two mAAs, computed as seed_bootstrap_maa does: the mean of the differences can fall on
    # the other side of a rounding half (-0.0085 printed -0.009 in Table 1 and -0.008 in claims.md; issue #47)
    return float(acc_a.mean() - acc_b.mean()), float(np.percentile(boot, tail)), float(np.percentile(boot, 100 - tail))


def seed_bootstrap_maa(errors_a, errors_b, limit: float, strata=None, n_boot: int = 2000, seed: int = 0,
                       level: float = 0.95, paired_seeds: bool = False) -> dict[str, float]:
    """mAA(a) - mAA(b) across training seeds, on the same instances, with a hierarchical bootstrap interval.

    errors_a: (S_a, M) errors of S_a training seeds of a method on M instances; errors_b: (S_b, M) of another
    (S_b = 1 for a method that is not trained), the instances in the same order (NaN = failure). strata: (M,)
    labels (buildings); instances are resampled within each stratum, keeping its size. Each bootstrap draw
    resamples the seeds of each method with replacement, then the instances (the same draw for both methods: the
    pairing), and takes the difference of the seed means: the interval covers training noise as well as the
    choice of test pairs (issue #27).

    Returns {"diff", "lo", "hi"} (the seed means' difference and its interval), {"mean_a", "sd_a", "mean_b",
    "sd_b"} (seed mean and seed-to-seed standard deviation of each method's mAA; sd 0 for one seed) and
    "p_improve": the probability that a random seed of a beats a random seed of b on a random stratum (rliable's
    probability of improvement with the strata as its tasks, ties counting one half).

    paired_seeds: row s of a and of b come from the same training run (e.g. two checkpoints of one run,
    rlsac.experiments.selection): each draw picks the same seeds for both (S_a = S_b), as it picks the same instances.
    """
    a, b = (np.atleast_2d(np.asarray(e, dtype=np.float64)) for e in (errors_a, errors_b))
    if a.shape[1] != b.shape[1] or a.shape[1] == 0 or 0 in (a.shape[0], b.shape[0]):
        raise ValueError(f"seed bootstrap needs (S, M) errors of one M > 0, got {a.shape} and {b.shape}")
    m = a.shape[1]
    strata = _strata(strata, m)
    acc_a = np.stack([accuracy_per_instance(e, limit) for e in a])  # (S_a, M)
    acc_b = np.stack([accuracy_per_instance(e, limit) for e in b])
    rng = np.random.default_rng(seed)
    idx = stratified_draws(rng, strata, n_boot)  # (n_boot, M): the same instances for a and b
    per_a, per_b = acc_a[:, idx].mean(axis=2), acc_b[:, idx].mean(axis=2)  # (S, n_boot): each seed's resampled mAA
    pick_a = rng.integers(0, len(acc_a), size=(n_boot, len(acc_a)))
    if paired_seeds and len(acc_a) != len(acc_b):
        raise ValueError(f"paired seeds need as many seeds in a as in b, got {len(acc_a)} and {len(acc_b)}")
    pick_b = pick_a if paired_seeds else rng.integers(0, len(acc_b), size=(n_boot, len(acc_b)))
    cols = np.arange(n_boot)[:, None]
    boot = per_a[pick_a, cols].mean(axis=1) - per_b[pick_b, cols].mean(axis=1)
    tail = 100 * (1 - level) / 2
    maa_a, maa_b = acc_a.mean(axis=1), acc_b.mean(axis=1)
    wins = []
    for k in np.unique(strata):  # P(a > b) per stratum over every pair of seeds, then averaged over strata
        ka, kb = acc_a[:, strata == k].mean(axis=1), acc_b[:, strata == k].mean(axis=1)
        wins.append(((ka[:, None] > kb[None, :]) + 0.5 * (ka[:, None] == kb[None, :])).mean())
    return {"diff": float(maa_a.mean() - maa_b.mean()), "lo": float(np.percentile(boot, tail)),
            "hi": float(np.percentile(boot, 100 - tail)), "mean_a": float(maa_a.mean()),
            "sd_a": float(maa_a.std(ddof=1)) if len(maa_a) > 1 else 0.0, "mean_b": float(maa_b.mean()),
            "sd_b": float(maa_b.std(ddof=1)) if len(maa_b) > 1 else 0.0, "p_improve": float(np.mean(wins))}


def _strata(strata, m: int) -> np.ndarray:
    strata = np.zeros(m, dtype=np.int64) if strata is None else np.asarray(strata)
    if strata.shape != (m,):
        raise ValueError(f"strata must have one label per instance ({m}), got shape {strata.shape}")
    return strata


def stratified_draws(rng: np.random.Generator, strata: np.ndarray, n_boot: int) -> np.ndarray:
    """(n_boot, M) instance indices, each draw resampling every stratum within itself (its size kept)."""
    return np.concatenate([rng.choice(np.flatnonzero(strata == k), size=(n_boot, int((strata == k).sum())))
                           for k in np.unique(strata)], axis=1)


def seed_bootstrap_median(errors_a, errors_b, strata=None, n_boot: int = 2000, seed: int = 0,
                          level: float = 0.95) -> dict[str, float]:
    """median(a) - median(b) across training seeds, on the same instances: ``seed_bootstrap_maa``'s hierarchical
    bootstrap (seeds of each method, then the instances within their stratum, the same draw for both) with each
    seed's median error in place of its mAA; a failure (NaN) counts as an infinite error, as in ``median``.

    Returns {"diff", "lo", "hi", "mean_a", "mean_b"}: the seed means of the medians, their difference and its
    interval (lower is better: a negative difference favours a)."""
    a, b = (np.atleast_2d(np.asarray(e, dtype=np.float64)) for e in (errors_a, errors_b))
    if a.shape[1] != b.shape[1] or a.shape[1] == 0 or 0 in (a.shape[0], b.shape[0]):
        raise ValueError(f"seed bootstrap needs (S, M) errors of one M > 0, got {a.shape} and {b.shape}")
    a, b = (np.where(np.isnan(e), np.inf, e) for e in (a, b))
    strata = _strata(strata, a.shape[1])
    rng = np.random.default_rng(seed)
    idx = stratified_draws(rng, strata, n_boot)
    per_a, per_b = np.median(a[:, idx], axis=2), np.median(b[:, idx], axis=2)  # (S, n_boot)
    pick_a = rng.integers(0, len(a), size=(n_boot, len(a)))
    pick_b = rng.integers(0, len(b), size=(n_boot, len(b)))
    cols = np.arange(n_boot)[:, None]
    boot = per_a[pick_a, cols].mean(axis=1) - per_b[pick_b, cols].mean(axis=1)
    tail = 100 * (1 - level) / 2
    med_a, med_b = np.median(a, axis=1), np.median(b, axis=1)
    return {"diff": float(med_a.mean() - med_b.mean()), "lo": float(np.percentile(boot, tail)),
            "hi": float(np.percentile(boot, 100 - tail)), "mean_a": float(med_a.mean()), "mean_b": float(med_b.mean())}


def median(errors: np.ndarray) -> float:
    errors = np.asarray(errors, dtype=np.float64).ravel()
    if errors.size == 0:
        return float("nan")
    return float(np.median(np.where(np.isnan(errors), np.inf, errors)))


def line_angle_deg(n_est: np.ndarray, n_gt: np.ndarray) -> np.ndarray:
    """Angle between undirected lines given by their normals (..., 2) -> degrees in [0, 90]."""
    a = n_est / np.linalg.norm(n_est, axis=-1, keepdims=True)
    b = n_gt / np.linalg.norm(n_gt, axis=-1, keepdims=True)
    cos = np.clip(np.abs((a * b).sum(-1)), 0.0, 1.0)
    return np.degrees(np.arccos(cos))


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> np.ndarray:
    """Angle of R_est R_gt^T. (..., 3, 3) -> (...) degrees in [0, 180]."""
    tr = np.einsum("...ij,...ij->...", R_est, R_gt)  # trace(R_est @ R_gt.T)
    return np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))


def translation_error_deg(t_est: np.ndarray, t_gt: np.ndarray) -> np.ndarray:
    """Angle between translation directions ignoring sign. (..., 3) -> (...) degrees in [0, 90]."""
    t_est, t_gt = _as_vec3(t_est), _as_vec3(t_gt)
    na = np.linalg.norm(t_est, axis=-1)
    nb = np.linalg.norm(t_gt, axis=-1)
    cos = np.abs((t_est * t_gt).sum(-1)) / np.maximum(na * nb, 1e-15)
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def _as_vec3(t) -> np.ndarray:
    """(..., 3) or column vectors (..., 3, 1) -> (..., 3) float64."""
    t = np.asarray(t, dtype=np.float64)
    return t[..., 0] if t.ndim >= 2 and t.shape[-2:] == (3, 1) else t


def _per_seed_draws(values: np.ndarray, idx: np.ndarray, kind: str) -> np.ndarray:
    """(n_boot, S) statistic of each seed on each draw's instances: values (1 or n_boot, S, M) per-instance accuracy
    (kind "maa": the mean) or error (kind "median"), idx (n_boot, M) the draws' instances."""
    got = np.take_along_axis(values, idx[:, None, :], axis=2)
    return got.mean(axis=2) if kind == "maa" else np.median(got, axis=2)


def contrast_bootstrap(rows: list[tuple[float, np.ndarray, np.ndarray | None]], kind: str, limit: float | None = None,
                       strata=None, n_boot: int = 2000, seed: int = 0, level: float = 0.95) -> dict[str, Any]:
    """Σ_k w_k·stat(row_k), stat the seed mean of mAA (kind "maa", at ``limit``) or of the median error (kind
    "median"), with two 95% intervals (issue #62):

    rows: (w_k, full_k, draws_k): full_k (S_k, M) errors of the row's S_k training seeds at its tables' settings;
    draws_k (V, S_k, M) or None: the row's errors with the setting re-chosen on validation resample v (None: the
    row's settings do not move, e.g. fixed settings or a learned row whose per-seed tuning the seed spread holds).
    Every row with draws has the same V, and draw v is the same validation resample for all of them (the pairing).

    Each bootstrap draw resamples the instances within their stratum (the same for every row), then each row's seeds
    (as ``seed_bootstrap_maa``, with the same random stream: with two rows "lo"/"hi" are its interval), and, for the
    interval with selection ("sel_lo"/"sel_hi"), one validation resample from a second stream, on which every row
    with draws takes its re-chosen setting. -> {"diff", "lo", "hi", "sel_lo", "sel_hi", "means", "selection"}
    (sel_* equal lo/hi when no row has draws; "selection": whether one had)."""
    if kind not in ("maa", "median") or (kind == "maa" and limit is None):
        raise ValueError(f"contrast kind must be maa (with a limit) or median, got {kind!r}")
    fulls = [np.atleast_2d(np.asarray(f, dtype=np.float64)) for _, f, _ in rows]
    m = fulls[0].shape[1]
    if m == 0 or any(f.shape[1] != m or not f.shape[0] for f in fulls):
        raise ValueError(f"contrast needs (S, M) errors of one M > 0, got {[f.shape for f in fulls]}")
    vs = {np.shape(d)[0] for _, _, d in rows if d is not None}
    if len(vs) > 1:
        raise ValueError(f"re-selected rows with different numbers of validation draws {sorted(vs)}")

    def values(e):  # what the statistic averages (mAA) or takes the median of, per instance
        e = np.asarray(e, dtype=np.float64)
        if kind == "median":
            return np.where(np.isnan(e), np.inf, e)
        return np.reshape([accuracy_per_instance(r, limit) for r in e.reshape(-1, m)], e.shape)

    strata = _strata(strata, m)
    rng = np.random.default_rng(seed)
    idx = stratified_draws(rng, strata, n_boot)
    picks = [rng.integers(0, len(f), size=(n_boot, len(f))) for f in fulls]
    v = np.random.default_rng([seed, 1]).integers(0, vs.pop(), n_boot) if vs else None
    cols = np.arange(n_boot)[:, None]
    boot, sel, means = np.zeros(n_boot), np.zeros(n_boot), []
    for (w, _, d), f, pick in zip(rows, fulls, picks, strict=True):
        fixed = _per_seed_draws(values(f)[None], idx, kind)[cols, pick].mean(axis=1)
        boot += w * fixed
        if d is None:
            sel += w * fixed
        else:
            dv = np.asarray(d, dtype=np.float64)
            if dv.shape[1:] != f.shape:
                raise ValueError(f"a row's draws {dv.shape} do not match its errors {f.shape}")
            sel += w * _per_seed_draws(values(dv)[v], idx, kind)[cols, pick].mean(axis=1)
        per = values(f).mean(axis=1) if kind == "maa" else np.median(values(f), axis=1)
        means.append(float(per.mean()))
    tail = 100 * (1 - level) / 2
    lo, hi = np.percentile(boot, [tail, 100 - tail])
    s_lo, s_hi = np.percentile(sel, [tail, 100 - tail])
    return {"diff": float(sum(w * mu for (w, _, _), mu in zip(rows, means, strict=True))), "lo": float(lo),
            "hi": float(hi), "sel_lo": float(s_lo), "sel_hi": float(s_hi), "means": means, "selection": v is not None}
