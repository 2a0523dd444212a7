"""EdgeConv (DGCNN) networks: the actor's per-point logits and the critics' per-point values.

Input states are (R, N, C) with C = c data channels + 3 memory channels. The first graph is the
k-nearest-neighbour graph of the first ``graph_dims`` data channels (point coordinates: 2 for lines,
4 for correspondences); later layers rebuild it in feature space, as DGCNN does.

EdgeConv with a one-layer edge MLP, h(x_i, x_j - x_i) = W1 x_i + W2 (x_j - x_i), is computed as
(W1 - W2) x_i + W2 x_j: two per-point products and a gather instead of an (N, k, 2C) edge tensor,
15 times less work at k = 15 for the same function.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn


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

    def graph(self, state: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """kNN graph of the coordinate channels (R, N, k); fixed per instance, so callers cache it."""
        return knn(state[..., : self.conf.graph_dims], self.conf.k, mask)

    def forward(self, state: torch.Tensor, mask: torch.Tensor | None = None,
                graph: torch.Tensor | None = None) -> torch.Tensor:
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


class Actor(PointNet):
    """Per-point logits; softmax over valid points is the probability of joining the minimal set."""

    def forward(self, state, mask=None, graph=None):
        logits = super().forward(state, mask, graph)
        return logits if mask is None else logits.masked_fill(~mask, float("-inf"))


class Critic(PointNet):
    """Per-point values q_i; Q(s, a) of a minimal set a is the mean of q_i over its m points."""
