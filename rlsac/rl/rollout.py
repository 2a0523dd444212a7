"""Test-time RLSAC: many instances x episodes in one batched rollout, and checkpoint loading."""

from __future__ import annotations

import math

import torch

from rlsac.errors import RlsacError
from rlsac.estimation.sampling import set_keys
from rlsac.rl.env import MEMORY_DIM, EnvConf, SampleConsensusEnv
from rlsac.rl.policy import Actor
from rlsac.tasks import Task


@torch.inference_mode()
def rlsac_estimate(task: Task, batch: dict, actor: Actor | None, iterations: int, env_conf: EnvConf | None = None,
                   sampling: str = "max", generator: torch.Generator | None = None,
                   record: bool = False, reference: bool = False, guide: torch.Tensor | None = None,
                   policy_every: int = 1, sets_per_step: int = 1, confidence: float = 0.0,
                   state_threshold: float | None = None) -> dict:
    """Run ceil(iterations / (psi k)) episodes per instance in parallel, at most ``iterations`` hypotheses.

    batch: coords (B, N, d), mask (B, N), plus what ``task.features`` needs.
    actor None = the uniform control: the same environment (episodes, de-duplication, scoring,
    refinement, budget) with uniformly random minimal sets instead of the policy's.
    guide (B, N): with actor None, fixed per-point logits instead of the policy's (the guided control:
    minimal sets drawn without replacement with probabilities ~ exp(guide), Gumbel top-m as ``prob``).
    env_conf: the environment of the checkpoint (``rlsac.rl.checkpoint.env_conf``); default EnvConf().
    -> hyp (B, *H), valid (B,), inliers (B, N); with ``record`` also ``steps``: per step the minimal
    sets (R, m), hypotheses, inlier masks and rewards of every row (for figures).
    reference: the original per-step path (the full (R, N, c + 3) state through
    ``actor.reference_forward``), kept for the equivalence test and the benchmarks' before/after
    ratios. The default path sends the data channels through the first layer once per instance
    (``actor.precompute``) and only the 3 memory channels per step (``actor.forward_memory``), and
    picks minimal sets with ``select_lazily``: the same function, the same final hypotheses
    (tests/test_speed_equivalence.py).
    policy_every: the policy's logits are recomputed every ``policy_every`` steps and reused in between
    (the memory features still change every step; a reused set is taken, so the environment's fallback draws
    from the same probabilities). 1 = every step (the paper). Not in the paper: a speed lever (issue #17,
    reports/speed.md).
    sets_per_step: k minimal sets drawn per row and step from the policy's probabilities (``env.select_many``),
    all scored, the best of them the step's action; one network call per k hypotheses. 1 = the paper.
    confidence: > 0 stops an instance at RANSAC's termination bound (``SampleConsensusEnv.confident``); 0 = the
    whole budget (the paper). Both not in the paper: speed levers (reports/speed.md).
    state_threshold: the residual scale of the policy's state (a checkpoint's ``state_scales``); None = the task's
    inlier threshold (``SampleConsensusEnv``). Scoring and inlier counts always use ``task.threshold``.
    """
    if sampling not in ("max", "prob"):
        raise RlsacError(f"sampling must be 'max' or 'prob', got {sampling!r}")
    if iterations < 1:
        raise RlsacError(f"iterations must be positive, got {iterations}")
    if policy_every < 1 or (policy_every > 1 and reference):
        raise RlsacError(f"policy_every must be >= 1 (1 on the reference path), got {policy_every}")
    if sets_per_step < 1 or (sets_per_step > 1 and reference):
        raise RlsacError(f"sets_per_step must be >= 1 (1 on the reference path), got {sets_per_step}")
    if not 0.0 <= confidence < 1.0:
        raise RlsacError(f"confidence must be in [0, 1), got {confidence}")
    if guide is not None and (actor is not None or guide.shape != batch["mask"].shape):
        raise RlsacError(f"guide must be (B, N) = {tuple(batch['mask'].shape)} logits without an actor")
    conf = env_conf or EnvConf()
    psi = conf.steps_per_episode
    env = SampleConsensusEnv(task, conf, training=False, state_threshold=state_threshold)
    k = int(sets_per_step)
    episodes = math.ceil(iterations / (psi * k))
    feats = task.features(batch)
    graph = prepared = None
    if actor is not None and reference:
        graph = actor.graph(feats, batch["mask"]).repeat_interleave(episodes, 0)
    elif actor is not None:
        prepared = actor.precompute(feats, batch["mask"], episodes)
    state = env.reset(batch, feats, episodes, budget=iterations, generator=generator, sets_per_step=k,
                      confidence=confidence)
    select = select_lazily if k == 1 else SampleConsensusEnv.select_many
    steps = []
    if record:
        steps.append(_snapshot(env))
    if guide is not None:
        guide = guide.to(feats.dtype).repeat_interleave(episodes, 0)
    logits = None
    for t in range(1, psi):
        if not env.active.any():
            break
        if guide is not None:  # the guided control: a fixed, hand-made sampling distribution
            env.step(select(env, guide, sample=True))
        elif actor is None:  # the uniform control
            env.step(env.select_random())
        else:
            if reference:
                logits = actor.reference_forward(state, env.mask, graph)
                env.step(env.select(logits, sample=sampling == "prob"))
                state = env.state()
            else:
                if logits is None or (t - 1) % policy_every == 0:
                    logits = actor.forward_memory(prepared, env.memory())
                env.step(select(env, logits, sample=sampling == "prob"))
        if record:
            steps.append(_snapshot(env))
    out = env.result()
    out["hypotheses"] = env.spent.clone()  # (B,) minimal sets scored per instance (< budget after a confidence stop)
    if record:
        out["steps"] = steps
    return out


