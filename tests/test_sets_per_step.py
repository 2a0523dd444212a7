"""Issue #17's levers that change the algorithm (several minimal sets per step, early termination) and the
same-function rewrites under them (grouped scoring, the minimal 8-point path, set keys)."""

from __future__ import annotations

import math

import pytest
import torch
from test_speed_equivalence import line_batch, two_view_batch

from rlsac.errors import RlsacError
from rlsac.estimation.lo import score_sets
from rlsac.estimation.sampling import gather_points, set_keys, uniform_minimal_sets
from rlsac.maths import geometry
from rlsac.rl.env import EnvConf, SampleConsensusEnv
from rlsac.rl.policy import Actor, PolicyConf
from rlsac.rl.rollout import in_channels, rlsac_estimate
from rlsac.tasks.fundamental import FundamentalTask
from rlsac.tasks.line import LineTask

# four points on y = 0, three off it; threshold 0.1 (as tests/test_env.py)
PTS = torch.tensor([[0, 0], [1, 0], [2, 0], [3, 0], [0, 5], [0, 3], [3, 5]], dtype=torch.float32)


def line_env(episodes: int, k: int, budget: int | None = None, confidence: float = 0.0, first=None):
    task = LineTask()
    batch = {"coords": PTS[None].clone(), "mask": torch.ones(1, 7, dtype=torch.bool)}
    env = SampleConsensusEnv(task, EnvConf(), training=False)
    env.reset(batch, task.features(batch), episodes=episodes, budget=budget, first=first,
              generator=torch.Generator().manual_seed(0), sets_per_step=k, confidence=confidence)
    return env


# ------------------------------------------------------------------------ same-function rewrites
def test_set_keys_known_values_and_order_free():
    assert set_keys(torch.tensor([[3, 1, 2], [2, 3, 1]]), 10).tolist() == [123, 123]
    assert set_keys(torch.tensor([[0, 7]]), 100).tolist() == [7]
    # wraps modulo 2^64 like the sequential key * n + s it replaced (n^m beyond int64)
    idx = torch.tensor([[1999, 1998, 1997, 1996, 1995, 1994, 1993, 1992]])
    key = 0
    for s in sorted(idx[0].tolist()):
        key = (key * 2000 + s) % 2**64
    assert set_keys(idx, 2000).item() == (key - 2**64 if key >= 2**63 else key)


def test_minimal_eight_point_is_the_general_path_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(400, 8, 4, generator=g) * 1000
    pts[:20, 1] = pts[:20, 0]  # a repeated point: degenerate
    pts[20:30, :, 2:] = pts[20:30, :, :2] * 0.5  # an affine map between the views
    fast, valid = geometry.eight_point(pts)
    slow, valid_slow = geometry.eight_point(pts, torch.ones(400, 8))  # weights: the general path
    assert torch.equal(fast, slow) and torch.equal(valid, valid_slow)
    assert not valid[:20].any() and valid[30:].all()


@pytest.mark.parametrize("task", [LineTask(), FundamentalTask(), FundamentalTask(residual="symmetric")],
                         ids=["line", "fundamental", "fundamental-symmetric"])
def test_grouped_scoring_equals_scoring_each_set_against_its_own_copy(task):
    batch = line_batch(3) if task.name == "line" else two_view_batch(3, N=60)
    coords, mask = batch["coords"], batch["mask"]
    B, S = coords.shape[0], 7
    idx = uniform_minimal_sets(mask, task.sample_size, S, torch.Generator().manual_seed(1))  # (B, S, m)
    pts = gather_points(coords, idx)
    hyps, valid, res, count = score_sets(task, pts, coords, mask)
    one = score_sets(task, pts.flatten(0, 1)[:, None], coords.repeat_interleave(S, 0), mask.repeat_interleave(S, 0))
    for grouped, single in zip((hyps, valid, count), (one[0], one[1], one[3]), strict=True):
        assert torch.equal(grouped, single.view(grouped.shape))
    # one (S, 2) x (2, N) product instead of S (N, 2) x (2, 1) ones may round the last bit differently
    torch.testing.assert_close(res, one[2].view(res.shape), rtol=1e-6, atol=1e-6)
    assert hyps.shape[:2] == (B, S) and res.shape == (B, S, coords.shape[1]) and count.shape == (B, S)
    # against the task's own per-row residuals of each hypothesis on its instance's points
    own = task.residuals(hyps.flatten(0, 1), coords.repeat_interleave(S, 0)).view(B, S, -1)
    torch.testing.assert_close(res, own, rtol=1e-6, atol=1e-6)
    assert torch.equal(count, ((own <= task.threshold) & mask[:, None]).sum(-1))


def test_score_sets_rejects_per_row_shapes():
    task = LineTask()
    with pytest.raises(RlsacError, match="score_sets"):
        score_sets(task, PTS[None, :2], PTS[None], torch.ones(1, 7, dtype=torch.bool))


