"""The RL environment's episode bookkeeping (rlsac.rl.env): the clock and budget of every row, the minimal sets each
instance has used (candidates drawn from the policy's scores, de-duplicated: ``select``, ``select_many``), the
hypotheses spent, and when an episode ends (psi steps; kappa / varsigma while training; the confidence stop).

Part of ``SampleConsensusEnv`` (a mixin): it owns ``t``, ``budget``, ``ep_first``, ``set_index``, ``used``,
``spent``, ``hypotheses``, ``done``, ``count``, ``same_count``, ``ep_best``, ``no_better``; it reads the rows'
``mask``, the generator ``gen``, ``conf``, ``task`` and, for the confidence stop, the scoring's ``best_count``.
"""

from __future__ import annotations

import math

import torch

from rlsac.estimation.sampling import set_keys, uniform_minimal_sets


class EpisodeBookkeeping:
    """Which rows act, which sets they may take, and when their episodes end."""

    def _start_bookkeeping(self, budget: int | None) -> None:
        """Every row at step 0 of its episode, nothing used or spent; ``budget`` hypotheses per instance (None: every
        episode's steps)."""
        B, E, psi, dev = self.B, self.E, self.conf.steps_per_episode, self.coords.device
        R = B * E
        self.budget = budget if budget is not None else E * psi * self.k
        self.ep_first = torch.arange(R, device=dev) % E * psi  # (R,) first step of each row's episode (instance-major)
        self.set_index = torch.arange(self.k, device=dev)
        self.t = 0
        self.used = torch.full((B, E * psi * self.k), -1, dtype=torch.int64, device=dev)
        self.spent = torch.zeros(B, dtype=torch.long, device=dev)  # hypotheses per instance so far
        self.done = torch.zeros(R, dtype=torch.bool, device=dev)
        self.count = torch.full((R,), -1, dtype=torch.long, device=dev)
        self.same_count = torch.zeros(R, dtype=torch.long, device=dev)
        self.ep_best = torch.full((R,), -1, dtype=torch.long, device=dev)
        self.no_better = torch.zeros(R, dtype=torch.long, device=dev)
        self.hypotheses = 0

    @property
    def active(self) -> torch.Tensor:
        """(R,) rows that still produce hypotheses: episode running and within the budget."""
        return ~self.done & ((self.ep_first + self.t) * self.k < self.budget)

    def counted(self, active: torch.Tensor) -> torch.Tensor:
        """(R, k) the sets of this step within the budget: row e's j-th set is hypothesis (e psi + t) k + j;
        active (R,) = ``self.active``."""
        first = (self.ep_first + self.t) * self.k
        return active[:, None] & (first[:, None] + self.set_index < self.budget)

    def select(self, logits: torch.Tensor, sample: bool = False, random: bool = False) -> torch.Tensor:
        """Pick an unused minimal set per row from per-point scores. logits (R, N) -> idx (R, m).

        Candidate 0 is the top-m (max sampling) or a draw without replacement from softmax(logits)
        (probabilistic sampling, Gumbel top-m); further candidates are always draws from the policy's
        probabilities, as the paper prescribes for a duplicate, then uniform sets in case the policy
        is too peaked to offer an unused one. ``random`` = uniform sets only.
        """
        m, K = self.task.sample_size, self.conf.candidates
        R, N = logits.shape
        logits = logits.masked_fill(~self.mask, float("-inf"))
        uniform = uniform_minimal_sets(self.mask, m, K, self.gen)
        if random:
            cand = uniform
        else:
            u = torch.rand((R, K, N), generator=self.gen, device=logits.device).clamp_(1e-12, 1 - 1e-12)
            gumbel = logits[:, None, :] - torch.log(-torch.log(u))
            cand = gumbel.topk(m, dim=-1).indices
            if not sample:
                cand[:, 0] = logits.topk(m, dim=-1).indices
            # a peaked policy may keep drawing used sets: uniform sets come last as the fallback
            cand = torch.cat([cand, uniform], dim=1)
        K = cand.shape[1]
        keys = set_keys(cand, N)  # (R, K)
        inst = torch.arange(R, device=logits.device) // self.E
        taken = (keys[:, :, None] == self.used[inst][:, None, :]).any(-1)  # (R, K)
        rows = torch.arange(R, device=logits.device)
        earlier = torch.ones(self.E, self.E, dtype=torch.bool, device=logits.device).tril(-1)
        act = self.active.view(self.B, self.E)
        for _ in range(K):
            # each row's first candidate not used before (the last one if all were: a rare repeat)
            free = ~taken
            ptr = torch.where(free.any(-1), free.float().argmax(-1), torch.full_like(rows, K - 1))
            chosen = keys[rows, ptr].view(self.B, self.E)
            same = (chosen[:, :, None] == chosen[:, None, :]) & act[:, :, None] & act[:, None, :]
            dup = (same & earlier).any(-1).flatten() & free.any(-1)
            if not dup.any():
                break
            taken[rows[dup], ptr[dup]] = True  # an earlier episode of the instance took it this step
        return cand[rows, ptr]

    def select_random(self) -> torch.Tensor:
        """Uniformly random unused minimal sets: (R, m) by ``select``, or (R, k, m) by ``select_many`` for k > 1."""
        if self.k == 1:
            return self.select(self.action, random=True)
        return self.select_many(self.action, random=True)

    def select_many(self, logits: torch.Tensor, sample: bool = False, random: bool = False) -> torch.Tensor:
        """k = ``sets_per_step`` unused minimal sets per row from per-point scores. logits (R, N) -> (R, k, m).

        Candidates in order: the top-m (max sampling) or a Gumbel top-m draw, then 2k - 1 more draws without
        replacement from softmax(logits) (``random``: 2k uniform sets); 2k uniform sets are appended while a row
        has fewer than k free ones (a peaked policy; four times at most). A candidate is taken if any episode
        of its instance used it before or an earlier candidate of the instance this step equals it; each row
        gets its first k free candidates (a row short of free ones repeats taken ones, as ``select`` does).
        """
        m, k = self.task.sample_size, self.k
        R, N = logits.shape
        used = self.used.sort(dim=-1).values
        if random:
            cand = uniform_minimal_sets(self.mask, m, 2 * k, self.gen)
        else:
            logits = logits.masked_fill(~self.mask, float("-inf"))
            u = torch.rand((R, 2 * k, N), generator=self.gen, device=logits.device).clamp_(1e-12, 1 - 1e-12)
            cand = (logits[:, None, :] - torch.log(-torch.log(u))).topk(m, dim=-1).indices
            if not sample:
                cand[:, 0] = logits.topk(m, dim=-1).indices
        taken = self._taken(cand, used)
        for _ in range(4):  # a row short of free sets (a peaked policy): 2k more uniform sets, a few times at most
            if not bool(((~taken).sum(-1) < k).any()):
                break
            cand = torch.cat([cand, uniform_minimal_sets(self.mask, m, 2 * k, self.gen)], dim=1)
            taken = self._taken(cand, used)
        J = cand.shape[1]
        rank = torch.arange(J, device=cand.device).expand(R, J) + J * taken
        pick = rank.topk(k, dim=-1, largest=False).indices.sort(dim=-1).values  # the first k free ones
        return cand.gather(1, pick[..., None].expand(R, k, m))

    def _taken(self, cand: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
        """cand (R, J, m) candidate sets, used (B, U) sorted keys -> (R, J): used before by the instance, or
        equal to an earlier candidate of the instance (rows in order, then candidates)."""
        R, J, _ = cand.shape
        keys = set_keys(cand, self.N).view(self.B, self.E * J)
        pos = torch.searchsorted(used, keys).clamp_max_(used.shape[1] - 1)
        taken = used.gather(1, pos) == keys
        srt, order = keys.sort(dim=-1, stable=True)  # equal keys keep their order: the first one is free
        again = torch.cat([torch.zeros_like(srt[:, :1], dtype=torch.bool), srt[:, 1:] == srt[:, :-1]], dim=1)
        return (taken | torch.zeros_like(again).scatter_(1, order, again)).view(R, J)

    def _remember_sets(self, idx: torch.Tensor, counted: torch.Tensor) -> None:
        """The de-duplication memory: this step's set keys idx (R, k, m) of the counted sets, per instance."""
        k = idx.shape[1]
        keys = set_keys(idx, self.N).masked_fill(~counted, -1).view(self.B, self.E * k)
        self.used[:, self.t * self.E * k: (self.t + 1) * self.E * k] = keys

    def _count_hypotheses(self, counted: torch.Tensor) -> None:
        """The hypotheses each instance has spent of its budget: this step's counted sets (R, k)."""
        B, n = self.B, counted.numel() // self.B
        spent = counted.view(B, n).sum(-1)
        self.spent += spent
        self.hypotheses += int(spent.sum())

    def _terminate(self, count: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """Advance the clock; -> done (R,): psi steps always, kappa / varsigma only while training."""
        conf = self.conf
        self.same_count = torch.where(count == self.count, self.same_count + 1, torch.zeros_like(count))
        improved = count > self.ep_best
        self.no_better = torch.where(improved, torch.zeros_like(count), self.no_better + 1)
        self.ep_best = torch.maximum(self.ep_best, count)
        self.count = torch.where(act, count, self.count)
        self.t += 1
        done = torch.full_like(act, self.t >= conf.steps_per_episode)
        if self.training:
            done = done | (self.same_count >= conf.kappa) | (self.no_better >= conf.varsigma)
        elif self.confidence > 0:
            done = done | self.confident().repeat_interleave(self.E)
        return done

    def confident(self) -> torch.Tensor:
        """(B,) instances whose hypotheses so far reach RANSAC's bound log(1 - p) / log(1 - w^m) for
        confidence p and best inlier ratio w (as OpenCV's and MAGSAC++'s termination)."""
        w = (self.best_count.clamp_min(0) / self.inst_mask.sum(-1).clamp_min(1)).double()
        miss = 1.0 - w.pow(self.task.sample_size)  # a minimal set not all inliers
        need = math.log1p(-self.confidence) / torch.log(miss.clamp(1e-300, 1.0 - 1e-16))
        return (self.best_count >= self.task.sample_size) & (self.spent >= need)
