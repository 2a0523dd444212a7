"""Minimal-set sampling shared by RANSAC and the RLSAC environment."""

from __future__ import annotations

import functools

import torch


def uniform_minimal_sets(mask: torch.Tensor, m: int, k: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """k uniformly random minimal sets of m distinct valid points per row.

    mask (B, N) bool valid points -> indices (B, k, m) long. Rows need at least m valid points.
    """
    B, N = mask.shape
    keys = torch.rand((B, k, N), generator=generator, device=mask.device)
    keys = keys.masked_fill(~mask[:, None, :], -1.0)
    return keys.topk(m, dim=-1).indices


def weighted_minimal_sets(logits: torch.Tensor, mask: torch.Tensor, m: int, k: int,
                          generator: torch.Generator | None = None) -> torch.Tensor:
    """k minimal sets of m distinct valid points per row drawn from softmax(logits) without replacement
    (Gumbel top-m: the same law as drawing the m points one after the other, renormalising after each).

    logits (B, N) float, mask (B, N) bool -> indices (B, k, m) long, each set in its draw order (the
    order ``set_log_prob`` scores). Rows need at least m valid points; masked points are never drawn.
    """
    if logits.shape != mask.shape or logits.dim() != 2:
        raise ValueError(f"weighted_minimal_sets: logits {tuple(logits.shape)} must be mask's (B, N) "
                         f"{tuple(mask.shape)}")
    B, N = mask.shape
    u = torch.rand((B, k, N), generator=generator, device=mask.device).clamp_(1e-12, 1 - 1e-12)
    keys = logits.detach()[:, None, :] - torch.log(-torch.log(u))
    return keys.masked_fill(~mask[:, None, :], float("-inf")).topk(m, dim=-1).indices


def set_log_prob(logits: torch.Tensor, mask: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """log P(idx) of ordered draws without replacement from softmax(logits) over the valid points:
    sum_j [log p(i_j) - log(1 - sum_{l<j} p(i_l))], differentiable in ``logits`` (NG-RANSAC's
    log-probability of a sampled minimal set; the exact without-replacement law of ``weighted_minimal_sets``).

    logits (B, N), mask (B, N) bool, idx (B, k, m) long -> (B, k).
    """
    if idx.dim() != 3 or idx.shape[0] != logits.shape[0] or logits.shape != mask.shape:
        raise ValueError(f"set_log_prob: logits (B, N), mask (B, N), idx (B, k, m) expected, got "
                         f"{tuple(logits.shape)}, {tuple(mask.shape)}, {tuple(idx.shape)}")
    logp = torch.log_softmax(logits.masked_fill(~mask, float("-inf")), dim=-1)  # (B, N)
    B, k, m = idx.shape
    lp = torch.gather(logp, 1, idx.reshape(B, k * m)).view(B, k, m)  # log p(i_j)
    # probability mass already drawn before each point: 0, p1, p1 + p2, ... (1 - it renormalises)
    before = torch.cumsum(lp.exp(), dim=-1) - lp.exp()
    return (lp - torch.log1p(-before.clamp(max=1 - 1e-6))).sum(-1)


def gather_points(coords: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """coords (B, N, d), idx (B, ..., m) -> (B, ..., m, d)."""
    B, N, d = coords.shape
    flat = idx.reshape(B, -1)
    out = torch.gather(coords, 1, flat[..., None].expand(-1, -1, d))
    return out.reshape(*idx.shape, d)


def set_keys(idx: torch.Tensor, n: int) -> torch.Tensor:
    """Order-free integer key of each minimal set: sorted indices read as base-n digits (int64).

    idx (..., m) -> (...). Exact while n^m < 2^63 (n=150, m=8 gives 2.6e17); beyond that it is a
    hash whose collisions only make de-duplication slightly over-cautious.
    """
    return (idx.sort(dim=-1).values * _powers(n, idx.shape[-1], idx.device)).sum(-1)


@functools.lru_cache(maxsize=64)
def _powers(n: int, m: int, device: torch.device) -> torch.Tensor:
    """(m,) int64 n^(m-1), ..., n, 1 modulo 2^64 (as signed), so that sum_j s_j n^(m-1-j) in one product wraps
    like the Horner loop key * n + s it replaced."""
    pw = [(n ** (m - 1 - j)) % 2**64 for j in range(m)]
    return torch.tensor([p - 2**64 if p >= 2**63 else p for p in pw], dtype=torch.int64, device=device)
