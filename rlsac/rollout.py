"""Test-time RLSAC: many instances x episodes in one batched rollout, and checkpoint loading."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from rlsac.config import build
from rlsac.env import MEMORY_DIM, EnvConf, SampleConsensusEnv
from rlsac.errors import RlsacError
from rlsac.io import load_torch
from rlsac.policy import Actor, PolicyConf
from rlsac.tasks import Task


@torch.no_grad()
def rlsac_estimate(task: Task, batch: dict, actor: Actor | None, iterations: int, env_conf: EnvConf | None = None,
                   sampling: str = "max", generator: torch.Generator | None = None,
                   record: bool = False, reference: bool = False) -> dict:
    """Run ceil(iterations / psi) episodes per instance in parallel, at most ``iterations`` hypotheses.

    batch: coords (B, N, d), mask (B, N), plus what ``task.features`` needs.
    actor None = the uniform control: the same environment (episodes, de-duplication, scoring,
    refinement, budget) with uniformly random minimal sets instead of the policy's.
    env_conf: the environment of the checkpoint (``checkpoint_env``); default EnvConf().
    -> hyp (B, *H), valid (B,), inliers (B, N); with ``record`` also ``steps``: per step the minimal
    sets (R, m), hypotheses, inlier masks and rewards of every row (for figures).
    reference: the original per-step path (the full (R, N, c + 3) state through
    ``actor.reference_forward``), kept for the equivalence test and the benchmarks' before/after
    ratios. The default path sends the data channels through the first layer once per instance
    (``actor.precompute``) and only the 3 memory channels per step (``actor.forward_memory``): the
    same function, same final hypotheses (tests/test_speed_equivalence.py).
    """
    if sampling not in ("max", "prob"):
        raise RlsacError(f"sampling must be 'max' or 'prob', got {sampling!r}")
    if iterations < 1:
        raise RlsacError(f"iterations must be positive, got {iterations}")
    conf = env_conf or EnvConf()
    psi = conf.steps_per_episode
    env = SampleConsensusEnv(task, conf, training=False)
    episodes = math.ceil(iterations / psi)
    feats = task.features(batch)
    graph = prepared = None
    if actor is not None and reference:
        graph = actor.graph(feats, batch["mask"]).repeat_interleave(episodes, 0)
    elif actor is not None:
        prepared = actor.precompute(feats, batch["mask"], episodes)
    state = env.reset(batch, feats, episodes, budget=iterations, generator=generator)
    steps = []
    if record:
        steps.append(_snapshot(env))
    for _ in range(1, psi):
        if not env.active.any():
            break
        if actor is None:
            env.step(env.select(env.action, random=True))
            continue
        if reference:
            logits = actor.reference_forward(state, env.mask, graph)
        else:
            logits = actor.forward_memory(prepared, env.memory())
        env.step(env.select(logits, sample=sampling == "prob"))
        if reference:
            state = env.state()
        if record:
            steps.append(_snapshot(env))
    out = env.result()
    out["hypotheses"] = env.hypotheses
    if record:
        out["steps"] = steps
    return out


def _snapshot(env: SampleConsensusEnv) -> dict:
    a = env.action > 0
    m = env.task.sample_size
    return {
        "minimal_set": a.float().topk(m, dim=-1).indices.cpu(),
        "hyp": env.last_hyps.cpu(),
        "inliers": env.last_inliers.cpu(),
        "count": env.count.cpu(),
    }


def load_actor(path: str | Path, device: str | torch.device = "cpu") -> tuple[Actor, dict]:
    """Load an actor checkpoint written by ``rlsac train`` -> (actor in eval mode, training conf)."""
    path = Path(path)
    if not path.is_file():
        raise RlsacError(f"{path}: no such checkpoint")
    try:
        ckpt = load_torch(path, device)  # a text or h5 file: one-line error
        conf = ckpt["conf"]
        pconf = build(PolicyConf, conf["policy"])
        actor = Actor(ckpt["in_channels"], pconf).to(device)
        actor.load_state_dict(ckpt["actor"])
    except (KeyError, RuntimeError, EOFError, ValueError, TypeError) as e:
        raise RlsacError(f"{path}: not an rlsac checkpoint ({e.__class__.__name__}: {str(e)[:80]})") from None
    actor.eval()
    return actor, conf


def checkpoint_env(ckpt_conf: dict, steps_per_episode: int | None = None) -> EnvConf:
    """The environment a checkpoint was trained with (its ``env`` section), psi optionally overridden."""
    env = dict((ckpt_conf or {}).get("env") or {})
    if steps_per_episode is not None:
        env["steps_per_episode"] = int(steps_per_episode)
    return build(EnvConf, env, "checkpoint env")


def in_channels(task: Task) -> int:
    return task.feature_dim + MEMORY_DIM
