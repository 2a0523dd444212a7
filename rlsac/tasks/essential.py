"""Essential-matrix estimation (not in the paper): calibrated correspondences, as in the CVPR 2020
RANSAC tutorial's essential-matrix track. m = 5, Nister's five-point solver (kornia's batched one, up
to 10 solutions per minimal set, the best-scoring one kept by ``rlsac.estimation.lo.score_sets``), Sampson
residuals in normalised image coordinates, least-squares refit projected onto the essential manifold.

The data are the prepared two-view files of the fundamental task (rlsac.data.fundamental); this task's
``to_batch`` replaces the pixel coordinates by calibrated ones, K^-1 x (pixels kept as "pixels").
Pose errors and mAA are the fundamental task's (cv2.recoverPose on the inliers, the tutorial's metric).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
import torch

from rlsac.data import fundamental as fundamental_data
from rlsac.errors import RlsacError
from rlsac.maths import geometry
from rlsac.tasks.fundamental import FundamentalTask, opencv_model, poselib_ransac, recover_pose
from rlsac.tasks.registry import register_task

# Our Strecha copy is imported at 1024 x 683 px with f = 920 px (every pair), so thresholds in normalised
# units are pixels / 920.
STRECHA_FOCAL = 920.0


@register_task
@dataclass
class EssentialTask(FundamentalTask):
    experiment: ClassVar[str] = "essential"
    default_iterations: ClassVar[int] = 1000  # the fundamental task's budget (Table 2), for Table E beside it
    residual_dof: ClassVar[int] = 4
    opencv_threshold: ClassVar[float] = 0.75 / STRECHA_FOCAL
    # Table E: params essential's rows on the fundamental folds' data (their data stages are the fundamental task's),
    # one model per fold trained by `rlsac train --task essential` (stage essential_train) and one per other seed
    fold_rows: ClassVar[str] = "essential"
    fold_stages: ClassVar[tuple[str, ...]] = ("tune", "evaluate")
    fold_checkpoint: ClassVar[str] = "checkpoints/essential/{regime}/{fold}{seed}.pt"
    sampler_knobs: ClassVar[tuple[str, ...]] = ("refit_output",)  # the refit of the output (tuning.refit_output)

    # Sampson distance in normalised image coordinates: 0.75 px at f = 920 px, the OpenCV rows' untuned default (the
    # tutorial's starter value); the fold benchmark tunes it per fold and row on validation pairs
    # (rlsac.evaluation.tune)
    threshold: float = 0.75 / STRECHA_FOCAL
    residual: str = "sampson"
    # The default output is the best minimal model (as OpenCV's RANSAC): the 8-point least-squares refit projected
    # onto the essential manifold can lose inliers on near-planar facades. Table E tunes it per fold and row
    # (tuning.refit_output); LO (the *-lo methods) still refits, keeping a refit only when it scores better.
    refit_output: bool = False
    name: str = "essential"
    sample_size: int = 5
    solutions: int = 10  # the five-point solver's candidates per minimal set (up to 10 real roots)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.residual not in ("sampson", "sampson_sq"):  # the batched (R, S, 3, 3) residuals are Sampson's
            raise RlsacError(f"essential residual must be sampson or sampson_sq, got {self.residual!r}")

    def px_thresholds(self, px: float) -> tuple[float, float]:
        """``px`` pixels -> (``threshold`` in normalised units, squared for sampson_sq; OpenCV's, normalised) at the
        Strecha focal length (every pair of our copy has f = 920 px)."""
        t = float(px) / STRECHA_FOCAL
        return (t * t if self.residual == "sampson_sq" else t), t

    @staticmethod
    def to_batch(data: dict[str, np.ndarray], idx=slice(None), device: str | torch.device = "cpu") -> dict:
        """The fundamental batch with coords (B, N, 4) calibrated: [K1^-1 x1, K2^-1 x2] (padding stays 0)."""
        batch = fundamental_data.to_batch(data, idx, device)
        px = batch["coords"]
        Kinv = [torch.as_tensor(np.linalg.inv(np.asarray(batch[k], np.float64)), dtype=torch.float64, device=px.device)
                for k in ("K1", "K2")]
        cal = []
        for j, Ki in enumerate(Kinv):
            h = torch.cat([px[..., 2 * j: 2 * j + 2].double(), torch.ones_like(px[..., :1], dtype=torch.float64)], -1)
            h = h @ Ki.transpose(1, 2)
            cal.append(h[..., :2] / h[..., 2:3])
        batch["pixels"] = px
        batch["coords"] = (torch.cat(cal, -1) * batch["mask"][..., None]).to(px.dtype)
        return batch

    def features(self, batch: dict) -> torch.Tensor:
        """[x1, y1, x2, y2] calibrated (about [-0.6, 0.6] here), then the optional SNN ratio and descriptors."""
        coords, feats = batch["coords"], batch["features"]
        extra = [feats[..., 4:5]] if self.use_snn else []
        extra += [feats[..., 5:261]] if self.use_descriptors else []
        out = torch.cat([coords, *[e.to(coords.dtype) for e in extra]], dim=-1)
        return out * batch["mask"][..., None].to(coords.dtype)

    def true_inliers(self, batch: dict) -> torch.Tensor:
        """Sampson distance to the ground-truth E = [t]x R within the threshold (warm start only)."""
        E = fundamental_data.skew(np.asarray(batch["dT"]).reshape(-1, 3)) @ np.asarray(batch["dR"], np.float64)
        E = torch.as_tensor(E / np.linalg.norm(E, axis=(-2, -1), keepdims=True), dtype=batch["coords"].dtype,
                            device=batch["coords"].device)
        return (self.residuals(E, batch["coords"]) <= self.threshold) & batch["mask"]

    def solve(self, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pts (B, 5, 4) calibrated -> E (B, 10, 3, 3), valid (B, 10) (geometry.five_point)."""
        return geometry.five_point(pts)

    def refine(self, coords: torch.Tensor, inliers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The fundamental task's least-squares (8-point) fit on the inliers in calibrated coordinates,
        projected onto the essential manifold. coords (B, N, 4), inliers (B, N) -> E (B, 3, 3), valid (B,)."""
        E, valid = super().refine(coords, inliers)
        E = geometry.project_to_essential(E.double()).to(E.dtype)
        return torch.where(valid[:, None, None], E, torch.zeros_like(E)), valid

    @staticmethod
    def pose(hyp: np.ndarray, K1: np.ndarray, K2: np.ndarray, pts: np.ndarray):
        """(R, t) from E (3, 3) and its calibrated inliers pts (n, 4); None on failure."""
        return recover_pose(hyp, pts[:, :2], pts[:, 2:4])

    # DEGENSAC is a fundamental-matrix (and homography) estimator: no degensac_fit here
    degensac_fit = None

    @staticmethod
    def poselib_fit(pts: np.ndarray, threshold: float, confidence: float, iterations: int, seed: int):
        """poselib.estimate_relative_pose (five-point LO-RANSAC, then bundle adjustment of the pose) on calibrated
        pts (n, 4), cameras with f = 1 (so the threshold is in normalised units) -> (E = [t]x R, inliers, hypotheses
        scored) or None."""
        import poselib

        cam = {"model": "PINHOLE", "width": 2, "height": 2, "params": [1.0, 1.0, 0.0, 0.0]}
        pose, info = poselib.estimate_relative_pose(np.ascontiguousarray(pts[:, :2]), np.ascontiguousarray(pts[:, 2:4]),
                                                    cam, cam, poselib_ransac(threshold, confidence, iterations, seed),
                                                    {})
        E = fundamental_data.skew(pose.t) @ np.asarray(pose.R, np.float64)
        out = opencv_model(E, info.get("inliers"))
        return None if out is None else (*out, int(info["iterations"]))

    @staticmethod
    def opencv_fit(pts: np.ndarray, flag: int, threshold: float, confidence: float, iterations: int):
        """cv2.findEssentialMat on calibrated pts (n, 4) with K = I (threshold in normalised units) ->
        (E (3, 3) unit Frobenius norm, inliers (n,) bool), None on failure (its first E of a stack). ``flag``: a
        method preset, or a cv2.UsacParams holding threshold, confidence and budget."""
        p1, p2 = np.ascontiguousarray(pts[:, :2]), np.ascontiguousarray(pts[:, 2:4])
        try:
            if isinstance(flag, cv2.UsacParams):
                E, inl = cv2.findEssentialMat(p1, p2, np.eye(3), np.eye(3), np.zeros(5), np.zeros(5), flag)
            else:
                E, inl = cv2.findEssentialMat(p1, p2, np.eye(3), flag, confidence, threshold, iterations)
        except cv2.error:
            return None
        return opencv_model(E, inl)
