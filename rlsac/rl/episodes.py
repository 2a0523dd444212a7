"""What a training episode sees: the same N points of a pair every time (the record's recipe), or N points redrawn
from the pair's pool for every episode, the two images swapped at random (issue #46, item 2a).

A training file of the fold benchmark holds the N = 150 points the hard regime drew once per pair from its 1000
lowest-SNN matches; an epoch over it repeats every input. ``RedrawnPairs`` reads a pool file instead (the same pairs
prepared with the pool's size, the 1000 lowest-SNN matches: `rlsac folds --stage pool`) and draws a fresh N of each
pair's valid points per episode, the hard regime's own draw, so an input almost never repeats. With ``swap`` an
episode sees the pair with its images exchanged with probability 1/2 (x1 <-> x2, the two descriptors, the image
sizes: F becomes F^T, and the self-supervised reward, an inlier count under the symmetric Sampson error, is the same).

The replay buffer keeps what rebuilds a transition's data channels: the instance, and for redrawn episodes the drawn
point indices and the swap flag (``ReplayBuffer(extra=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from rlsac.errors import RlsacError
from rlsac.tasks.registry import prefiltered


@dataclass
class EpisodeConf:
    # a prepared file of the same pairs with more points each (the pool); "" = episodes see the training file's points
    pool: str = ""
    points: int = 150  # N drawn per episode from the pool (the paper's N); used with a pool only
    swap: bool = False  # exchange the two images with probability 1/2 per episode
    # SNN pre-filters, one drawn per episode (1.0 = none), masking what the evaluation's tuned pre-filter masks: the
    # policy sees pre-filtered pairs in training as at test (issue #46, item 1); [] = none. With a pool only
    prefilter: list[float] = field(default_factory=list)
    ranges = {"points": "[8, inf)", "prefilter": "(0, 1]"}


class FixedPairs:
    """Instance i is always the training file's N points (the record's recipe): nothing drawn, nothing stored."""

    extra_width = 0

    def __init__(self, task, data: dict, actor) -> None:
        self.feats, self.mask, self.coords = data["features"], data["mask"], data["coords"]
        self.graph = actor.graph(self.feats, self.mask)  # data features never change: one graph per instance
        self.n_instances, self.n_points = self.mask.shape
        self._labels = data.get("labels")  # (I, N) ground-truth inliers: the supervised warm start only
        self.has_labels = self._labels is not None

    def labels(self, inst: torch.Tensor, extra: torch.Tensor | None) -> torch.Tensor:
        """Ground-truth inliers (b, N) of stored transitions (instances ``inst``)."""
        return self._labels[inst]

    def draw(self, inst: torch.Tensor, generator: torch.Generator):
        """-> batch (coords, mask), data features, kNN graph of the episodes of instances ``inst``, and None."""
        return {"coords": self.coords[inst], "mask": self.mask[inst]}, self.feats[inst], self.graph[inst], None

    def lookup(self, inst: torch.Tensor, extra: torch.Tensor | None):
        """Data features, mask and graph of stored transitions (instances ``inst``)."""
        return self.feats[inst], self.mask[inst], self.graph[inst]


class RedrawnPairs:
    """N points drawn per episode from each pair's pool, the images swapped with probability 1/2 (``swap``)."""

    def __init__(self, task, pool: dict, actor, points: int, swap: bool, prefilter=(),
                 labels: torch.Tensor | None = None) -> None:
        """labels (P, pool N) bool: the pool's ground-truth inliers, for the supervised warm start only."""
        self.task, self.pool, self.actor, self.swap = task, pool, actor, bool(swap)
        self._labels, self.has_labels = labels, labels is not None
        self.n_instances, pool_n = pool["mask"].shape
        self.n_points = int(points)
        if self.n_points > pool_n:
            raise RlsacError(f"episodes.points {points} is more than the pool's {pool_n} points per pair")
        self.prefilter = torch.tensor([float(r) for r in prefilter], dtype=torch.float64)
        # the drawn indices, the swap flag, and with pre-filters the index of the episode's pre-filter
        self.extra_width = self.n_points + 1 + (1 if len(self.prefilter) else 0)

    def draw(self, inst: torch.Tensor, generator: torch.Generator):
        """A fresh draw for every episode -> batch, features, graph, and the (E, N + 1) record of the draw."""
        mask = self.pool["mask"][inst]
        u = torch.rand(mask.shape, generator=generator, device=generator.device).to(mask.device)
        idx = u.masked_fill(~mask, -1.0).topk(self.n_points, dim=-1).indices.sort(dim=-1).values  # SNN order kept
        flip = torch.rand(inst.shape[0], generator=generator, device=generator.device).to(mask.device) < 0.5
        flip = flip & self.swap
        extra = torch.cat([idx, flip[:, None].long()], dim=-1)
        if len(self.prefilter):  # drawn only with pre-filters: without, the stream is the redraw arm's
            which = torch.randint(len(self.prefilter), (inst.shape[0],), generator=generator,
                                  device=generator.device).to(mask.device)
            extra = torch.cat([extra, which[:, None]], dim=-1)
        batch, feats, graph = self._build(inst, extra)
        return batch, feats, graph, extra

    def lookup(self, inst: torch.Tensor, extra: torch.Tensor):
        batch, feats, graph = self._build(inst, extra)
        return feats, batch["mask"], graph

    def labels(self, inst: torch.Tensor, extra: torch.Tensor) -> torch.Tensor:
        """Ground-truth inliers (b, N) of stored transitions: the pool's labels of the drawn points (a swap of the
        two images keeps a correspondence's label)."""
        return self._labels[inst].gather(1, extra[:, : self.n_points]) & self.lookup(inst, extra)[1]

    def _build(self, inst: torch.Tensor, extra: torch.Tensor):
        n = self.n_points
        idx, flip = extra[:, :n], extra[:, n].bool()
        take = lambda k: self.pool[k][inst].gather(  # noqa: E731
            1, idx[..., None].expand(-1, -1, self.pool[k].shape[-1]))
        coords, raw = take("coords"), take("features")
        mask = self.pool["mask"][inst].gather(1, idx)
        size1, size2 = self.pool["size1"][inst], self.pool["size2"][inst]
        if bool(flip.any()):
            f = flip[:, None, None]
            coords = torch.where(f, coords[..., [2, 3, 0, 1]], coords)
            raw = torch.where(f, _swap_features(raw), raw)
            s = flip[:, None]
            size1, size2 = torch.where(s, size2, size1), torch.where(s, size1, size2)
        batch = {"coords": coords, "mask": mask, "features": raw, "size1": size1, "size2": size2}
        if len(self.prefilter):  # the evaluation's pre-filter at the episode's drawn ratio, unless it leaves < m points
            batch = prefiltered(self.task, batch, self.prefilter.to(coords.device)[extra[:, n + 1]], keep_short=True)
            mask = batch["mask"]
        feats = self.task.features(batch)
        return {"coords": coords, "mask": mask}, feats, self.actor.graph(feats, mask)


def _swap_features(raw: torch.Tensor) -> torch.Tensor:
    """The prepared features (.., 261) of the swapped pair: x2, y2, x1, y1, SNN, descriptor 2, descriptor 1."""
    d = (raw.shape[-1] - 5) // 2
    order = [2, 3, 0, 1, 4, *range(5 + d, 5 + 2 * d), *range(5, 5 + d)]
    return raw[..., order]


def pool_tensors(pool: dict, device) -> dict:
    """A pool file's arrays (rlsac.data read) as the tensors ``RedrawnPairs`` takes (sizes as (P, 2) tensors)."""
    out = {k: pool[k] for k in ("coords", "features", "mask")}
    for k in ("size1", "size2"):
        out[k] = torch.as_tensor(pool[k], device=device)
    return out
