"""Synthetic 2D-line instances (paper Sec. 4.2) and their h5 files.

Per instance: a ground-truth line through two uniform points of the [0, S]^2 picture; round(N(1-rho))
true inliers spread uniformly along the part of the line inside the picture and displaced
uniformly within +-band of it; the remaining points uniform over the picture (outliers may fall in
the band, as the paper allows). ``band``, the noise model and the along-line spread are the knobs the
paper leaves open; their defaults were calibrated so that our 150-iteration RANSAC reproduces the paper's RANSAC
row of Table 1 (see reports/calibration_lines.md; mAA and median together: reports/calibration_landscape.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import torch

from rlsac.data import validity
from rlsac.errors import RlsacError
from rlsac.io import atomic_path, open_h5, read_array


@dataclass
class LineDataConf:
    outlier_rate: float = 0.5
    n_instances: int = 1000
    n_points: int = 100  # the paper's N
    picture_size: float = 10.0  # the paper's 10 x 10 picture
    # inlier half-width (the sd with noise="gaussian"); paper: "within a range of 0.1"; calibrated on RANSAC, 12 seeds
    band: float = 0.0825
    # ground-truth line: "two_points" (through two uniform points), "point_angle" (one uniform point,
    # uniform direction) or "angle_offset" (uniform direction, uniform offset among lines meeting the picture)
    line: str = "point_angle"  # calibrated: two_points gives too few hard (short-chord) instances
    inlier_count: str = "fixed"  # round(N(1-rho)) inliers, as the paper words it; "binomial": each w.p. 1-rho
    extent: str = "chord"  # inliers spread along the whole chord in the picture, or the "segment" p0-p1
    # perpendicular inlier displacement: "uniform" in +-band (the paper's "uniformly disturbed"), or "gaussian"
    # N(0, band^2), a peaked core with a tail, for the joint mAA / median calibration (reports/calibration_landscape.md)
    noise: str = "uniform"
    seed: int = 0

    # checked by rlsac.config.build (outlier_rate and the counts by check(), with their own messages)
    ranges = {"picture_size": "(0, inf)", "band": "[0, inf)", "line": ("two_points", "point_angle", "angle_offset"),
              "inlier_count": ("fixed", "binomial"), "extent": ("chord", "segment"),
              "noise": ("uniform", "gaussian"), "seed": "[0, 4294967295]"}

    def check(self) -> None:
        if not 0.0 <= self.outlier_rate < 1.0:
            raise RlsacError(f"outlier rate must be in [0, 1), got {self.outlier_rate}")
        if self.n_instances <= 0 or self.n_points <= 0:
            raise RlsacError(f"counts must be positive (n_instances={self.n_instances}, n_points={self.n_points})")
        if round(self.n_points * (1 - self.outlier_rate)) < 2:
            raise RlsacError(f"{self.n_points} points at outlier rate {self.outlier_rate} leave fewer than 2 inliers")
        if self.extent not in ("chord", "segment"):
            raise RlsacError(f"extent must be 'chord' or 'segment', got {self.extent!r}")
        if self.line not in ("two_points", "point_angle", "angle_offset"):
            raise RlsacError(f"line must be two_points, point_angle or angle_offset, got {self.line!r}")
        if self.inlier_count not in ("fixed", "binomial"):
            raise RlsacError(f"inlier_count must be 'fixed' or 'binomial', got {self.inlier_count!r}")
        if self.noise not in ("uniform", "gaussian"):
            raise RlsacError(f"noise must be 'uniform' or 'gaussian', got {self.noise!r}")
        if self.band < 0 or self.picture_size <= 0:
            raise RlsacError("band must be >= 0 and picture_size > 0")


def _chord(p: np.ndarray, d: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Parameter interval [t0, t1] of p + t d inside [0, size]^2 (d unit, p inside). (I,2) -> (I,), (I,)"""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (0.0 - p) / d
        tb = (size - p) / d
    lo = np.nanmax(np.where(np.isfinite(ta), np.minimum(ta, tb), -np.inf), axis=1)
    hi = np.nanmin(np.where(np.isfinite(ta), np.maximum(ta, tb), np.inf), axis=1)
    return lo, hi


