"""What a training set's matches look like, as the synthetic generator's fitted statistics (issue #46, item 2c).

From a prepared two-view batch (numpy arrays, rlsac.data.fundamental's schema) and its ground-truth inliers (the
caller's: the runner gives ``FundamentalTask.true_inliers``, the training reward's threshold): per pair, the inlier
ratio of its points; the SNN ratio's quantiles for inliers and for outliers; the
image positions (x / w, y / h, per image) of inliers and outliers as histograms on a GRID. ``fit`` on the real
training pairs gives what ``rlsac.data.synthetic_pairs`` (snn="fitted") draws from; ``fit`` on the synthetic pairs
it made measures how close they come (``compare``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

QUANTILES = [round(q, 2) for q in np.linspace(0.0, 1.0, 21)]  # the SNN ratio's quantiles kept (0, 0.05, ..., 1)
GRID = (8, 6)  # position histogram cells (x, y) over the image


def _positions(coords: np.ndarray, size: np.ndarray) -> np.ndarray:
    """coords (M, 2) px in images of size (M, 2) -> (M, 2) in [0, 1]."""
    return np.clip(coords / size, 0.0, 1.0 - 1e-9)


def _hist(pos: np.ndarray) -> list[list[float]]:
    h, _, _ = np.histogram2d(pos[:, 0], pos[:, 1], bins=GRID, range=[[0, 1], [0, 1]])
    return (h / max(h.sum(), 1.0)).round(6).tolist()


def fit(batch: dict[str, Any], inliers: np.ndarray) -> dict[str, Any]:
    """batch: coords (P, N, 4) px, features (P, N, >= 5; [..., 4] the SNN ratio), mask (P, N), size1, size2 (P, 2);
    inliers (P, N) bool -> the statistics (JSON-able)."""
    coords, mask = np.asarray(batch["coords"], np.float64), np.asarray(batch["mask"], bool)
    if coords.ndim != 3 or coords.shape[-1] != 4 or mask.shape != coords.shape[:2] or inliers.shape != mask.shape:
        raise ValueError(f"coords (P, N, 4), mask and inliers (P, N) expected, got {coords.shape}, {mask.shape} and "
                         f"{inliers.shape}")
    snn = np.asarray(batch["features"])[..., 4].astype(np.float64)
    inl = np.asarray(inliers, bool) & mask
    out = mask & ~inl
    size1 = np.repeat(np.asarray(batch["size1"], np.float64)[:, None], coords.shape[1], 1)
    size2 = np.repeat(np.asarray(batch["size2"], np.float64)[:, None], coords.shape[1], 1)
    stats: dict[str, Any] = {"pairs": int(coords.shape[0]), "points": int(mask.sum()),
                             "inlier_ratio": (inl.sum(1) / np.maximum(mask.sum(1), 1)).round(6).tolist(),
                             "quantiles": QUANTILES, "grid": list(GRID)}
    for name, sel in (("inliers", inl), ("outliers", out)):
        stats[f"snn_{name}"] = np.quantile(snn[sel], QUANTILES).round(6).tolist() if sel.any() else []
        for i, (xy, size) in enumerate(((coords[..., :2], size1), (coords[..., 2:], size2)), 1):
            stats[f"position{i}_{name}"] = _hist(_positions(xy[sel], size[sel])) if sel.any() else []
    return stats


def compare(real: dict[str, Any], synthetic: dict[str, Any]) -> list[dict[str, Any]]:
    """The fitted statistics beside those of the synthetic pairs: one row per statistic (name, real, synthetic)."""
    rows = [{"statistic": f"inlier ratio per pair, q{int(q * 100)}",
             "real": float(np.quantile(real["inlier_ratio"], q)),
             "synthetic": float(np.quantile(synthetic["inlier_ratio"], q))} for q in (0.25, 0.5, 0.75)]
    for kind in ("inliers", "outliers"):
        for q in (0.1, 0.5, 0.9):
            i = QUANTILES.index(q)
            rows.append({"statistic": f"SNN ratio of the {kind}, q{int(q * 100)}", "real": real[f"snn_{kind}"][i],
                         "synthetic": synthetic[f"snn_{kind}"][i]})
    for kind in ("inliers", "outliers"):
        for img in (1, 2):
            a, b = np.asarray(real[f"position{img}_{kind}"]), np.asarray(synthetic[f"position{img}_{kind}"])
            rows.append({"statistic": f"image-{img} positions of the {kind}: total variation to the real histogram "
                                      f"({GRID[0]}x{GRID[1]} cells)", "real": 0.0,
                         "synthetic": float(0.5 * np.abs(a - b).sum())})
    return rows


def sample_snn(rng: np.random.Generator, quantiles: list[float], n: int) -> np.ndarray:
    """n draws from the distribution whose quantiles at QUANTILES are ``quantiles`` (inverse CDF, linear between)."""
    return np.interp(rng.uniform(0.0, 1.0, n), QUANTILES, quantiles)


def sample_positions(rng: np.random.Generator, hist: list[list[float]], n: int) -> np.ndarray:
    """n positions in [0, 1]^2 from a GRID histogram: a cell by its mass, then uniform within it."""
    h = np.asarray(hist, np.float64)
    cells = rng.choice(h.size, size=n, p=h.ravel() / h.sum())
    ix, iy = np.unravel_index(cells, h.shape)
    return np.stack([(ix + rng.uniform(0, 1, n)) / h.shape[0], (iy + rng.uniform(0, 1, n)) / h.shape[1]], 1)
