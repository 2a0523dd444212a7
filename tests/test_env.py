"""The sample-consensus environment on hand-made line instances."""

import torch

from rlsac.rl.env import EnvConf, SampleConsensusEnv
from rlsac.tasks.line import LineTask

# four points on y = 0, three off it; threshold 0.1
PTS = torch.tensor([[0, 0], [1, 0], [2, 0], [3, 0], [0, 5], [0, 3], [3, 5]], dtype=torch.float32)


def make_env(training=True, episodes=1, mask=None, first=(0, 4), budget=None):
    task = LineTask()
    batch = {"coords": PTS[None].clone(), "mask": torch.ones(1, 7, dtype=torch.bool) if mask is None else mask}
    env = SampleConsensusEnv(task, EnvConf(), training=training)
    first = torch.tensor([first] * episodes)
    env.reset(batch, task.features(batch), episodes=episodes, first=first, budget=budget,
              generator=torch.Generator().manual_seed(0))
    return env


def test_state_transition_and_reward():
    env = make_env(first=(4, 5))  # x = 0: (0,0), (0,5), (0,3)
    assert env.count.tolist() == [3]
    reward, done, act = env.step(torch.tensor([[0, 1]]))  # y = 0: four inliers
    assert act.tolist() == [True] and not done.item()
    assert torch.allclose(reward, torch.tensor([4 / 7]))
    state = env.state()
    assert state.shape == (1, 7, 2 + 3)
    assert torch.equal(state[0, :, :2], PTS / 10)  # data features
    assert state[0, :, 2].tolist() == [1, 1, -1, -1, -1, -1, -1]  # action
    res = state[0, :, 3]
    assert torch.allclose(res[:4], torch.zeros(4)) and torch.allclose(res[4:], torch.ones(3))  # 3..5 / 0.1 clipped
    assert state[0, :, 4].tolist() == [1, 1, 0, 0, 1, 1, 0]  # history: (4,5) then (0,1)


def test_reward_counts_only_valid_points():
    mask = torch.ones(1, 7, dtype=torch.bool)
    mask[0, 6] = False
    env = make_env(mask=mask, first=(4, 5))
    reward, _, _ = env.step(torch.tensor([[0, 1]]))
    assert torch.allclose(reward, torch.tensor([4 / 6]))


def test_kappa_termination_unchanged_count():
    env = make_env(first=(4, 5))  # count 3
    _, done, _ = env.step(torch.tensor([[0, 1]]))  # 4
    assert not done.item()
    _, done, _ = env.step(torch.tensor([[2, 3]]))  # 4, unchanged once
    assert not done.item()
    _, done, _ = env.step(torch.tensor([[0, 2]]))  # 4, unchanged twice: kappa = 2
    assert done.item()
    assert not env.active.any()


def test_varsigma_termination_no_new_best():
    env = make_env(first=(0, 1))  # count 4 = episode best
    counts = []
    for idx, expect_done in (([4, 5], False), ([1, 6], False), ([0, 6], True)):  # 3, 2, 2: never above 4
        _, done, _ = env.step(torch.tensor([idx]))
        counts.append(int(env.count))
        assert done.item() == expect_done
    assert counts == [3, 2, 2]
    assert int(env.same_count) < env.conf.kappa  # it was varsigma, not kappa


def test_test_time_runs_psi_steps_without_early_stop():
    env = make_env(training=False, first=(0, 1))
    for _ in range(13):  # the same count every step would stop a training episode
        env.step(env.select(torch.zeros(1, 7), sample=True))
        assert env.active.all()
    env.step(env.select(torch.zeros(1, 7), sample=True))
    assert env.t == 15 and not env.active.any()
    assert env.hypotheses == 15


def test_deduplication_within_and_across_episodes():
    env = make_env(training=False, episodes=3, first=(0, 1))  # forced first sets: (0, 1) is used
    logits = torch.full((3, 7), -10.0)
    logits[:, 0] = logits[:, 1] = 10.0  # every episode wants (0, 1) again
    idx = env.select(logits)
    chosen = {tuple(sorted(r)) for r in idx.tolist()}
    assert (0, 1) not in chosen and len(chosen) == 3


def test_budget_limits_hypotheses_and_best_is_refined():
    env = make_env(training=False, episodes=2, budget=20, first=(4, 5))
    while env.active.any():
        env.step(env.select(torch.zeros(2, 7), sample=True))
    assert env.hypotheses == 20
    out = env.result()
    assert out["valid"].all() and int(out["inliers"].sum()) == 4
    assert torch.allclose(out["hyp"][0, :2].abs(), torch.tensor([0.0, 1.0]), atol=1e-5)  # y = 0


def test_random_first_sets_are_distinct_across_episodes():
    task = LineTask()
    batch = {"coords": PTS[None, :3].clone(), "mask": torch.ones(1, 3, dtype=torch.bool)}  # only 3 pairs exist
    env = SampleConsensusEnv(task, EnvConf(), training=False)
    env.reset(batch, task.features(batch), episodes=3, generator=torch.Generator().manual_seed(0))
    assert sorted(env.used[0, :3].tolist()) == [0 * 3 + 1, 0 * 3 + 2, 1 * 3 + 2]


def test_improvement_reward_pays_only_new_bests():
    task = LineTask()
    batch = {"coords": PTS[None].clone(), "mask": torch.ones(1, 7, dtype=torch.bool)}
    env = SampleConsensusEnv(task, EnvConf(reward="improvement"), training=True)
    env.reset(batch, task.features(batch), first=torch.tensor([[4, 5]]))  # 3 inliers
    r1, _, _ = env.step(torch.tensor([[0, 1]]))  # 4: improves by 1/7
    r2, _, _ = env.step(torch.tensor([[1, 6]]))  # 2: no improvement
    assert torch.allclose(r1, torch.tensor([1 / 7])) and r2.item() == 0.0