# ------------------------------------------------------------------------ several sets per step
def test_select_many_gives_k_unused_sets_distinct_within_the_instance():
    env = line_env(episodes=2, k=3, first=torch.tensor([[[0, 1], [0, 2], [0, 3]], [[4, 5], [4, 6], [5, 6]]]))
    used = set(env.used[0].tolist()) - {-1}
    assert len(used) == 6
    logits = torch.full((2, 7), -10.0)
    logits[:, 0] = logits[:, 1] = 10.0  # both episodes want the used (0, 1)
    idx = env.select_many(logits)
    assert idx.shape == (2, 3, 2)
    keys = set_keys(idx, 7).flatten().tolist()
    assert len(set(keys)) == 6 and not set(keys) & used  # six new sets, none repeated


def test_select_many_falls_back_to_uniform_sets_when_the_policy_is_peaked():
    env = line_env(episodes=1, k=4)
    logits = torch.full((1, 7), -1e4)
    logits[0, :2] = 1e4  # every draw is (0, 1): one free candidate, three uniform ones needed
    idx = env.select_many(logits, sample=True)
    keys = set(set_keys(idx, 7).flatten().tolist())
    assert len(keys) == 4 and 1 in keys  # (0, 1) = key 0 * 7 + 1, and three other sets


def test_step_scores_all_k_sets_and_acts_with_the_best():
    env = line_env(episodes=1, k=2, first=torch.tensor([[[4, 5], [0, 4]]]))  # both sets give x = 0: 3 inliers
    assert env.hypotheses == 2 and env.count.tolist() == [3]
    reward, _, _ = env.step(torch.tensor([[[5, 6], [0, 1]]]))  # (0, 1) gives y = 0, four inliers: the action
    assert torch.allclose(reward, torch.tensor([4 / 7])) and env.count.tolist() == [4]
    assert env.action[0].tolist() == [1, 1, -1, -1, -1, -1, -1]
    assert env.history[0].tolist() == [1, 1, 0, 0, 1, 1, 0]  # actions: (4, 5) (first of two equal bests), (0, 1)
    assert env.hypotheses == 4 and env.best_count.tolist() == [4]


def test_budget_is_exact_and_sets_never_repeat_with_several_sets_per_step():
    task = LineTask()
    batch = line_batch(2)
    env = SampleConsensusEnv(task, EnvConf(), training=False)
    env.reset(batch, task.features(batch), episodes=2, budget=40, generator=torch.Generator().manual_seed(0),
              sets_per_step=3)  # 2 episodes x 15 steps x 3 sets = 90 slots for 40 hypotheses
    while env.active.any():
        env.step(env.select_many(torch.zeros(4, batch["coords"].shape[1]), sample=True))
    assert env.hypotheses == 80 and env.spent.tolist() == [40, 40]
    for b in range(2):
        keys = env.used[b][env.used[b] >= 0]
        assert keys.numel() == 40 and keys.unique().numel() == 40


def test_rollout_budget_and_episodes_with_sets_per_step():
    task = LineTask()
    torch.manual_seed(0)
    actor = Actor(in_channels(task), PolicyConf(widths=[8, 8], global_width=8, head_width=8)).eval()
    batch = line_batch(3)
    out = rlsac_estimate(task, batch, actor, 100, generator=torch.Generator().manual_seed(0), sets_per_step=4)
    assert int(out["hypotheses"].sum()) == 3 * 100 and out["hyp"].shape == (3, 3)  # ceil(100 / 60) = 2 episodes
    again = rlsac_estimate(task, batch, actor, 100, generator=torch.Generator().manual_seed(0), sets_per_step=4)
    assert torch.equal(out["hyp"], again["hyp"])  # seeded
    bad_options = ({"sets_per_step": 0}, {"confidence": 1.0}, {"confidence": -0.1},
                   {"sets_per_step": 2, "reference": True})
    for bad in bad_options:
        with pytest.raises(RlsacError):
            rlsac_estimate(task, batch, actor, 100, **bad)


# ------------------------------------------------------------------------ early termination
def test_confidence_bound_known_value():
    env = line_env(episodes=1, k=1, confidence=0.99)
    env.best_count = torch.tensor([4])  # w = 4 / 7
    need = math.log(0.01) / math.log(1 - (4 / 7) ** 2)
    env.spent = torch.tensor([math.floor(need)])
    assert not env.confident().item()
    env.spent = torch.tensor([math.ceil(need)])
    assert env.confident().item()
    env.best_count = torch.tensor([1])  # fewer inliers than a minimal set: never confident
    assert not env.confident().item()


def test_confidence_stops_an_easy_instance_early_and_zero_spends_the_budget():
    task = LineTask()
    batch = line_batch(4, rate=0.1)
    stop = rlsac_estimate(task, batch, None, 300, generator=torch.Generator().manual_seed(0), confidence=0.99)
    full = rlsac_estimate(task, batch, None, 300, generator=torch.Generator().manual_seed(0))
    assert int(full["hypotheses"].sum()) == 4 * 300
    # 10% outliers: log(0.01) / log(1 - 0.81) = 2.8 sets suffice; one step of 20 episodes spends 20 of 300
    assert int(stop["hypotheses"].sum()) <= 4 * 40
    assert stop["valid"].all()
