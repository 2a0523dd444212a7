"""Synthetic two-view pairs in the prepared-file schema (rlsac.data.fundamental): random scenes, camera pairs, pixel
noise and outliers, with ground-truth poses, so every fundamental-matrix method and metric runs on them unchanged.

Used by the learner's positive control (issue #46, item 2d; benchmarks/positive_control.py): with
``snn="separable"`` the SNN channel separates the true inliers by construction (inliers U(0, 0.5), outliers
U(0.5, 1)), so a sampler that reads it can reach the oracle; ``snn="uninformative"`` draws it U(0, 1) for every
point; ``snn="fitted"`` draws what a real training set's matches show (``statistics``, rlsac.data.match_statistics):
each pair's inlier ratio from the real pairs' ratios, the SNN ratio of inliers and of outliers from their real
quantiles, the outliers' image positions from their real histograms (the inliers' come from the scene's geometry).
The descriptor channels are noise at the scale of RootSIFT (U(0, 0.2)): they carry nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rlsac.data import match_statistics as ms
from rlsac.data.fundamental import N_FEATURES
from rlsac.errors import RlsacError

SNN_MODES = ("separable", "uninformative", "fitted")
# where each pair's inlier ratio and the outliers' image positions come from; "auto": from ``statistics`` exactly when
# snn="fitted" (the generator as the scale study fitted it), else the fixed ``inlier_ratio`` and uniform positions.
# The learner's ladder (rlsac.experiments.ladder) sets them apart, one change per rung.
SOURCES = ("auto", "fixed", "fitted")
POSITIONS = ("auto", "uniform", "fitted")


@dataclass
class SyntheticPairsConf:
    n_pairs: int = 200
    n_points: int = 150  # the paper's N
    inlier_ratio: float = 0.3  # below the hard regime's ~0.45: sampling matters
    noise_px: float = 0.5  # Gaussian pixel noise of the inliers (both images)
    snn: str = "separable"
    width: float = 1000.0  # image size (px) and focal length: a Strecha-like 1000 x 750 camera
    height: float = 750.0
    focal: float = 800.0
    seed: int = 0
    statistics: dict[str, Any] = field(default_factory=dict)  # snn="fitted": match_statistics.fit of real pairs
    ratios: str = "auto"  # SOURCES: "fitted" draws each pair's inlier ratio from statistics["inlier_ratio"]
    positions: str = "auto"  # POSITIONS: "fitted" draws the outliers' positions from the statistics' histograms

    def fitted_ratios(self) -> bool:
        return self.ratios == "fitted" or (self.ratios == "auto" and self.snn == "fitted")

    def fitted_positions(self) -> bool:
        return self.positions == "fitted" or (self.positions == "auto" and self.snn == "fitted")

    def check(self) -> None:
        if self.n_pairs < 1 or self.n_points < 8:
            raise RlsacError(f"need n_pairs >= 1 and n_points >= 8, got {self.n_pairs}, {self.n_points}")
        if not 0.0 < self.inlier_ratio <= 1.0:
            raise RlsacError(f"inlier_ratio must be in (0, 1], got {self.inlier_ratio}")
        if self.snn not in SNN_MODES:
            raise RlsacError(f"snn must be one of {SNN_MODES}, got {self.snn!r}")
        if self.ratios not in SOURCES or self.positions not in POSITIONS:
            raise RlsacError(f"ratios must be one of {SOURCES} and positions one of {POSITIONS}, got "
                             f"{self.ratios!r}, {self.positions!r}")
        need = [*(("snn_inliers", "snn_outliers") if self.snn == "fitted" else ()),
                *(("inlier_ratio",) if self.fitted_ratios() else ()),
                *(("position1_outliers", "position2_outliers") if self.fitted_positions() else ())]
        if any(not self.statistics.get(k) for k in need):
            raise RlsacError(f"snn={self.snn!r}, ratios={self.ratios!r}, positions={self.positions!r} need statistics "
                             f"with {', '.join(need)} (rlsac.data.match_statistics.fit)")


def _rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(deg)
    return np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S


def generate(conf: SyntheticPairsConf) -> dict[str, np.ndarray]:
    """-> arrays of a prepared file (coords (P, N, 4) px, features (P, N, 261), mask, K1, K2, dR, dT, size1,
    size2, pair, scene) plus ``inliers`` (P, N) bool, the points generated as inliers."""
    conf.check()
    rng = np.random.default_rng(conf.seed)
    P, N, W, H = conf.n_pairs, conf.n_points, conf.width, conf.height
    K = np.array([[conf.focal, 0, W / 2], [0, conf.focal, H / 2], [0, 0, 1]])
    coords = np.zeros((P, N, 4), np.float32)
    feats = np.zeros((P, N, N_FEATURES), np.float32)
    inl = np.zeros((P, N), bool)
    Rs, ts = np.zeros((P, 3, 3)), np.zeros((P, 3))
    st = conf.statistics
    for p in range(P):
        ratio = rng.choice(st["inlier_ratio"]) if conf.fitted_ratios() else conf.inlier_ratio
        n_in = min(N, max(8, int(round(N * ratio))))
        R = _rotation(rng.normal(size=3), rng.uniform(5, 25))
        t = np.array([1.0, rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)])
        t /= np.linalg.norm(t)
        pts = np.zeros((0, 4))
        while len(pts) < n_in:  # points in front of both cameras and inside both images
            X = np.stack([rng.uniform(-4, 4, 4 * N), rng.uniform(-3, 3, 4 * N), rng.uniform(4, 12, 4 * N)], 1)
            X2 = X @ R.T + t
            x1, x2 = X @ K.T, X2 @ K.T
            x1, x2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
            ok = (X2[:, 2] > 0) & (x1 >= 0).all(1) & (x1 < [W, H]).all(1) & (x2 >= 0).all(1) & (x2 < [W, H]).all(1)
            pts = np.concatenate([pts, np.concatenate([x1, x2], 1)[ok]])
        pts = pts[:n_in] + rng.normal(scale=conf.noise_px, size=(n_in, 4))
        if conf.fitted_positions():  # where real outliers lie in each image
            outl = np.concatenate([ms.sample_positions(rng, st["position1_outliers"], N - n_in) * [W, H],
                                   ms.sample_positions(rng, st["position2_outliers"], N - n_in) * [W, H]], 1)
        else:
            outl = rng.uniform([0, 0, 0, 0], [W, H, W, H], size=(N - n_in, 4))
        order = rng.permutation(N)
        coords[p] = np.concatenate([pts, outl])[order]
        inl[p] = (np.arange(N) < n_in)[order]
        if conf.snn == "separable":
            snn = np.where(inl[p], rng.uniform(0.0, 0.5, N), rng.uniform(0.5, 1.0, N))
        elif conf.snn == "fitted":
            snn = np.where(inl[p], ms.sample_snn(rng, st["snn_inliers"], N), ms.sample_snn(rng, st["snn_outliers"], N))
        else:
            snn = rng.uniform(0.0, 1.0, N)
        feats[p, :, :4], feats[p, :, 4] = coords[p], snn
        feats[p, :, 5:] = rng.uniform(0.0, 0.2, (N, N_FEATURES - 5))
        Rs[p], ts[p] = R, t
    size = np.tile(np.array([W, H], np.int32), (P, 1))
    return {"coords": coords, "features": feats, "mask": np.ones((P, N), bool), "K1": np.repeat(K[None], P, 0),
            "K2": np.repeat(K[None], P, 0), "dR": Rs, "dT": ts, "size1": size, "size2": size.copy(),
            "pair": np.array([f"synthetic-{conf.seed}-{p}" for p in range(P)], dtype=object),
            "scene": np.array(["synthetic"] * P, dtype=object), "inliers": inl}
