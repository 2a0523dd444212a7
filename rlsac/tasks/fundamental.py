"""Fundamental-matrix estimation (paper Sec. 4.3): m = 8, normalised 8-point solver, epipolar residuals.

A hypothesis is a 3x3 F with unit Frobenius norm in pixel coordinates, x2^T F x1 = 0. Evaluation
follows the CVPR 2020 RANSAC tutorial (ducha-aiki/ransac-tutorial-2020-data, utils.eval_essential_matrix):
E = K2^T F K1, cv2.recoverPose on the estimated inliers in calibrated coordinates, rotation error =
angle of R_est R_gt^T, translation error = angle between directions ignoring sign, and the tutorial
score mAA@10deg of max(err_R, err_t) over the thresholds 1, 2, ..., 10 deg.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import torch

from rlsac.data import fundamental as fundamental_data
from rlsac.errors import RlsacError
from rlsac.layout.protocol import FOLD_CHECKPOINT, FOLD_STAGES
from rlsac.maths import geometry, metrics
from rlsac.tasks.registry import register_task

RESIDUALS = ("sampson", "sampson_sq", "symmetric")
MAX_ERR_R = 180.0  # a failed estimate counts as the maximal error (tutorial: pi and pi/2 rad)
MAX_ERR_T = 90.0
MIN_POSE_INLIERS = 5  # the tutorial's eval_essential_matrix fails below 5 inliers


@register_task
@dataclass
class FundamentalTask:
    experiment: ClassVar[str] = "fundamental"
    default_iterations: ClassVar[int] = 1000  # Table 2's budget
    residual_dof: ClassVar[int] = 4  # as OpenCV's MAGSAC++ for F
    true_inlier_data: ClassVar[bool] = False
    # its part in the fold benchmark (rlsac.experiments.folds puts these into the protocol it runs, so that no module
    # branches on a task's name): the params section naming its rows, the `folds` stages it has, where a fold's models
    # live ({model} the row's model, {seed} "-s<seed>" or ""), and what its rows of our samplers tune after threshold x
    # pre-filter
    fold_rows: ClassVar[str] = "folds"
    fold_stages: ClassVar[tuple[str, ...]] = FOLD_STAGES
    fold_checkpoint: ClassVar[str] = FOLD_CHECKPOINT
    sampler_knobs: ClassVar[tuple[str, ...]] = ()
    read = staticmethod(fundamental_data.read)
    to_batch = staticmethod(fundamental_data.to_batch)

    # eps = 4 (paper) read as the squared Sampson error (px^2, i.e. 2 px; residual="sampson" reads it as 4 px): the
    # training reward's threshold. Evaluation thresholds are tuned per fold and method on validation
    # (rlsac.evaluation.tune);
    # how this reading was picked, and what it saw: reports/folds.md ("Protocol")
    threshold: float = 4.0
    # "sampson_sq" (px^2), "sampson" (px) or "symmetric" (RMS of the two point-to-epipolar-line distances, px)
    residual: str = "sampson_sq"
    use_descriptors: bool = True  # ablation: False drops the two 128-d SIFT descriptors (c = 5)
    # False hides the SNN ratio from the policy (not in the paper): does it learn anything beyond ranking by SNN?
    use_snn: bool = True
    refine_iterations: int = 0  # extra Sampson-reweighted least-squares passes in ``refine``
    maa_limit_deg: float = 10.0  # Table 2 reports mAA@10 deg (thresholds 1..10 deg)

    name: str = "fundamental"
    sample_size: int = 8
    coord_dim: int = 4
    solutions: int = 1

    def __post_init__(self) -> None:
        if self.residual not in RESIDUALS:
            raise RlsacError(f"unknown residual {self.residual!r} (known: {', '.join(RESIDUALS)})")
        if self.refine_iterations < 0:
            raise RlsacError(f"refine_iterations must be >= 0, got {self.refine_iterations}")

    @property
    def feature_dim(self) -> int:
        return 4 + int(self.use_snn) + 256 * int(self.use_descriptors)

    # ----------------------------------------------------------------------------- network input
    def features(self, batch: dict) -> torch.Tensor:
        """[x1, y1, x2, y2] centred on each image and divided by its max(w, h), then (each optional) the SNN
        ratio and the descriptors as stored in batch["features"][..., 4:]. Padded rows are zero. -> (B, N, c)"""
        coords, feats = batch["coords"], batch["features"]
        dev, dt = coords.device, coords.dtype
        s1 = torch.as_tensor(np.asarray(batch["size1"]), dtype=dt, device=dev)  # (B, 2) w, h
        s2 = torch.as_tensor(np.asarray(batch["size2"]), dtype=dt, device=dev)
        c1 = (coords[..., :2] - s1[:, None] / 2) / s1.amax(-1)[:, None, None]
        c2 = (coords[..., 2:4] - s2[:, None] / 2) / s2.amax(-1)[:, None, None]
        extra = [feats[..., 4:5]] if self.use_snn else []
        extra += [feats[..., 5:261]] if self.use_descriptors else []
        out = torch.cat([c1, c2, *[e.to(dt) for e in extra]], dim=-1)
        return out * batch["mask"][..., None].to(dt)

    def match_quality(self, batch: dict) -> torch.Tensor:
        """Per-correspondence side information the samplers may use without ground truth: the SNN
        ratio (second-nearest-neighbour descriptor ratio, lower = more distinctive). -> (B, N)"""
        return batch["features"][..., 4].to(batch["coords"].dtype)

    def true_inliers(self, batch: dict) -> torch.Tensor:
        """Ground-truth inlier labels (B, N) bool: Sampson distance to the ground-truth F within the
        inlier threshold (supervised warm start only; the paper's RLSAC never sees them)."""
        F = fundamental_data.gt_fundamental(_np(batch["K1"]), _np(batch["K2"]), _np(batch["dR"]), _np(batch["dT"]))
        F = torch.as_tensor(F, dtype=batch["coords"].dtype, device=batch["coords"].device)
        return (self.residuals(F, batch["coords"]) <= self.threshold) & batch["mask"]

    # ------------------------------------------------------------------------------- geometry
    def solve(self, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pts (B, 8, 4) -> F (B, 3, 3), valid (B,) (False for degenerate samples; F is then 0)."""
        return geometry.eight_point(pts)

    def residuals(self, hyps: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """hyps (B, 3, 3), coords (B, N, 4) -> (B, N) in the unit of ``residual``; +inf for F = 0.
        hyps (B, S, 3, 3) -> (B, S, N)."""
        if self.residual == "sampson":
            return geometry.sampson_distance(hyps, coords)
        if self.residual == "sampson_sq":
            return geometry.sampson_distance(hyps, coords, squared=True)
        if hyps.dim() == 4:
            B, S = hyps.shape[:2]
            return self.residuals(hyps.flatten(0, 1), coords.repeat_interleave(S, 0)).view(B, S, -1)
        return (geometry.symmetric_epipolar_distance(hyps, coords, squared=True) / 2).sqrt()

    def refine(self, coords: torch.Tensor, inliers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Least-squares 8-point on the inliers, then ``refine_iterations`` passes reweighted by the
        inverse Sampson gradient (so the algebraic cost approximates the Sampson error) on the same set.

        coords (B, N, 4), inliers (B, N) bool -> F (B, 3, 3), valid (B,) (False with < 8 inliers).
        """
        F, valid = geometry.eight_point(coords, inliers)
        for _ in range(self.refine_iterations):
            _, l2, l1 = geometry.epipolar_terms(F.double(), coords.double())
            den = l2[..., :2].square().sum(-1) + l1[..., :2].square().sum(-1)
            w = inliers.double() / den.clamp_min(1e-30)
            w = w / w.amax(-1, keepdim=True).clamp_min(1e-30)
            F2, ok = geometry.eight_point(coords, torch.where(valid[:, None], w, inliers.double()))
            keep = ok & valid
            F = torch.where(keep[:, None, None], F2, F)
        return F, valid

    # ----------------------------------------------------------------------------- OpenCV baselines
    # The CVPR 2020 tutorial's starter-pack threshold for ~1000 px images (create_F_submission.py), used when no
    # tuned value is given; the tutorial tunes the threshold and an SNN pre-filter per method on validation
    # (rlsac.evaluation.tune, params.yaml tuning), as the fold benchmark does.
    opencv_threshold: ClassVar[float] = 0.75
    hypothesis_shape: ClassVar[tuple[int, ...]] = (3, 3)

    def px_thresholds(self, px: float) -> tuple[float, float]:
        """An inlier threshold of ``px`` pixels -> (``threshold`` in this task's residual unit, OpenCV's threshold):
        px^2 for the squared Sampson error, px for the others; OpenCV's findFundamentalMat takes pixels."""
        px = float(px)
        return (px * px if self.residual == "sampson_sq" else px), px

    @staticmethod
    def opencv_fit(pts: np.ndarray, flag: int, threshold: float, confidence: float, iterations: int):
        """cv2.findFundamentalMat on pts (n, 4) pixels -> (F (3, 3) unit Frobenius norm, inliers (n,) bool),
        None on failure (OpenCV's stacked (3k, 3) output keeps its first F). ``flag``: a method preset, or a
        cv2.UsacParams that holds the threshold, confidence and budget itself."""
        p1, p2 = np.ascontiguousarray(pts[:, :2]), np.ascontiguousarray(pts[:, 2:4])
        try:
            if isinstance(flag, cv2.UsacParams):
                F, inl = cv2.findFundamentalMat(p1, p2, flag)
            else:
                F, inl = cv2.findFundamentalMat(p1, p2, flag, threshold, confidence, iterations)
        except cv2.error:
            return None
        return opencv_model(F, inl)

    # ----------------------------------------------------------------------------- peers (issue #29)
    @staticmethod
    def degensac_fit(pts: np.ndarray, threshold: float, confidence: float, iterations: int, seed: int):
        """pydegensac.findFundamentalMatrix (DEGENSAC: LO-RANSAC with a check for a dominant plane) on pts (n, 4)
        pixels, Sampson error at ``threshold`` px -> (F, inliers) or None. ``seed`` (>= 0) seeds pydegensac's RNG:
        its default (-1) seeds it from the clock, so two runs on the same pairs could differ."""
        import pydegensac

        if seed < 0:
            raise ValueError(f"DEGENSAC needs a seed >= 0 (a negative one seeds it from the clock), got {seed}")
        F, inl = pydegensac.findFundamentalMatrix(np.ascontiguousarray(pts[:, :2]), np.ascontiguousarray(pts[:, 2:4]),
                                                  float(threshold), float(confidence), int(iterations),
                                                  seed=int(seed))
        out = opencv_model(F, inl)
        return None if out is None else (*out, None)

    @staticmethod
    def poselib_fit(pts: np.ndarray, threshold: float, confidence: float, iterations: int, seed: int):
        """poselib.estimate_fundamental (LO-RANSAC, then bundle adjustment of F on the inliers) on pts (n, 4)
        pixels, epipolar error at ``threshold`` px -> (F, inliers, hypotheses scored) or None."""
        import poselib

        F, info = poselib.estimate_fundamental(np.ascontiguousarray(pts[:, :2]), np.ascontiguousarray(pts[:, 2:4]),
                                               poselib_ransac(threshold, confidence, iterations, seed), {})
        out = opencv_model(F, info.get("inliers"))
        return None if out is None else (*out, int(info["iterations"]))

    # ----------------------------------------------------------------------------- evaluation
    def errors(self, hyps, valid, inliers, batch) -> dict[str, np.ndarray]:
        """Tutorial pose errors in degrees: {'err_R': (B,), 'err_t': (B,)}; failures get 180 / 90."""
        hyps = _np(hyps).astype(np.float64)
        valid = _np(valid).astype(bool)
        inliers = _np(inliers).astype(bool) & _np(batch["mask"]).astype(bool)
        coords = _np(batch["coords"]).astype(np.float64)
        K1, K2 = np.asarray(batch["K1"], np.float64), np.asarray(batch["K2"], np.float64)
        dR, dT = np.asarray(batch["dR"], np.float64), np.asarray(batch["dT"], np.float64).reshape(-1, 3)
        B = hyps.shape[0]
        err_R, err_t = np.full(B, MAX_ERR_R), np.full(B, MAX_ERR_T)
        for b in range(B):
            pose = self.pose(hyps[b], K1[b], K2[b], coords[b, inliers[b]]) if valid[b] else None
            if pose is None:
                continue
            R, t = pose
            err_R[b] = metrics.rotation_error_deg(R, dR[b])
            err_t[b] = metrics.translation_error_deg(t, dT[b])
        return {"err_R": err_R, "err_t": err_t}

    @staticmethod
    def pose(hyp: np.ndarray, K1: np.ndarray, K2: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(R, t) of a hypothesis (3, 3) from its inliers pts (n, 4), None on failure."""
        return relative_pose_from_fundamental(hyp, K1, K2, pts)

    def summarize(self, errors: dict[str, np.ndarray]) -> dict[str, float]:
        eR, et = np.asarray(errors["err_R"], np.float64), np.asarray(errors["err_t"], np.float64)
        lim = self.maa_limit_deg
        return {
            "mAA_R": metrics.mAA(eR, lim), "mAA_t": metrics.mAA(et, lim), "mAA": metrics.mAA(np.maximum(eR, et), lim),
            "median_R": metrics.median(eR), "median_t": metrics.median(et), "n": int(eR.size),
        }


def poselib_ransac(threshold: float, confidence: float, iterations: int, seed: int) -> dict:
    """PoseLib's RansacOptions with the benchmark's budget and stopping confidence (its other options are its
    defaults; min_iterations, 100 by default, never above the budget)."""
    return {"max_epipolar_error": float(threshold), "success_prob": float(confidence),
            "max_iterations": int(iterations), "min_iterations": min(100, int(iterations)), "seed": int(seed)}


def opencv_model(M, inl) -> tuple[np.ndarray, np.ndarray] | None:
    """An OpenCV two-view estimator's output (a (3k, 3) stack of 3 x 3 models, the inlier mask) -> (its first
    model with unit Frobenius norm, inliers (n,) bool); None when there is none or it is not finite / zero."""
    if M is None or M.size < 9 or inl is None:
        return None
    M = np.asarray(M, np.float64)[:3, :3]
    norm = np.linalg.norm(M)
    if not np.isfinite(M).all() or norm == 0:
        return None
    return M / norm, np.asarray(inl).ravel().astype(bool)


def relative_pose_from_fundamental(F: np.ndarray, K1: np.ndarray, K2: np.ndarray, pts: np.ndarray
                                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t) from F via E = K2^T F K1 and cv2.recoverPose on calibrated points (K^-1 x).

    F, K1, K2 (3, 3), pts (n, 4) pixels -> R (3, 3), t (3,); None when F is not finite / zero, n < 5
    or recoverPose fails.
    """
    if not np.all(np.isfinite(F)) or np.abs(F).sum() == 0:
        return None
    return recover_pose(K2.T @ F @ K1, _calibrate(pts[:, :2], K1), _calibrate(pts[:, 2:4], K2))


def recover_pose(E: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(R, t) from an essential matrix and calibrated inliers p1, p2 (n, 2) by cv2.recoverPose (the
    tutorial's cheirality check); None when E is not finite / zero, n < 5 or recoverPose fails."""
    if not np.all(np.isfinite(E)) or np.abs(E).sum() == 0 or p1.shape[0] < MIN_POSE_INLIERS:
        return None
    p1, p2 = np.ascontiguousarray(p1, np.float64), np.ascontiguousarray(p2, np.float64)
    try:
        _, R, t, _ = cv2.recoverPose(E, p1, p2)
    except cv2.error:
        return None
    if R is None or t is None or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None
    return R, t.reshape(3)


def _calibrate(x: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) -> normalised image coordinates (n, 2) through K^-1 (skew included)."""
    h = np.concatenate([x, np.ones_like(x[:, :1])], axis=1) @ np.linalg.inv(K).T
    return np.ascontiguousarray(h[:, :2] / h[:, 2:3])


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
