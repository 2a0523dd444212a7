"""The sample-consensus environment of RLSAC (paper Sec. 3.2-3.5), batched on one torch device.

Rows are laid out instance-major: B instances x E parallel episodes = R = B E rows. Every episode
starts from a uniformly random minimal set; each later minimal set comes from the policy. The state
of a row is the instance's data features (N x c) concatenated with three memory features:

* action: +1 for the points of the last minimal set, -1 otherwise;
* residual: distance to the last hypothesis divided by the *state threshold*, clipped at ``residual_clip`` and
  scaled to [0, 1] (inliers span [0, 1/clip]; far outliers saturate at 1). The state threshold is the one the
  policy was trained with (a checkpoint's ``state_scales``, issue #46), not the threshold the evaluation scores
  with: a threshold tuned per fold changes which points count as inliers, never what the policy sees. Without
  one (training, the controls, a checkpoint from before the key) it is the task's inlier threshold;
* history: how many times the point has been in a minimal set of this episode.

Reward = inlier ratio of the hypothesis. A minimal set already used for this instance (by any of its
episodes) is never used again: the next candidate drawn from the policy's probabilities is taken.
The output is the best hypothesis (most inliers) over all episodes, refined on its inliers.

Not in the paper (test time, issue #17): ``sets_per_step`` k > 1 draws k sets per row and step
(``select_many``), scores all of them and acts with the best; ``confidence`` stops an instance at
RANSAC's termination bound (``confident``). k = 1 and confidence 0 are the paper's environment.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from rlsac.baselines import finalize
from rlsac.lo import Best, LOConf, finish, score_sets, update_best
from rlsac.sampling import gather_points, set_keys, uniform_minimal_sets
from rlsac.tasks import Task

MEMORY_DIM = 3


@dataclass
class EnvConf:
    steps_per_episode: int = 15  # psi: hypotheses per episode, the random initial one included (paper)
    kappa: int = 2  # training: stop when the inlier count is unchanged for kappa steps (paper)
    varsigma: int = 3  # training: stop when the episode best is not exceeded for varsigma steps (paper)
    residual_clip: float = 5.0  # residual feature = min(r / eps, clip) / clip; 5 eps separates near-inliers
    candidates: int = 16  # candidate minimal sets drawn per row and step for de-duplication
    # "inlier_ratio" (paper) or "improvement": the gain of the ratio over the episode's best so far,
    # which rewards what the output keeps (the best hypothesis) rather than every good repeat
    reward: str = "inlier_ratio"
    # not in the paper: local optimisation / scoring of the best hypothesis (rlsac.lo); off by default
    lo: LOConf = field(default_factory=LOConf)

    # checked by rlsac.config.build for every source (params.yaml, --set, a checkpoint's env section)
    ranges = {"steps_per_episode": "[1, inf)", "kappa": "[1, inf)", "varsigma": "[1, inf)",
              "residual_clip": "(0, inf)", "candidates": "[1, inf)", "reward": ("inlier_ratio", "improvement")}


class SampleConsensusEnv:
    """Batched environment. Call ``reset`` with a batch, then alternate ``choose`` and ``step``."""

    def __init__(self, task: Task, conf: EnvConf, training: bool, state_threshold: float | None = None):
        """state_threshold: the residual scale of the policy's state (in the task's residual unit); None = the
        task's inlier threshold (the two are one while training)."""
        if state_threshold is not None and not (math.isfinite(state_threshold) and state_threshold > 0):
            raise ValueError(f"state_threshold must be a positive number, got {state_threshold!r}")
        self.task, self.conf, self.training = task, conf, training
        self.state_threshold = float(task.threshold if state_threshold is None else state_threshold)

    # ---------------------------------------------------------------- setup
    def reset(self, batch: dict, features: torch.Tensor, episodes: int = 1, budget: int | None = None,
              generator: torch.Generator | None = None, first: torch.Tensor | None = None,
              sets_per_step: int = 1, confidence: float = 0.0) -> torch.Tensor:
        """Start ``episodes`` episodes per instance; returns the first state (R, N, c + 3).

        batch: coords (B, N, d), mask (B, N); features (B, N, c) network data features.
        budget: total hypotheses per instance (test time); rows past it stay inactive.
        first: (R, m) initial minimal sets instead of uniformly random ones (tests, figures).
        sets_per_step: k minimal sets per row and step (test time, not in the paper): all k are scored and
        compete for the output; the best of them is the step's action (memory, reward). 1 = the paper.
        confidence: test time, not in the paper; > 0 stops an instance once RANSAC's termination bound
        log(1 - confidence) / log(1 - w^m) (w = its best inlier ratio) is below its hypotheses so far.
        """
        coords, mask = batch["coords"], batch["mask"]
        B, N, _ = coords.shape
        E, psi, dev = episodes, self.conf.steps_per_episode, coords.device
        self.B, self.E, self.N, self.k = B, E, N, int(sets_per_step)
        self.confidence = float(confidence)
        self.gen = generator
        self.inst_coords, self.inst_mask = coords, mask
        self.coords = coords.repeat_interleave(E, 0)
        self.mask = mask.repeat_interleave(E, 0)
        self.data = features.repeat_interleave(E, 0)
        self.n_valid = self.mask.sum(-1).clamp_min(1)
        self.budget = budget if budget is not None else E * psi * self.k
        R = B * E
        self.ep_first = torch.arange(R, device=dev) % E * psi  # (R,) first step of each row's episode (instance-major)
        self.set_index = torch.arange(self.k, device=dev)
        self.t = 0
        self.used = torch.full((B, E * psi * self.k), -1, dtype=torch.int64, device=dev)
        self.spent = torch.zeros(B, dtype=torch.long, device=dev)  # hypotheses per instance so far
        self.history = torch.zeros((R, N), device=dev)
        self.action = torch.full((R, N), -1.0, device=dev)
        self.residual = torch.ones((R, N), device=dev)
        self.done = torch.zeros(R, dtype=torch.bool, device=dev)
        self.count = torch.full((R,), -1, dtype=torch.long, device=dev)
        self.same_count = torch.zeros(R, dtype=torch.long, device=dev)
        self.ep_best = torch.full((R,), -1, dtype=torch.long, device=dev)
        self.no_better = torch.zeros(R, dtype=torch.long, device=dev)
        self.best = Best.empty(B, dev)  # best hypothesis per instance (rlsac.lo.update_best, LO if conf.lo)
        self.best_count = self.best.count
        self.best_hyp: torch.Tensor | None = None
        self.hypotheses = 0
        self.step(self.select_random() if first is None else first)
        return self.state()

    def state(self) -> torch.Tensor:
        return torch.cat([self.data, self.memory()], dim=-1)

    def memory(self) -> torch.Tensor:
        """(R, N, 3): action, residual, history."""
        return torch.stack([self.action, self.residual, self.history], dim=-1)

    @property
    def active(self) -> torch.Tensor:
        """(R,) rows that still produce hypotheses: episode running and within the budget."""
        return ~self.done & ((self.ep_first + self.t) * self.k < self.budget)

    def counted(self, active: torch.Tensor) -> torch.Tensor:
        """(R, k) the sets of this step within the budget: row e's j-th set is hypothesis (e psi + t) k + j;
        active (R,) = ``self.active``."""
        first = (self.ep_first + self.t) * self.k
        return active[:, None] & (first[:, None] + self.set_index < self.budget)

    # ---------------------------------------------------------------- acting
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

    def step(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Apply minimal sets idx (R, m), or (R, k, m) with k = ``sets_per_step``. Returns reward (R,),
        done (R,), active-before-step (R,)."""
        act = self.active
        idx = idx[:, None] if idx.dim() == 2 else idx
        counted = self.counted(act) if idx.shape[1] > 1 else act[:, None]
        hyps, valid, res, count = self._score(idx)  # (R, k, ...)
        pick = count.masked_fill(~counted, -1).argmax(-1)  # the step's action: its best set
        rows = torch.arange(idx.shape[0], device=idx.device)
        res_a, count_a = res[rows, pick], count[rows, pick]
        self.last_hyps, self.last_inliers = hyps[rows, pick], (res_a <= self.task.threshold) & self.mask
        reward = self._reward(count_a)
        self._update_memory(idx[rows, pick], res_a, act)
        self._remember_sets(idx, counted)
        self._update_best(hyps, count, res, counted)
        done = self._terminate(count_a, act)
        newly = act & done
        self.done = self.done | done
        return reward * act, newly, act

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

    def _update_memory(self, idx: torch.Tensor, res: torch.Tensor, act: torch.Tensor) -> None:
        """The memory features of the next state; only rows that acted change."""
        conf = self.conf
        onehot = torch.zeros_like(self.action, dtype=torch.bool).scatter_(1, idx, True)
        a = act[:, None]
        self.action = torch.where(a, onehot.float() * 2 - 1, self.action)
        r_feat = (res / self.state_threshold).clamp(max=conf.residual_clip) / conf.residual_clip
        self.residual = torch.where(a, r_feat.masked_fill(~self.mask, 1.0), self.residual)
        self.history = self.history + (onehot & a).float()

    def _remember_sets(self, idx: torch.Tensor, counted: torch.Tensor) -> None:
        """The de-duplication memory: this step's set keys idx (R, k, m) of the counted sets, per instance."""
        k = idx.shape[1]
        keys = set_keys(idx, self.N).masked_fill(~counted, -1).view(self.B, self.E * k)
        self.used[:, self.t * self.E * k: (self.t + 1) * self.E * k] = keys

    def _update_best(self, hyps: torch.Tensor, count: torch.Tensor, res: torch.Tensor, counted: torch.Tensor) -> None:
        """The best hypothesis of each instance over all its episodes (with LO if ``conf.lo``)."""
        B, n = self.B, count.numel() // self.B
        c = count.masked_fill(~counted, -1).view(B, n)
        self.best = update_best(self.task, self.conf.lo, self.inst_coords, self.inst_mask, self.best,
                                hyps.reshape(B, n, *hyps.shape[2:]), c, res.reshape(B, n, -1), self.gen)
        self.best_hyp, self.best_count = self.best.hyp, self.best.count
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

    # ---------------------------------------------------------------- output
    def instances(self) -> tuple[torch.Tensor, torch.Tensor]:
        """coords (B, N, d), mask (B, N) of the instances (rows are instance-major)."""
        return self.inst_coords, self.inst_mask

    def result(self) -> dict[str, torch.Tensor]:
        """Best hypothesis per instance over all episodes, refined on its inliers (with LO: rlsac.lo.finish)."""
        coords, mask = self.instances()
        if self.conf.lo.enabled:
            return finish(self.task, self.conf.lo, coords, mask, self.best, self.gen)
        return finalize(self.task, coords, mask, self.best_hyp, self.best_count >= self.task.sample_size)
