"""Batched two-view epipolar geometry in torch (fundamental matrices).

Conventions: a correspondence is a row (x1, y1, x2, y2) in pixels; F maps image-1 points to
image-2 epipolar lines, x2^T F x1 = 0 with homogeneous x = (x, y, 1). Batch dims come first; all
solvers work in float64 internally and return the input dtype. Nothing here raises on degenerate
input: solvers return a ``valid`` flag and a zero matrix where the flag is False.
"""

from __future__ import annotations

import math

import torch

EPS = 1e-12
# Degeneracy test: the second-smallest singular value of the (Hartley-normalised) design matrix
# must exceed this fraction of the largest, i.e. the null space must be one-dimensional.
GAP_TOL = 1e-5


def _to_h(x: torch.Tensor) -> torch.Tensor:
    """(..., 2) -> homogeneous (..., 3)."""
    return torch.cat([x, torch.ones_like(x[..., :1])], dim=-1)


def hartley_normalization(x: torch.Tensor, weights: torch.Tensor | None = None
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Similarity T moving the (weighted) centroid to 0 and the mean distance to sqrt(2).

    x (B, N, 2), weights (B, N) or None -> x_n (B, N, 2) = T x, T (B, 3, 3), ok (B,) bool (False when
    the points have no spread, e.g. all identical, or no positive weight).
    """
    w = torch.ones_like(x[..., 0]) if weights is None else weights.to(x.dtype)
    wsum = w.sum(-1)
    mean = (x * w[..., None]).sum(1) / wsum.clamp_min(EPS)[:, None]
    dist = (x - mean[:, None]).norm(dim=-1)
    mean_dist = (dist * w).sum(-1) / wsum.clamp_min(EPS)
    ok = (wsum > 0) & (mean_dist > 1e-8 * (1.0 + mean.abs().amax(-1)))
    scale = math.sqrt(2.0) / mean_dist.clamp_min(EPS)
    T = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype, device=x.device)
    T[:, 0, 0] = scale
    T[:, 1, 1] = scale
    T[:, 0, 2] = -scale * mean[:, 0]
    T[:, 1, 2] = -scale * mean[:, 1]
    T[:, 2, 2] = 1.0
    return (x - mean[:, None]) * scale[:, None, None], T, ok


def enforce_rank2(F: torch.Tensor) -> torch.Tensor:
    """Closest rank-2 matrix in Frobenius norm. (B, 3, 3) -> (B, 3, 3)."""
    U, S, Vh = torch.linalg.svd(F)
    S = torch.cat([S[:, :2], torch.zeros_like(S[:, 2:])], dim=-1)
    return (U * S[:, None, :]) @ Vh  # U diag(S) Vh, the scaling written out (same values, one product less)


def eight_point(pts: torch.Tensor, weights: torch.Tensor | None = None, gap_tol: float = GAP_TOL
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised (weighted) 8-point algorithm with rank-2 enforcement.

    pts (B, N, 4) pixels (N >= 8), weights (B, N) float or bool (None = all ones; a bool mask
    selects points) -> F (B, 3, 3) unit Frobenius norm in pixel coordinates, valid (B,) bool.

    Minimises sum_i w_i (x2_i^T F x1_i)^2 over the Hartley-normalised points via the smallest
    eigenvector of A^T W A. valid is False (and F zero) for fewer than 8 positive weights, points
    without spread, a null space of dimension > 1 (repeated / collinear / coplanar-degenerate
    samples: second-smallest singular value below ``gap_tol`` times the largest) or non-finite
    input / output.
    """
    dtype = pts.dtype
    p = pts.double()
    B, N, _ = p.shape
    if weights is None and N == 8 and bool(torch.isfinite(p).all()):
        return _eight_point_minimal(p, gap_tol, dtype)
    w0 = torch.ones(B, N, dtype=torch.float64, device=p.device) if weights is None else weights.double()
    finite_in = torch.isfinite(p).all(-1)
    bad_input = (~finite_in & (w0 != 0)).any(-1) | ~torch.isfinite(w0).all(-1)
    w = torch.where(finite_in & torch.isfinite(w0), w0.clamp_min(0.0), torch.zeros_like(w0))
    p = torch.where(finite_in[..., None], p, torch.zeros_like(p))

    x1, T1, ok1 = hartley_normalization(p[..., :2], w)
    x2, T2, ok2 = hartley_normalization(p[..., 2:], w)
    h1, h2 = _to_h(x1), _to_h(x2)
    A = (h2[..., :, None] * h1[..., None, :]).reshape(B, N, 9)  # row-major vec(F) coefficients
    M = A.transpose(1, 2) @ (A * w[..., None])
    M = torch.where(torch.isfinite(M), M, torch.zeros_like(M))
    evals, evecs = torch.linalg.eigh(M)  # ascending
    sv = evals.clamp_min(0.0).sqrt()
    gap_ok = sv[:, 1] > gap_tol * sv[:, -1].clamp_min(EPS)
    Fn = enforce_rank2(evecs[..., 0].reshape(B, 3, 3))
    F = T2.transpose(1, 2) @ Fn @ T1
    norm = F.flatten(1).norm(dim=-1)
    F = F / norm.clamp_min(EPS)[:, None, None]
    count = (w > 0).sum(-1)
    valid = (count >= 8) & ok1 & ok2 & gap_ok & ~bad_input & (norm > EPS) & torch.isfinite(F).flatten(1).all(-1)
    F = torch.where(valid[:, None, None], F, torch.zeros_like(F))
    return F.to(dtype), valid


def _eight_point_minimal(p: torch.Tensor, gap_tol: float, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``eight_point`` of finite minimal samples p (B, 8, 4) float64 without weights: the general path's
    arithmetic (a unit weight multiplies exactly, the weight sum is exactly 8) without its weight and
    non-finite handling, both images normalised at once: the same F and valid in fewer ops (the RLSAC
    environment solves a few dozen sets per step, where the op count is much of the cost)."""
    B = p.shape[0]
    x = p.view(B, 8, 2, 2)  # (set, point, image, xy)
    mean = x.sum(1) / 8.0  # (B, 2, 2)
    d = x - mean[:, None]
    mean_dist = d.norm(dim=-1).sum(1) / 8.0  # (B, 2)
    ok = (mean_dist > 1e-8 * (1.0 + mean.abs().amax(-1))).all(-1)
    scale = math.sqrt(2.0) / mean_dist.clamp_min(EPS)
    xn = d * scale[:, None, :, None]  # (B, 8, 2, 2) Hartley-normalised points
    x1, y1, x2, y2 = xn[..., 0, 0], xn[..., 0, 1], xn[..., 1, 0], xn[..., 1, 1]
    one = torch.ones_like(x1)
    A = torch.stack([x2 * x1, x2 * y1, x2, y2 * x1, y2 * y1, y2, x1, y1, one], -1)  # row-major vec(F) coefficients
    evals, evecs = torch.linalg.eigh(A.transpose(1, 2) @ A)
    sv = evals.clamp_min(0.0).sqrt()
    gap_ok = sv[:, 1] > gap_tol * sv[:, -1].clamp_min(EPS)
    z, o = torch.zeros_like(scale), torch.ones_like(scale)
    shift = -scale[..., None] * mean  # (B, image, xy)
    T = torch.stack([scale, z, shift[..., 0], z, scale, shift[..., 1], z, z, o], -1).view(B, 2, 3, 3)
    F = T[:, 1].transpose(1, 2) @ enforce_rank2(evecs[..., 0].reshape(B, 3, 3)) @ T[:, 0]
    norm = F.flatten(1).norm(dim=-1)
    F = F / norm.clamp_min(EPS)[:, None, None]
    valid = ok & gap_ok & (norm > EPS) & torch.isfinite(F).flatten(1).all(-1)
    return torch.where(valid[:, None, None], F, torch.zeros_like(F)).to(dtype), valid


def epipolar_terms(F: torch.Tensor, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Algebraic error and epipolar lines. F (B, 3, 3), pts (B, N, 4) ->
    e = x2^T F x1 (B, N), l2 = F x1 (B, N, 3) line in image 2, l1 = F^T x2 (B, N, 3) line in image 1."""
    h1, h2 = _to_h(pts[..., :2]), _to_h(pts[..., 2:])
    l2 = h1 @ F.transpose(1, 2)
    l1 = h2 @ F
    e = (h2 * l2).sum(-1)
    return e, l2, l1


def sampson_distance(F: torch.Tensor, pts: torch.Tensor, squared: bool = False) -> torch.Tensor:
    """Sampson (first-order geometric) error in pixels.

    F (B, 3, 3), pts (B, N, 4) -> (B, N): e^2 / (|l2_xy|^2 + |l1_xy|^2) when squared, else its sqrt.
    F (B, S, 3, 3) (S hypotheses of each set of points) -> (B, S, N).
    Points whose gradient vanishes (e.g. F = 0, both points at the epipoles) get +inf. Computed in
    float64 (pixel coordinates ~1e3 cancel badly in float32), returned in the dtype of ``pts``.
    """
    if F.dim() == 4:  # (B, S, 3, 3): S hypotheses per point set
        return _sampson_many(F, pts, squared)
    e, l2, l1 = epipolar_terms(F.double(), pts.double())
    den = l2[..., :2].square().sum(-1) + l1[..., :2].square().sum(-1)
    d2 = e.square() / den.clamp_min(1e-30)
    d2 = torch.where(den > 1e-30, d2, torch.full_like(d2, float("inf")))
    return (d2 if squared else d2.sqrt()).to(pts.dtype)


def _sampson_many(F: torch.Tensor, pts: torch.Tensor, squared: bool) -> torch.Tensor:
    """sampson_distance of F (B, S, 3, 3) on pts (B, N, 4) -> (B, S, N), as (B, 3S, 3) @ (B, 3, N)
    products: one batched product per point set instead of S copies of the points."""
    B, S = F.shape[:2]
    N = pts.shape[1]
    F, p = F.double(), pts.double()
    h1, h2 = _to_h(p[..., :2]).transpose(1, 2), _to_h(p[..., 2:]).transpose(1, 2)  # (B, 3, N)
    l2 = (F.reshape(B, 3 * S, 3) @ h1).view(B, S, 3, N)  # F x1
    l1 = (F.transpose(-1, -2).reshape(B, 3 * S, 3) @ h2).view(B, S, 3, N)  # F^T x2
    e = (l2 * h2[:, None]).sum(2)
    den = l2[:, :, :2].square().sum(2) + l1[:, :, :2].square().sum(2)
    d2 = e.square() / den.clamp_min(1e-30)
    d2 = torch.where(den > 1e-30, d2, torch.full_like(d2, float("inf")))
    return (d2 if squared else d2.sqrt()).to(pts.dtype)


def symmetric_epipolar_distance(F: torch.Tensor, pts: torch.Tensor, squared: bool = False) -> torch.Tensor:
    """Symmetric epipolar distance d(x2, F x1)^2 + d(x1, F^T x2)^2 (pixels^2) when squared, else its sqrt.

    F (B, 3, 3), pts (B, N, 4) -> (B, N); +inf where an epipolar line is undefined. float64 inside.
    """
    e, l2, l1 = epipolar_terms(F.double(), pts.double())
    n2 = l2[..., :2].square().sum(-1)
    n1 = l1[..., :2].square().sum(-1)
    d2 = e.square() * (1.0 / n2.clamp_min(1e-30) + 1.0 / n1.clamp_min(1e-30))
    d2 = torch.where((n1 > 1e-30) & (n2 > 1e-30), d2, torch.full_like(d2, float("inf")))
    return (d2 if squared else d2.sqrt()).to(pts.dtype)


def skew(t: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix. (B, 3) -> (B, 3, 3) with skew(t) v = t x v."""
    z = torch.zeros_like(t[:, 0])
    return torch.stack([
        torch.stack([z, -t[:, 2], t[:, 1]], -1),
        torch.stack([t[:, 2], z, -t[:, 0]], -1),
        torch.stack([-t[:, 1], t[:, 0], z], -1),
    ], dim=1)


def essential_from_pose(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """E = [t]x R for X2 = R X1 + t. R (B, 3, 3), t (B, 3) or (B, 3, 1) -> (B, 3, 3)."""
    return skew(t.reshape(-1, 3)) @ R


def fundamental_from_pose(K1: torch.Tensor, K2: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """F = K2^-T [t]x R K1^-1, unit Frobenius norm. K1, K2, R (B, 3, 3), t (B, 3) -> (B, 3, 3)."""
    F = torch.linalg.inv(K2).transpose(1, 2) @ essential_from_pose(R, t) @ torch.linalg.inv(K1)
    return F / F.flatten(1).norm(dim=-1).clamp_min(EPS)[:, None, None]


def project_to_essential(E: torch.Tensor) -> torch.Tensor:
    """Nearest essential matrix (singular values (1, 1, 0)), unit Frobenius norm up to sqrt(2).

    E (B, 3, 3) -> (B, 3, 3) U diag(1, 1, 0) V^T / sqrt(2)."""
    if E.dim() != 3 or E.shape[-2:] != (3, 3):
        raise ValueError(f"project_to_essential: E must be (B, 3, 3), got {tuple(E.shape)}")
    U, _, Vh = torch.linalg.svd(E)
    d = torch.tensor([1.0, 1.0, 0.0], dtype=E.dtype, device=E.device) / 2**0.5
    return (U * d) @ Vh


def five_point(pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nister's five-point solver (kornia's batched implementation, in float64).

    pts (B, 5, 4) calibrated correspondences [x1, y1, x2, y2] (K^-1 applied) -> E (B, 10, 3, 3) with
    x2^T E x1 = 0, unit Frobenius norm, zero where a candidate does not exist; valid (B, 10) bool
    (finite, non-zero candidates of a non-degenerate sample).
    """
    if pts.dim() != 3 or pts.shape[1:] != (5, 4):
        raise ValueError(f"five_point: pts must be (B, 5, 4), got {tuple(pts.shape)}")
    from kornia.geometry.epipolar.essential import run_5point

    p = pts.double()
    if p.shape[0] == 0:
        return pts.new_zeros(0, 10, 3, 3), torch.zeros(0, 10, dtype=torch.bool, device=pts.device)
    finite = torch.isfinite(p).flatten(1).all(-1)
    p = torch.where(finite[:, None, None], p, torch.zeros_like(p))
    E = run_5point(p[..., :2], p[..., 2:4]).reshape(-1, 10, 3, 3)
    norm = E.flatten(2).norm(dim=-1)
    valid = torch.isfinite(E).flatten(2).all(-1) & (norm > EPS) & finite[:, None]
    E = torch.where(valid[..., None, None], E / norm.clamp_min(EPS)[..., None, None], torch.zeros_like(E))
    return E.to(pts.dtype), valid
