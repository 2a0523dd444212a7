"""The RL environment's scoring (rlsac.rl.env): each step's minimal sets scored per instance
(rlsac.estimation.lo.score_sets), the
reward, the best hypothesis of each instance over all its episodes (with LO if asked), and the output.

Part of ``SampleConsensusEnv`` (a mixin): it owns ``n_valid``, ``best`` (rlsac.estimation.lo.Best), ``best_hyp``,
``best_count``; it reads the instances (``inst_coords``, ``inst_mask``), ``task``, ``conf`` (reward, lo), the
generator ``gen`` and, for the reward ``improvement``, the bookkeeping's ``ep_best``.
"""

from __future__ import annotations

import torch

from rlsac.estimation.baselines import finalize
from rlsac.estimation.lo import Best, finish, score_sets, update_best
from rlsac.estimation.sampling import gather_points


class Scoring:
    """The hypotheses of the chosen sets, their reward, and the best one per instance."""

    def _start_scoring(self) -> None:
        """No hypothesis yet: every instance's best is empty."""
        self.n_valid = self.mask.sum(-1).clamp_min(1)
        # best hypothesis per instance (rlsac.estimation.lo.update_best)
        self.best = Best.empty(self.B, self.coords.device)
        self.best_count = self.best.count
        self.best_hyp: torch.Tensor | None = None

    def _score(self, idx: torch.Tensor):
        """Hypotheses of the sets idx (R, k, m) -> hyps (R, k, *H), valid (R, k), residuals (R, k, N) (+inf for
        invalid sets and padding), inlier counts (R, k) (0 for invalid sets); scored per instance."""
        task, (B, E, N) = self.task, (self.B, self.E, self.N)
        R, k, m = idx.shape
        pts = gather_points(self.inst_coords, idx.reshape(B, E * k, m))
        hyps, valid, res, count = score_sets(task, pts, self.inst_coords, self.inst_mask)  # (B, E k, ...)
        res = torch.where(valid[..., None] & self.inst_mask[:, None], res, torch.full_like(res, float("inf")))
        return (hyps.reshape(R, k, *hyps.shape[2:]), valid.reshape(R, k), res.reshape(R, k, N),
                count.masked_fill(~valid, 0).reshape(R, k))

    def _reward(self, count: torch.Tensor) -> torch.Tensor:
        """The inlier ratio (paper), or its gain over the episode's best so far (``reward="improvement"``)."""
        reward = count.float() / self.n_valid
        if self.conf.reward == "improvement":
            reward = (reward - self.ep_best.clamp_min(0).float() / self.n_valid).clamp_min(0.0)
        return reward

    def _update_best(self, hyps: torch.Tensor, count: torch.Tensor, res: torch.Tensor, counted: torch.Tensor) -> None:
        """The best hypothesis of each instance over all its episodes (with LO if ``conf.lo``)."""
        B, n = self.B, count.numel() // self.B
        c = count.masked_fill(~counted, -1).view(B, n)
        self.best = update_best(self.task, self.conf.lo, self.inst_coords, self.inst_mask, self.best,
                                hyps.reshape(B, n, *hyps.shape[2:]), c, res.reshape(B, n, -1), self.gen)
        self.best_hyp, self.best_count = self.best.hyp, self.best.count

    def instances(self) -> tuple[torch.Tensor, torch.Tensor]:
        """coords (B, N, d), mask (B, N) of the instances (rows are instance-major)."""
        return self.inst_coords, self.inst_mask

    def result(self) -> dict[str, torch.Tensor]:
        """Best hypothesis per instance over all episodes, refined on its inliers (with LO:
        rlsac.estimation.lo.finish)."""
        coords, mask = self.instances()
        if self.conf.lo.enabled:
            return finish(self.task, self.conf.lo, coords, mask, self.best, self.gen)
        return finalize(self.task, coords, mask, self.best_hyp, self.best_count >= self.task.sample_size)
