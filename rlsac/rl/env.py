"""The sample-consensus environment of RLSAC (paper Sec. 3.2-3.5), batched on one torch device: ``EnvConf`` and
``SampleConsensusEnv``, composed of its state encoding (rlsac.rl.env_state), episode bookkeeping
(rlsac.rl.env_bookkeeping)
and scoring (rlsac.rl.env_scoring).

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

from rlsac.estimation.lo import LOConf
from rlsac.rl.env_bookkeeping import EpisodeBookkeeping
from rlsac.rl.env_scoring import Scoring
from rlsac.rl.env_state import MEMORY_DIM, StateEncoding  # noqa: F401  (MEMORY_DIM: also rlsac.rl.env's)
from rlsac.tasks import Task


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
    # not in the paper: local optimisation / scoring of the best hypothesis (rlsac.estimation.lo); off by default
    lo: LOConf = field(default_factory=LOConf)

    # checked by rlsac.config.build for every source (params.yaml, --set, a checkpoint's env section)
    ranges = {"steps_per_episode": "[1, inf)", "kappa": "[1, inf)", "varsigma": "[1, inf)",
              "residual_clip": "(0, inf)", "candidates": "[1, inf)", "reward": ("inlier_ratio", "improvement")}


class SampleConsensusEnv(StateEncoding, EpisodeBookkeeping, Scoring):
    """Batched environment. Call ``reset`` with a batch, then alternate ``choose`` and ``step``. Its parts: the
    state encoding (``state``), the episode bookkeeping (``active``, ``select``, ``select_many``, ``confident``) and
    the scoring (``result``); ``reset`` and ``step`` compose them."""

    def __init__(self, task: Task, conf: EnvConf, training: bool, state_threshold: float | None = None):
        """state_threshold: the residual scale of the policy's state (in the task's residual unit); None = the
        task's inlier threshold (the two are one while training)."""
        if state_threshold is not None and not (math.isfinite(state_threshold) and state_threshold > 0):
            raise ValueError(f"state_threshold must be a positive number, got {state_threshold!r}")
        self.task, self.conf, self.training = task, conf, training
        self.state_threshold = float(task.threshold if state_threshold is None else state_threshold)

    # ---------------------------------------------------------------- an episode: start, transition
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
        self.B, self.E, self.N, self.k = B, episodes, N, int(sets_per_step)
        self.confidence = float(confidence)
        self.gen = generator
        self.inst_coords, self.inst_mask = coords, mask
        self.coords = coords.repeat_interleave(episodes, 0)
        self.mask = mask.repeat_interleave(episodes, 0)
        self._start_state(features)
        self._start_bookkeeping(budget)
        self._start_scoring()
        self.step(self.select_random() if first is None else first)
        return self.state()

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
        self._count_hypotheses(counted)
        done = self._terminate(count_a, act)
        newly = act & done
        self.done = self.done | done
        return reward * act, newly, act
