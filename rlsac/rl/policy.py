"""EdgeConv (DGCNN) networks: the actor's per-point logits and the critics' per-point values.

Input states are (R, N, C) with C = c data channels + 3 memory channels. The first graph is the
k-nearest-neighbour graph of the first ``graph_dims`` data channels (point coordinates: 2 for lines,
4 for correspondences); later layers rebuild it in feature space, as DGCNN does.

EdgeConv with a one-layer edge MLP, h(x_i, x_j - x_i) = W1 x_i + W2 (x_j - x_i), is computed as
(W1 - W2) x_i + W2 x_j: two per-point products and a gather instead of an (N, k, 2C) edge tensor,
15 times less work at k = 15 for the same function.

Three evaluation paths compute the same function (``tests/test_speed_equivalence.py``):

* ``reference_forward``: the original implementation, kept as the reference for tests and benchmarks.
* ``forward(state, mask, graph)``: any states, autograd (training). The head's first layer is split
  into its local and global parts, so the pooled global feature goes through it once per row instead
  of being concatenated onto every point, and the global pooling's linear layer shares one product
  with the head's local part (max pooling commutes with the increasing leaky ReLU, so the pool is
  taken before the activation).
* ``precompute(features, mask, episodes)`` + ``forward_memory(prepared, memory)``: test-time rollouts,
  where the data channels (coordinates, SNN, descriptors: 261 of the 264 channels) never change. They
  go through the first layer once per instance; each step only multiplies the 3 memory channels. Rows
  are processed in chunks of at most ``chunk_points`` row x point pairs, point-major within an instance
  ((G, N, e, C): the E episodes of an instance share the graph, so the neighbour gather copies
  contiguous blocks), so no per-step tensor exceeds a few MB (glibc returns blocks over 32 MB to the
  OS and page-faults them back on every step).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from rlsac.rl.kernels import linear_for, neighbour_max_for

MEMORY_CHANNELS = 3  # the environment's memory channels, appended after the data channels (rlsac.rl.env.MEMORY_DIM)
# Row x point pairs per chunk of the rollout path: per-step tensors stay at ~4096 x 128 floats (2 MB) and
# the neighbour max's three (points, episodes x 32) buffers fit the 2 MB L2. CPU ms per instance and
# forward call on the 2-core machine (one thread) at 1024 / 2048 / 4096 / 8192 / 16384:
# lines, 16 instances x 10 episodes: 1.36 / 1.20 / 1.15 / 1.56 / 2.11; fundamental, one pair x 67
# episodes: 13.3 / 12.4 / 12.2 / 12.3 / 24.4.
CHUNK_POINTS = 4096
GATHER_AT_ONCE = 1 << 19  # neighbour gathers up to this many floats (2 MB) are done in one op


@dataclass
class PolicyConf:
    k: int = 15  # neighbours per EdgeConv graph (paper)
    widths: list[int] = field(default_factory=lambda: [32, 32, 32])  # EdgeConv layers; sized for CPU training
    global_width: int = 64  # pooled global feature broadcast back to every point
    head_width: int = 64  # per-point MLP before the logit / value
    graph_dims: int = 2  # data channels the first kNN graph uses (coordinates)
    dynamic: bool = False  # True rebuilds the graph in feature space per layer (DGCNN); off: 3x cheaper on CPU

    # checked by rlsac.config.build (widths: each layer)
    ranges = {"k": "[1, inf)", "widths": "[1, inf)", "global_width": "[1, inf)", "head_width": "[1, inf)",
              "graph_dims": "[1, inf)"}


def knn(x: torch.Tensor, k: int, mask: torch.Tensor | None) -> torch.Tensor:
    """x (R, N, C) -> neighbour indices (R, N, k) (self included), never pointing at masked points."""
    d = torch.cdist(x, x)
    if mask is not None:
        d = d.masked_fill(~mask[:, None, :], float("inf"))
    return d.topk(min(k, x.shape[1]), dim=-1, largest=False).indices


def _leaky(x: torch.Tensor) -> torch.Tensor:
    return F.leaky_relu(x, 0.2)


class EdgeConv(nn.Module):
    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.centre = nn.Linear(c_in, c_out)
        self.neigh = nn.Linear(c_in, c_out, bias=False)

    def forward(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """x (R, N, C), idx (R, N, k) -> (R, N, C_out), max over the k edges.

        leaky_relu is increasing, so max_j act(a_i + b_j) = act(a_i + max_j b_j): only the neighbour
        term goes through the (R, N, k, C_out) gather.
        """
        R, N, k = idx.shape
        b = self.neigh(x)  # W2 x_j
        a = self.centre(x) - b  # (W1 - W2) x_i + bias
        flat = (idx + torch.arange(R, device=idx.device).view(R, 1, 1) * N).reshape(-1)
        nb = b.reshape(R * N, -1).index_select(0, flat).view(R, N, k, -1).amax(dim=2)
        return nn.functional.leaky_relu(a + nb, 0.2)

    def split(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """-> W2 (neighbour term), W1 - W2 (centre term), bias: b = x W2^T, a = x (W1 - W2)^T + bias."""
        w2 = self.neigh.weight
        return w2, self.centre.weight - w2, self.centre.bias


def _edge_max(a: torch.Tensor, b: torch.Tensor, nbr: torch.Tensor,
              scratch: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """EdgeConv output act(a_i + max_j b_j). b (P, Q): rows P = (instances x N) points, Q = (episodes x
    C) contiguous; nbr (k, P) neighbour rows; scratch two (P, Q) buffers; a (numel of b) used in place.

    Large chunks: one neighbour at a time, k gathers of contiguous (episodes x C) blocks, each the size
    of b and so cache-resident, instead of one (k, P, Q) tensor (19 MB per fundamental pair, 5x slower
    at batch 256). Small chunks (gather under GATHER_AT_ONCE floats): one gather and one max, 2 ops
    instead of 2k (at one line instance per call the op count, not the bytes, is the cost).
    """
    k = nbr.shape[0]
    if b.numel() * k <= GATHER_AT_ONCE:
        nb = b.index_select(0, nbr.view(-1)).view(k, *b.shape).amax(dim=0)
    else:
        nb, tmp = scratch
        torch.index_select(b, 0, nbr[0], out=nb)
        for j in range(1, k):
            torch.maximum(nb, torch.index_select(b, 0, nbr[j], out=tmp), out=nb)
    a.view(b.shape).add_(nb)
    return F.leaky_relu_(a, 0.2)


@dataclass
class Prepared:
    """What ``PointNet.precompute`` keeps per rollout: the data channels through the first layer, the
    fused weights of the later layers and the row chunks with their neighbour indices. A snapshot of
    the weights: build a new one after an optimiser step."""

    instances: int
    episodes: int
    n_points: int
    mask: torch.Tensor | None  # (B, N) valid points, None = all valid
    proj: tuple[torch.Tensor, torch.Tensor]  # first layer's neighbour / centre terms of the data channels (B, N, C1)
    mem_w: tuple[torch.Tensor, torch.Tensor]  # first layer's memory weights, transposed (3, C1)
    layers: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]  # later layers: W2^T, (W1 - W2)^T, bias
    chunks: list[tuple[int, int, int, int, torch.Tensor]]  # (g0, g1, e0, e1, neighbour rows (k, G N))
    features: torch.Tensor | None = None  # data channels, kept for the dynamic-graph fallback
    graph: torch.Tensor | None = None
    buffers: dict = field(default_factory=dict)  # scratch of the neighbour max, reused across steps

    def scratch(self, p: int, q: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        key = (p, q)
        if key not in self.buffers:
            self.buffers[key] = (like.new_empty(p, q), like.new_empty(p, q))
        return self.buffers[key]


class PointNet(nn.Module):
    """EdgeConv trunk + global max pool + per-point head -> one scalar per point (R, N)."""

    def __init__(self, c_in: int, conf: PolicyConf):
        super().__init__()
        self.conf = conf
        dims = [c_in, *conf.widths]
        self.convs = nn.ModuleList(EdgeConv(a, b) for a, b in zip(dims[:-1], dims[1:], strict=True))
        local = sum(conf.widths)
        self.glob = nn.Sequential(nn.Linear(local, conf.global_width), nn.LeakyReLU(0.2))
        self.head = nn.Sequential(
            nn.Linear(local + conf.global_width, conf.head_width), nn.LeakyReLU(0.2),
            nn.Linear(conf.head_width, conf.head_width // 2), nn.LeakyReLU(0.2),
            nn.Linear(conf.head_width // 2, 1),
        )
        self.linear = F.linear  # the training path's dense products (set_kernels); the rollout path keeps ATen's
        self.neighbour_max = neighbour_max_for("eager")  # the training path's EdgeConv max (set_kernels)

    def set_kernels(self, name: str, neighbour_max: str = "eager") -> PointNet:
        """The training path's products from kernels ``name`` (rlsac.rl.kernels.KERNELS) and its neighbour max from
        ``neighbour_max`` (rlsac.rl.kernels.NEIGHBOUR_MAX); not saved with the weights."""
        self.linear = linear_for(name)
        self.neighbour_max = neighbour_max_for(neighbour_max)
        return self

    def graph(self, state: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """kNN graph of the coordinate channels (R, N, k); fixed per instance, so callers cache it."""
        return knn(state[..., : self.conf.graph_dims], self.conf.k, mask)

    # ------------------------------------------------------------------ reference (original) path
    def reference_forward(self, state: torch.Tensor, mask: torch.Tensor | None = None,
                          graph: torch.Tensor | None = None) -> torch.Tensor:
        """The original forward pass, kept verbatim as the reference the fast paths are tested against."""
        idx = self.graph(state, mask) if graph is None else graph
        feats, x = [], state
        for i, conv in enumerate(self.convs):
            if i > 0 and self.conf.dynamic:
                idx = knn(x, self.conf.k, mask)
            x = conv(x, idx)
            feats.append(x)
        local = torch.cat(feats, dim=-1)
        g = self.glob(local)
        if mask is not None:
            g = g.masked_fill(~mask[..., None], float("-inf"))
        g = g.amax(dim=1, keepdim=True).expand(-1, local.shape[1], -1)
        return self.head(torch.cat([local, g], dim=-1)).squeeze(-1)

    # ------------------------------------------------------------------ generic path (autograd)
    def forward(self, state: torch.Tensor, mask: torch.Tensor | None = None,
                graph: torch.Tensor | None = None) -> torch.Tensor:
        """state (R, N, C), mask (R, N), graph (R, N, k) -> (R, N); the function of ``reference_forward``."""
        idx = self.graph(state, mask) if graph is None else graph
        R, N, k = idx.shape
        rows = torch.arange(R, device=idx.device).view(R, 1, 1) * N
        flat = (idx + rows).view(R * N, k).t().reshape(-1)  # neighbour-major, as neighbour_max takes it
        feats, x = [], state
        for i, conv in enumerate(self.convs):
            if i > 0 and self.conf.dynamic:
                idx = knn(x, self.conf.k, mask)
                flat = (idx + rows).view(R * N, k).t().reshape(-1)
            w2, wd, bias = conv.split()
            b = self.linear(x, w2).reshape(R * N, -1)
            nb = self.neighbour_max(b, flat, k).view(R, N, -1)
            x = _leaky(self.linear(x, wd, bias) + nb)
            feats.append(x)
        local = torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0]
        return self._head(local, None if mask is None else ~mask[..., None], self.linear)

    def _head(self, local: torch.Tensor, invalid: torch.Tensor | None, linear=F.linear) -> torch.Tensor:
        """local (A, N, ..., L) per-point features, points on dim 1 -> (A, N, ...) values.

        invalid: broadcastable to the pooled channels, True where a point is padding; linear: the products."""
        lin_g, h0, h1, h2 = self.glob[0], self.head[0], self.head[2], self.head[4]
        L, G = local.shape[-1], lin_g.out_features
        w = torch.cat([lin_g.weight, h0.weight[:, :L]], dim=0)
        bias = torch.cat([lin_g.bias, lin_g.bias.new_zeros(h0.out_features)])
        y = linear(local, w, bias)  # glob pre-activation | head's local term
        g = y[..., :G]
        if invalid is not None:
            g = g.masked_fill(invalid, float("-inf"))
        g = _leaky(g.amax(dim=1, keepdim=True))  # max pool before the (increasing) activation: same value
        h = _leaky(y[..., G:] + linear(g, h0.weight[:, L:], h0.bias))  # global term once per row
        return linear(_leaky(linear(h, h1.weight, h1.bias)), h2.weight, h2.bias).squeeze(-1)

    # ------------------------------------------------------------------ rollout path (inference)
    @torch.no_grad()
    def precompute(self, features: torch.Tensor, mask: torch.Tensor | None = None, episodes: int = 1,
                   graph: torch.Tensor | None = None, chunk_points: int = CHUNK_POINTS) -> Prepared:
        """Per-rollout constants for ``forward_memory``: features (B, N, c) data channels, mask (B, N),
        ``episodes`` rows per instance (rows are instance-major: row r is instance r // episodes)."""
        B, N, c = features.shape
        E = int(episodes)
        idx = self.graph(features, mask) if graph is None else graph
        k = idx.shape[-1]
        w2, wd, bias = self.convs[0].split()
        proj = (F.linear(features, w2[:, :c]), F.linear(features, wd[:, :c], bias))
        mem_w = (w2[:, c:].t().contiguous(), wd[:, c:].t().contiguous())
        layers = []
        for conv in self.convs[1:]:
            w2_, wd_, b_ = conv.split()
            layers.append((w2_.t().contiguous(), wd_.t().contiguous(), b_.detach().clone()))
        rows = max(1, int(chunk_points) // max(N, 1))
        spans: list[tuple[int, int, int, int]] = []
        if E <= rows:
            per = max(1, rows // E)
            spans = [(g, min(g + per, B), 0, E) for g in range(0, B, per)]
        else:
            parts = -(-E // rows)
            cuts = [round(i * E / parts) for i in range(parts + 1)]
            spans = [(g, g + 1, e0, e1) for g in range(B) for e0, e1 in zip(cuts[:-1], cuts[1:], strict=True)]
        offs = torch.arange(B, device=idx.device).view(B, 1, 1) * N
        flat_all = (idx + offs).reshape(B, N * k)
        chunks = [(g0, g1, e0, e1, (flat_all[g0:g1] - g0 * N).reshape(-1, k).t().contiguous())
                  for g0, g1, e0, e1 in spans]
        all_valid = mask is None or bool(mask.all())
        return Prepared(B, E, N, None if all_valid else mask, proj, mem_w, layers, chunks,
                        features if self.conf.dynamic else None, idx if self.conf.dynamic else None)

    @torch.no_grad()
    def forward_memory(self, prep: Prepared, memory: torch.Tensor) -> torch.Tensor:
        """memory (R, N, 3) memory channels of R = instances x episodes rows -> (R, N), the value of
        ``forward(cat([features, memory]), mask, graph)`` with the prepared data channels."""
        B, E, N = prep.instances, prep.episodes, prep.n_points
        if self.conf.dynamic:  # graphs depend on the memory: no per-instance reuse
            feats = prep.features.repeat_interleave(E, 0)
            mask = None if prep.mask is None else prep.mask.repeat_interleave(E, 0)
            return self.forward(torch.cat([feats, memory], -1), mask, prep.graph.repeat_interleave(E, 0))
        mem = memory.view(B, E, N, -1)
        out = memory.new_empty(B, E, N)
        (pb, pa), (mb, ma) = prep.proj, prep.mem_w
        for g0, g1, e0, e1, nbr in prep.chunks:
            G, e = g1 - g0, e1 - e0
            m = mem[g0:g1, e0:e1].permute(0, 2, 1, 3).reshape(G * N * e, -1)  # point-major (G, N, e)
            b = torch.mm(m, mb).view(G, N, e, -1).add_(pb[g0:g1, :, None])
            a = torch.mm(m, ma).view(G, N, e, -1).add_(pa[g0:g1, :, None])
            x = _edge_max(a, b.view(G * N, -1), nbr, prep.scratch(G * N, e * b.shape[-1], b))
            feats = [x]
            for w2t, wdt, bias in prep.layers:
                x2 = x.view(-1, x.shape[-1])
                b = torch.mm(x2, w2t).view(G * N, -1)
                a = torch.addmm(bias, x2, wdt).view(G, N, e, -1)
                x = _edge_max(a, b, nbr, prep.scratch(G * N, b.shape[1], b))
                feats.append(x)
            local = torch.cat(feats, dim=-1) if len(feats) > 1 else feats[0]
            invalid = None if prep.mask is None else ~prep.mask[g0:g1, :, None, None]
            out[g0:g1, e0:e1] = self._head(local, invalid).permute(0, 2, 1)
        return out.view(B * E, N)


class Actor(PointNet):
    """Per-point logits; softmax over valid points is the probability of joining the minimal set."""

    def forward(self, state, mask=None, graph=None):
        logits = super().forward(state, mask, graph)
        return logits if mask is None else logits.masked_fill(~mask, float("-inf"))

    def reference_forward(self, state, mask=None, graph=None):
        logits = super().reference_forward(state, mask, graph)
        return logits if mask is None else logits.masked_fill(~mask, float("-inf"))

    def forward_memory(self, prep: Prepared, memory: torch.Tensor) -> torch.Tensor:
        logits = super().forward_memory(prep, memory)
        if prep.mask is None:
            return logits
        B, E, N = prep.instances, prep.episodes, prep.n_points
        return logits.view(B, E, N).masked_fill_(~prep.mask[:, None, :], float("-inf")).view(B * E, N)


class Critic(PointNet):
    """Per-point values q_i; Q(s, a) of a minimal set a is the mean of q_i over its m points."""
