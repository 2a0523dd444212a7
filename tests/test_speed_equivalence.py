"""The fast evaluation paths compute the reference function (issue #17).

``PointNet.reference_forward`` is the original forward pass and ``rlsac_estimate(..., reference=True)``
the original rollout (full state per step, ``env.select``). The fast paths (fused ``forward``, the
per-instance ``precompute`` + ``forward_memory``, ``select_lazily``) must give the same logits up to
float32 rounding and the same final hypothesis on every instance.

Logit tolerance: 1e-5 absolute plus 1e-6 of the largest logit. The shipped checkpoints produce logits
up to ~50, where one float32 ulp is 4e-6: any change in the order of a 264-term sum moves them by a
few ulps (measured 1.4e-5 - 2.8e-5 there), so a purely absolute 1e-5 only holds for logits below ~10.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from rlsac.data import lines
from rlsac.errors import RlsacError
from rlsac.rl.checkpoint import env_conf, load_actor
from rlsac.rl.env import EnvConf, SampleConsensusEnv
from rlsac.rl.policy import Actor, Critic, PolicyConf
from rlsac.rl.rollout import rlsac_estimate, select_lazily
from rlsac.tasks.fundamental import FundamentalTask
from rlsac.tasks.line import LineTask

ROOT = Path(__file__).resolve().parents[1]


def close(fast: torch.Tensor, ref: torch.Tensor) -> None:
    """Same -inf pattern (masked points) and finite values within 1e-5 + 1e-6 max|ref|."""
    fin = torch.isfinite(ref)
    assert torch.equal(fin, torch.isfinite(fast))
    tol = 1e-5 + 1e-6 * ref[fin].abs().max().item()
    assert (fast[fin] - ref[fin]).abs().max().item() <= tol


def two_view_batch(B: int, N: int = 150, outlier_rate: float = 0.3, pad: int = 0, seed: int = 0) -> dict:
    """Synthetic pairs (1000 x 750 px, f = 800, 5-20 deg rotation, sideways baseline); ``pad`` padded
    points at the end of instance 0; descriptor channels at the scale of the real SIFT features."""
    rng = np.random.default_rng(seed)
    W, H = 1000.0, 750.0
    K = np.array([[800.0, 0, W / 2], [0, 800.0, H / 2], [0, 0, 1]])
    coords = np.zeros((B, N, 4), np.float32)
    for b in range(B):
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        th = np.radians(rng.uniform(5, 20))
        R = np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S
        t = np.array([1.0, rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)])
        X = np.stack([rng.uniform(-4, 4, 20 * N), rng.uniform(-3, 3, 20 * N), rng.uniform(5, 10, 20 * N)], 1)
        X2 = X @ R.T + t
        x1, x2 = X @ K.T, X2 @ K.T
        x1, x2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
        ok = (X2[:, 2] > 0) & (x1 >= 0).all(1) & (x1 < [W, H]).all(1) & (x2 >= 0).all(1) & (x2 < [W, H]).all(1)
        pts = np.concatenate([x1, x2], 1)[ok][:N] + rng.normal(scale=0.5, size=(N, 4))
        out = rng.choice(N, int(round(N * outlier_rate)), replace=False)
        pts[out, 2:] = rng.uniform([0, 0], [W, H], size=(out.size, 2))
        coords[b] = pts
    mask = np.ones((B, N), bool)
    if pad:
        coords[0, N - pad:] = 0
        mask[0, N - pad:] = False
    feats = np.concatenate([coords, rng.uniform(0, 1, (B, N, 1)), rng.uniform(0, 0.2, (B, N, 256))], -1)
    size = np.tile([W, H], (B, 1))
    return {"coords": torch.from_numpy(coords), "mask": torch.from_numpy(mask),
            "features": torch.from_numpy(feats.astype(np.float32)), "size1": size, "size2": size.copy()}


def line_batch(n: int, rate: float = 0.6, seed: int = 5) -> dict:
    return lines.to_batch(lines.generate(lines.LineDataConf(outlier_rate=rate, n_instances=n, seed=seed)))


def rollout_states(actor, task, batch, episodes, steps=5, env_conf=None):
    """(features, states (R, N, c + 3), memories, row masks, row graph) along a real rollout."""
    env = SampleConsensusEnv(task, env_conf or EnvConf(), training=False)
    feats = task.features(batch)
    state = env.reset(batch, feats, episodes, generator=torch.Generator().manual_seed(0))
    graph = actor.graph(feats, batch["mask"]).repeat_interleave(episodes, 0)
    out = []
    with torch.no_grad():
        for _ in range(steps):
            out.append((state, env.memory()))
            env.step(env.select(actor.reference_forward(state, env.mask, graph)))
            state = env.state()
    return feats, out, env.mask, graph


# ---------------------------------------------------------------------------------- network
@pytest.mark.parametrize("dynamic", [False, True])
@pytest.mark.parametrize("cls", [Actor, Critic])
def test_forward_and_gradients_match_reference(cls, dynamic):
    torch.manual_seed(0)
    net = cls(5, PolicyConf(dynamic=dynamic))
    s = torch.rand(6, 40, 5)
    mask = torch.ones(6, 40, dtype=torch.bool)
    mask[2, 31:] = False
    out, ref = net(s, mask), net.reference_forward(s, mask)
    close(out, ref)
    fin = torch.isfinite(ref)
    grads = torch.autograd.grad(out[fin].square().sum(), list(net.parameters()))
    ref_grads = torch.autograd.grad(ref[fin].square().sum(), list(net.parameters()))
    for g, r in zip(grads, ref_grads, strict=True):
        assert (g - r).abs().max().item() <= 1e-5 * r.abs().max().item()


def test_small_network_and_unmasked_forward():
    """Other widths (2 EdgeConv layers, narrow head) and mask=None take the same fast paths."""
    torch.manual_seed(1)
    net = Actor(5, PolicyConf(widths=[8, 8], global_width=8, head_width=8))
    s = torch.rand(4, 30, 5)
    close(net(s), net.reference_forward(s))
    prep = net.precompute(s[::2, :, :2], None, episodes=2)
    close(net.forward_memory(prep, s[:, :, 2:]), net.reference_forward(torch.cat([s[::2, :, :2].repeat_interleave(2, 0),
                                                                                  s[:, :, 2:]], -1)))


@pytest.mark.parametrize("chunk_points", [100, 250, 1 << 20])
def test_forward_memory_matches_reference_on_rollout_states(chunk_points):
    """Precomputed data channels + per-step memory: chunks splitting an instance's episodes (100),
    holding several instances (250) or everything (2^20); padded points in instance 0."""
    torch.manual_seed(2)
    task = FundamentalTask()
    actor = Actor(264, PolicyConf(graph_dims=4))
    batch = two_view_batch(3, N=40, pad=7)
    E = 5
    feats, states, mask, graph = rollout_states(actor, task, batch, E, steps=3)
    prep = actor.precompute(feats, batch["mask"], E, chunk_points=chunk_points)
    assert len(prep.chunks) == {100: 9, 250: 3, 1 << 20: 1}[chunk_points]
    with torch.no_grad():
        for state, memory in states:
            ref = actor.reference_forward(state, mask, graph)
            close(actor.forward_memory(prep, memory), ref)
            close(actor(state, mask, graph), ref)


@pytest.mark.parametrize("ckpt,task_name", [("checkpoints/folds/hard/fountain/rlsac.pt", "fundamental"),
                                            ("checkpoints/line_o0.7.pt", "line")])
def test_checkpoint_logits_match_reference(ckpt, task_name):
    """The shipped checkpoints keep loading (same state_dict keys) and give the reference logits."""
    actor, conf = load_actor(ROOT / ckpt)
    task = FundamentalTask() if task_name == "fundamental" else LineTask()
    batch = two_view_batch(2) if task_name == "fundamental" else line_batch(4)
    E = 6
    feats, states, mask, graph = rollout_states(actor, task, batch, E, steps=4, env_conf=env_conf(conf))
    prep = actor.precompute(feats, batch["mask"], E)
    with torch.no_grad():
        for state, memory in states:
            ref = actor.reference_forward(state, mask, graph)
            close(actor.forward_memory(prep, memory), ref)
            close(actor(state, mask, graph), ref)


# ---------------------------------------------------------------------------------- selection
@pytest.mark.parametrize("sample", [False, True])
@pytest.mark.parametrize("n_points,candidates", [(7, 3), (30, 16)])
def test_select_lazily_is_env_select(sample, n_points, candidates):
    """Same minimal sets and same generator state, with peaked logits that keep proposing used sets
    (7 points: C(7, 2) = 21 sets for 8 episodes x 15 steps, so fallbacks run out too)."""
    task = LineTask()
    rng = torch.Generator().manual_seed(3)
    batch = {"coords": torch.rand(4, n_points, 2, generator=rng) * 10,
             "mask": torch.ones(4, n_points, dtype=torch.bool)}
    batch["mask"][1, -2:] = False
    E = 8
    env = SampleConsensusEnv(task, EnvConf(candidates=candidates), training=False)
    g = torch.Generator().manual_seed(0)
    env.reset(batch, task.features(batch), E, budget=E * 15 - 5, generator=g)
    moved = 0
    for t in range(14):
        logits = torch.randn(4 * E, n_points, generator=torch.Generator().manual_seed(t)) * 0.01
        logits[:, :3] += 5.0
        before = g.get_state()
        ref = env.select(logits, sample=sample)
        after = g.get_state()
        g.set_state(before)
        fast = select_lazily(env, logits, sample=sample)
        assert torch.equal(fast, ref)
        assert torch.equal(g.get_state(), after)
        top = logits.masked_fill(~env.mask, float("-inf")).topk(2, dim=-1).indices
        moved += int((ref.sort(-1).values != top.sort(-1).values).any(-1).sum())
        env.step(ref)
    assert moved > 50  # the fallbacks were exercised


# ---------------------------------------------------------------------------------- rollouts
@pytest.mark.parametrize("sampling", ["max", "prob"])
def test_line_rollout_same_final_hypotheses(sampling):
    actor, conf = load_actor(ROOT / "checkpoints/line_o0.7.pt")
    task, env = LineTask(), env_conf(conf)
    batch = line_batch(24, rate=0.7)
    outs = [rlsac_estimate(task, batch, actor, 150, env, sampling=sampling,
                           generator=torch.Generator().manual_seed(4), reference=ref) for ref in (True, False)]
    assert torch.equal(outs[0]["hyp"], outs[1]["hyp"])
    assert torch.equal(outs[0]["inliers"], outs[1]["inliers"])
    assert int(outs[0]["hypotheses"].sum()) == int(outs[1]["hypotheses"].sum()) == 24 * 150


def test_fundamental_rollout_same_final_hypotheses():
    actor, conf = load_actor(ROOT / "checkpoints/folds/hard/fountain/rlsac.pt")
    task, env = FundamentalTask(), env_conf(conf)
    batch = two_view_batch(3, pad=10, seed=1)
    outs = [rlsac_estimate(task, batch, actor, 200, env, generator=torch.Generator().manual_seed(5), reference=ref)
            for ref in (True, False)]
    assert torch.equal(outs[0]["hyp"], outs[1]["hyp"])
    assert torch.equal(outs[0]["inliers"], outs[1]["inliers"])
    assert outs[0]["valid"].all()


@pytest.mark.parametrize("every,calls", [(1, 14), (3, 5), (14, 1), (100, 1)])
def test_policy_every_reuses_the_logits_between_network_calls(every, calls, monkeypatch):
    """policy_every = k: the network runs at steps 1, 1 + k, ... of the psi = 15 step episode (14 policy steps),
    the environment still steps every time; k = 1 is the default rollout exactly."""
    torch.manual_seed(0)
    actor = Actor(5, PolicyConf()).eval()
    task, batch = LineTask(), line_batch(3)
    seen = []
    forward = Actor.forward_memory

    def counting(self, prep, memory):
        seen.append(memory.clone())
        return forward(self, prep, memory)

    monkeypatch.setattr(Actor, "forward_memory", counting)
    out = rlsac_estimate(task, batch, actor, 30, generator=torch.Generator().manual_seed(1), policy_every=every)
    assert len(seen) == calls and int(out["hypotheses"].sum()) == 3 * 30
    if every == 1:
        ref = rlsac_estimate(task, batch, actor, 30, generator=torch.Generator().manual_seed(1))
        assert torch.equal(out["hyp"], ref["hyp"])
    with pytest.raises(RlsacError, match="policy_every"):
        rlsac_estimate(task, batch, actor, 30, policy_every=0)