def select_lazily(env: SampleConsensusEnv, logits: torch.Tensor, sample: bool = False) -> torch.Tensor:
    """``env.select(logits, sample)`` with the same random draws and the same result, computed lazily.

    ``env.select`` ranks all 2 x ``candidates`` fallback sets of every row (two (R, K, N) top-m and
    log-log passes) and compares each with every used set of its instance ((R, 2K, E psi) equalities),
    although a row almost always keeps its first candidate. Here the first candidate is ranked for every
    row and the fallbacks only for rows whose first candidate is taken (used before, or chosen by an
    earlier episode of the instance in this step); used sets are looked up by binary search. The
    random numbers are drawn exactly as ``env.select`` draws them, so the stream stays in step.
    """
    m, K, B, E = env.task.sample_size, env.conf.candidates, env.B, env.E
    R, N = logits.shape
    dev = logits.device
    logits = logits.masked_fill(~env.mask, float("-inf"))
    r_uniform = torch.rand((R, K, N), generator=env.gen, device=dev)  # uniform_minimal_sets' draw
    u = torch.rand((R, K, N), generator=env.gen, device=dev)
    if sample:
        first = (logits - torch.log(-torch.log(u[:, 0].clamp(1e-12, 1 - 1e-12)))).topk(m, dim=-1).indices
    else:
        first = logits.topk(m, dim=-1).indices
    J = 2 * K
    rows = torch.arange(R, device=dev)
    inst = rows // E
    used = env.used.sort(dim=-1).values  # (B, E psi): -1 = empty slot, never a key

    def member(keys: torch.Tensor, seq: torch.Tensor) -> torch.Tensor:
        pos = torch.searchsorted(seq, keys).clamp_max_(seq.shape[1] - 1)
        return seq.gather(1, pos) == keys

    keys = torch.full((R, J), -2, dtype=torch.int64, device=dev)  # -2: fallback not ranked (yet)
    key0 = set_keys(first, N)
    keys[:, 0] = key0
    taken = torch.zeros((R, J), dtype=torch.bool, device=dev)
    taken[:, 0] = member(key0.view(B, E), used).view(R)
    cand = torch.zeros((R, J, m), dtype=torch.int64, device=dev)
    ranked = torch.zeros(R, dtype=torch.bool, device=dev)

    def rank(sel: torch.Tensor) -> None:
        """The full candidate list of rows ``sel``, exactly as env.select builds it."""
        g = logits[sel][:, None, :] - torch.log(-torch.log(u[sel].clamp_(1e-12, 1 - 1e-12)))
        c = g.topk(m, dim=-1).indices
        c[:, 0] = first[sel]
        uni = r_uniform[sel].masked_fill(~env.mask[sel][:, None, :], -1.0).topk(m, dim=-1).indices
        c = torch.cat([c, uni], dim=1)
        k = set_keys(c, N)
        t = member(k, used[inst[sel]])
        t[:, 0] |= taken[sel, 0]
        keys[sel], taken[sel], cand[sel], ranked[sel] = k, t, c, True

    if taken[:, 0].any():
        rank(rows[taken[:, 0]])
    earlier = torch.ones(E, E, dtype=torch.bool, device=dev).tril(-1)
    act = env.active.view(B, E)
    for _ in range(J):  # env.select's loop; unranked rows sit on their free first candidate
        free = ~taken
        some = free.any(-1)
        ptr = torch.where(some, free.float().argmax(-1), torch.full_like(rows, J - 1))
        chosen = keys[rows, ptr].view(B, E)
        same = (chosen[:, :, None] == chosen[:, None, :]) & act[:, :, None] & act[:, None, :]
        dup = (same & earlier).any(-1).flatten() & some
        if not dup.any():
            break
        taken[rows[dup], ptr[dup]] = True
        fresh = dup & ~ranked
        if fresh.any():
            rank(rows[fresh])
    return torch.where(ranked[:, None], cand[rows, ptr], first)


def _snapshot(env: SampleConsensusEnv) -> dict:
    a = env.action > 0
    m = env.task.sample_size
    return {
        "minimal_set": a.float().topk(m, dim=-1).indices.cpu(),
        "hyp": env.last_hyps.cpu(),
        "inliers": env.last_inliers.cpu(),
        "count": env.count.cpu(),
    }


def in_channels(task: Task) -> int:
    return task.feature_dim + MEMORY_DIM


def with_lo(env: EnvConf, lo) -> EnvConf:
    """The environment conf with LO ``lo`` (rlsac.estimation.lo.LOConf), or unchanged when ``lo`` is None."""
    from dataclasses import replace

    return env if lo is None else replace(env, lo=lo)
