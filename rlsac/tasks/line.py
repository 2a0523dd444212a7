"""2D line fitting (paper Sec. 4.2): m = 2, point-to-line residuals, total-least-squares refinement.

A line is stored as (a, b, c) with a^2 + b^2 = 1 and a x + b y + c = 0, so the residual of a point
is its Euclidean distance to the line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from rlsac.data import lines
from rlsac.maths import metrics
from rlsac.tasks.registry import register_task

EPS = 1e-9


@register_task
@dataclass
class LineTask:
    experiment: ClassVar[str] = "lines"
    default_iterations: ClassVar[int] = 150  # Table 1's budget
    residual_dof: ClassVar[int] = 2
    true_inlier_data: ClassVar[bool] = True  # the generator stores the inlier mask (method oracle)
    hypothesis_shape: ClassVar[tuple[int, ...]] = (3,)
    # no fold benchmark: Table 1 is synthetic (rlsac.experiments.ablate, rlsac synth-lines)
    fold_rows: ClassVar[str] = ""
    read = staticmethod(lines.read)
    to_batch = staticmethod(lines.to_batch)

    threshold: float = 0.1  # the paper's inlier threshold: inliers are disturbed within 0.1 of the line
    picture_size: float = 10.0  # points live in [0, picture_size]^2; features are divided by it
    maa_limit_deg: float = 0.5  # Table 1 reports mAA@0.5 deg

    name: str = "line"
    sample_size: int = 2
    coord_dim: int = 2
    feature_dim: int = 2
    solutions: int = 1

    def solve(self, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """pts (B, 2, 2) -> lines (B, 3), valid (B,): the line through two distinct points."""
        d = pts[:, 1] - pts[:, 0]
        length = d.norm(dim=-1)
        valid = length > 1e-6
        normal = torch.stack([-d[:, 1], d[:, 0]], dim=-1) / length.clamp_min(EPS)[:, None]
        c = -(normal * pts[:, 0]).sum(-1)
        return torch.cat([normal, c[:, None]], dim=-1), valid

    def residuals(self, hyps: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """hyps (B, 3), coords (B, N, 2) -> distances (B, N); hyps (B, S, 3) -> (B, S, N)."""
        if hyps.dim() == 3:  # S lines per instance: one (S, 2) x (2, N) product per instance
            return (hyps[..., :2] @ coords.transpose(1, 2)).add(hyps[..., 2:3]).abs()
        return (coords @ hyps[:, :2, None]).squeeze(-1).add(hyps[:, 2:3]).abs()

    def refine(self, coords: torch.Tensor, inliers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(Weighted) total least squares: the normal is the smallest principal direction of the
        weighted scatter about the weighted mean, i.e. argmin sum_i w_i dist_i^2.

        coords (B, N, 2), inliers (B, N) bool, or float weights >= 0 (LO's IRLS, ``rlsac.estimation.lo``) ->
        lines (B, 3), valid (B,) (False with < 2 points of positive weight).
        """
        if inliers.shape != coords.shape[:2]:
            raise ValueError(f"refine: inliers {tuple(inliers.shape)} must be coords' (B, N) {tuple(coords.shape[:2])}")
        w = inliers.to(coords.dtype).clamp_min(0)
        wsum = w.sum(-1)
        mean = (coords * w[..., None]).sum(1) / wsum.clamp_min(1e-30)[:, None]
        # sqrt(w) on both sides of the scatter gives sum w (x - mean)(x - mean)^T; for a bool mask sqrt is
        # exact (0 or 1), so the unweighted fit is bit-identical to the plain TLS it replaces
        centred = (coords - mean[:, None]) * w.sqrt()[..., None]
        cov = centred.transpose(1, 2) @ centred
        _, vecs = torch.linalg.eigh(cov.double())
        normal = vecs[..., 0].to(coords.dtype)
        c = -(normal * mean).sum(-1)
        return torch.cat([normal, c[:, None]], dim=-1), (w > 0).sum(-1) >= 2

    def true_inliers(self, batch: dict) -> torch.Tensor:
        """Ground-truth inlier labels (B, N) bool: the generator's mask (supervised warm start only)."""
        return torch.as_tensor(np.asarray(batch["inlier_mask"]), dtype=torch.bool,
                               device=batch["coords"].device) & batch["mask"]

    def features(self, batch: dict) -> torch.Tensor:
        """Network input: coordinates scaled to [0, 1]. (B, N, 2)"""
        return batch["coords"] / self.picture_size

    def errors(self, hyps, valid, inliers, batch) -> dict[str, np.ndarray]:
        """Angle to the ground-truth line in degrees; an invalid estimate counts as 90 deg."""
        err = metrics.line_angle_deg(np.asarray(hyps)[:, :2], np.asarray(batch["line"])[:, :2])
        return {"err_deg": np.where(np.asarray(valid), err, 90.0)}

    def summarize(self, errors: dict[str, np.ndarray]) -> dict[str, float]:
        e = errors["err_deg"]
        return {"mAA": metrics.mAA(e, self.maa_limit_deg), "median_deg": metrics.median(e), "n": int(e.size)}
