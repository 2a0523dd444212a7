"""Test-time RLSAC: many instances x episodes in one batched rollout, and checkpoint loading."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from rlsac.config import build
from rlsac.env import MEMORY_DIM, EnvConf, SampleConsensusEnv
from rlsac.errors import RlsacError
from rlsac.policy import Actor, PolicyConf
from rlsac.tasks import Task


@torch.no_grad()
def rlsac_estimate(task: Task, batch: dict, actor: Actor, iterations: int, steps_per_episode: int = 15,
                   sampling: str = "max", generator: torch.Generator | None = None,
                   record: bool = False) -> dict:
    """Run ceil(iterations / psi) episodes per instance in parallel, at most ``iterations`` hypotheses.

    batch: coords (B, N, d), mask (B, N), plus what ``task.features`` needs.
    -> hyp (B, *H), valid (B,), inliers (B, N); with ``record`` also ``steps``: per step the minimal
    sets (R, m), hypotheses, inlier masks and rewards of every row (for figures).
    """
    if sampling not in ("max", "prob"):
        raise RlsacError(f"sampling must be 'max' or 'prob', got {sampling!r}")
    if iterations < 1:
        raise RlsacError(f"iterations must be positive, got {iterations}")
    env = SampleConsensusEnv(task, EnvConf(steps_per_episode=steps_per_episode), training=False)
    episodes = math.ceil(iterations / steps_per_episode)
    feats = task.features(batch)
    graph = actor.graph(feats, batch["mask"]).repeat_interleave(episodes, 0)
    state = env.reset(batch, feats, episodes, budget=iterations, generator=generator)
    steps = []
    if record:
        steps.append(_snapshot(env))
    for _ in range(1, steps_per_episode):
        if not env.active.any():
            break
        logits = actor(state, env.mask, graph)
        env.step(env.select(logits, sample=sampling == "prob"))
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
        ckpt = torch.load(path, map_location=device, weights_only=False)
        conf = ckpt["conf"]
        pconf = build(PolicyConf, conf["policy"])
        actor = Actor(ckpt["in_channels"], pconf).to(device)
        actor.load_state_dict(ckpt["actor"])
    except (KeyError, RuntimeError, EOFError, ValueError, TypeError) as e:
        raise RlsacError(f"{path}: not an rlsac checkpoint ({e.__class__.__name__}: {str(e)[:80]})") from None
    actor.eval()
    return actor, conf


def in_channels(task: Task) -> int:
    return task.feature_dim + MEMORY_DIM
