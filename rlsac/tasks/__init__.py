"""Estimation problems behind one protocol. A new task is one new module registered in TASKS.

Shapes: B batch rows, N points, m minimal size, d coordinate channels the solver uses, and
H the hypothesis shape (3 for a line, (3, 3) for a fundamental matrix).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch


class Task(Protocol):
    name: str
    sample_size: int  # m, points in a minimal set
    coord_dim: int  # d, channels of ``coords`` the solver needs
    threshold: float  # inlier threshold on ``residuals``
    feature_dim: int  # c, channels of ``features(batch)``, the network's data features

    def features(self, batch: dict) -> torch.Tensor:
        """Normalised per-point data features for the policy network. -> (B, N, c)"""

    def solve(self, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Minimal solver. pts (B, m, d) -> hypotheses (B, *H), valid (B,) bool (False = degenerate)."""

    def residuals(self, hyps: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
        """hyps (B, *H), coords (B, N, d) -> residuals (B, N), compared against ``threshold``."""

    def true_inliers(self, batch: dict) -> torch.Tensor:
        """Ground-truth inlier labels (B, N) bool, for the supervised warm start (not in the paper)."""

    def refine(self, coords: torch.Tensor, inliers: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Non-minimal fit on inliers. coords (B, N, d), inliers (B, N) bool -> hyps (B, *H), valid (B,)."""

    def errors(self, hyps: np.ndarray, valid: np.ndarray, inliers: np.ndarray, batch: dict) -> dict[str, np.ndarray]:
        """Per-row errors against the ground truth in ``batch`` (numpy), e.g. {'err': (B,)} in degrees."""

    def summarize(self, errors: dict[str, np.ndarray]) -> dict[str, float]:
        """Dataset-level metrics (mAA, medians) from the concatenated per-row errors."""


def get_task(name: str, **options) -> Task:
    from rlsac.errors import RlsacError

    if name == "line":
        from rlsac.tasks.line import LineTask

        return LineTask(**options)
    if name == "fundamental":
        from rlsac.tasks.fundamental import FundamentalTask

        return FundamentalTask(**options)
    raise RlsacError(f"unknown task '{name}' (known: line, fundamental)")


TASK_NAMES = ("line", "fundamental")