def generate(conf: LineDataConf) -> dict[str, np.ndarray]:
    """-> points (I, N, 2) float32, line (I, 3) float64 as (a, b, c), inlier_mask (I, N) bool."""
    conf.check()
    rng = np.random.default_rng(conf.seed)
    I, N, S = conf.n_instances, conf.n_points, conf.picture_size
    if conf.inlier_count == "fixed":
        n_in = np.full(I, int(round(N * (1 - conf.outlier_rate))))
    else:
        n_in = np.maximum(rng.binomial(N, 1 - conf.outlier_rate, size=I), 2)

    p0 = rng.uniform(0, S, size=(I, 2))
    p1 = rng.uniform(0, S, size=(I, 2))
    if conf.line != "two_points":
        theta = rng.uniform(0, np.pi, size=I)
        d = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        if conf.line == "angle_offset":
            n = np.stack([-d[:, 1], d[:, 0]], axis=1)
            corners = np.array([[0, 0], [S, 0], [0, S], [S, S]], dtype=float)
            proj = n @ corners.T  # (I, 4) offsets of the corners along the normal
            off = rng.uniform(proj.min(1), proj.max(1))
            centre_t = (np.full((I, 2), S / 2) * d).sum(1)
            p0 = off[:, None] * n + (centre_t[:, None] * d)  # on the line, nearest the picture centre
        p1 = p0 + d
    same = np.linalg.norm(p1 - p0, axis=1) < 1e-3
    p1[same] += 1.0
    d = (p1 - p0) / np.linalg.norm(p1 - p0, axis=1, keepdims=True)
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1)
    if conf.extent == "chord":
        lo, hi = _chord(p0, d, S)
    else:
        lo, hi = np.zeros(I), np.linalg.norm(p1 - p0, axis=1)

    t = rng.uniform(lo[:, None], hi[:, None], size=(I, N))
    if conf.noise == "uniform":
        off = rng.uniform(-conf.band, conf.band, size=(I, N))
    else:
        off = rng.normal(0.0, conf.band, size=(I, N))
    inl = p0[:, None] + t[..., None] * d[:, None] + off[..., None] * normal[:, None]
    out = rng.uniform(0, S, size=(I, N, 2))
    mask = np.arange(N)[None, :] < n_in[:, None]
    pts = np.where(mask[..., None], inl, out)
    perm = np.argsort(rng.random((I, N)), axis=1)
    pts = np.take_along_axis(pts, perm[..., None], axis=1)
    mask = np.take_along_axis(mask, perm, axis=1)
    line = np.concatenate([normal, -(normal * p0).sum(1, keepdims=True)], axis=1)
    return {"points": pts.astype(np.float32), "line": line, "inlier_mask": mask}


def write(path: str | Path, data: dict[str, np.ndarray], conf: LineDataConf) -> Path:
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for k, v in data.items():
                f.create_dataset(k, data=v, compression="gzip" if v.size > 10000 else None)
            for k, v in vars(conf).items():
                # the noise model is written only when it is not the default: files made before the option existed
                # (the committed record's line data, and what was evaluated on them) stay byte for byte the same
                if k != "noise" or v != LineDataConf.noise:
                    f.attrs[k] = v
            f.attrs["kind"] = "rlsac-lines"
    return Path(path)


def read(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """Read and validate a lines h5 file -> (arrays, attrs).

    Instances whose geometry is meaningless (``instance_problems``) are left out of the arrays and reported in
    ``attrs["unusable"]`` (rlsac.data.validity.keep_usable); a file without a usable instance is an RlsacError.
    The arrays of the usable instances are the file's, unchanged."""
    with open_h5(path) as f:
        pts = read_array(f, "points", (None, None, 2))
        line = read_array(f, "line", (pts.shape[0], 3))
        mask = read_array(f, "inlier_mask", pts.shape[:2])
        attrs = dict(f.attrs)
    if pts.shape[0] == 0:
        raise RlsacError(f"{path}: key 'points' holds no instances")
    if pts.shape[1] < 2:
        raise RlsacError(f"{path}: instances need at least 2 points, got {pts.shape[1]}")
    size = attrs.get("picture_size", LineDataConf.picture_size)
    if not (isinstance(size, (int, float, np.number)) and np.isfinite(size) and size > 0):
        raise RlsacError(f"{path}: attribute 'picture_size' must be a positive number, got {size!r}")
    out = {"points": pts, "line": line, "inlier_mask": mask.astype(bool)}
    out, report = validity.keep_usable(out, instance_problems(out, float(size)), None, path, "instance")
    if report:
        attrs[validity.REPORT] = report
    return out, attrs


def instance_problems(data: dict[str, np.ndarray], picture_size: float) -> np.ndarray:
    """What makes each instance unusable (rlsac.data.validity): identical points, points outside the picture,
    a ground-truth line with a zero normal or one that misses the picture. data: ``read``'s arrays, P
    instances -> (P,) reasons, "" for a usable instance."""
    checks = validity.line_points(data["points"], picture_size) + validity.ground_truth_lines(data["line"],
                                                                                                picture_size)
    return validity.first_problem(checks, len(data["points"]))


def to_batch(data: dict[str, np.ndarray], idx=slice(None), device: str | torch.device = "cpu") -> dict:
    """Slice arrays into the batch dict the environment and the baselines consume."""
    coords = torch.as_tensor(data["points"][idx], dtype=torch.float32, device=device)
    return {
        "coords": coords,
        "mask": torch.ones(coords.shape[:2], dtype=torch.bool, device=device),
        "line": data["line"][idx],
        "inlier_mask": data["inlier_mask"][idx],
    }
