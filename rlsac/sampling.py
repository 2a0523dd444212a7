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
