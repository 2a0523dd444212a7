"""One SAC-Discrete update on tiny fixed-weight networks, checked against values computed here by hand,
and what the training loop stores in the replay buffer.

Adam's first step moves every parameter by exactly -lr * g / (|g| + eps) (the bias-corrected moments
are g and g^2), so comparing each parameter's change with the gradient of a loss written out here
checks the sign, the masking and the reduction of each loss term, not just that something moved.
"""

from __future__ import annotations

import copy

import pytest
import torch

from rlsac.data.lines import LineDataConf, generate, to_batch
from rlsac.rl.env import EnvConf
from rlsac.rl.policy import PolicyConf
from rlsac.rl.sac import ReplayBuffer, SACAgent, SACConf, masked_policy, train_loop
from rlsac.tasks.line import LineTask

IN = 5  # line task: 2 data channels + 3 memory channels
PCONF = PolicyConf(k=3, widths=[8, 8], global_width=8, head_width=8)
ADAM_EPS = 1e-8


def make_agent(**sac) -> SACAgent:
    torch.manual_seed(0)
    agent = SACAgent(IN, PCONF, SACConf(**sac))
    with torch.no_grad():  # spread the fresh networks' nearly flat outputs: logits and values that differ
        for net in (agent.actor, agent.qf1, agent.qf2):
            net.head[-1].weight.mul_(20.0)
        agent.qf1_target.load_state_dict(agent.qf1.state_dict())
        agent.qf2_target.load_state_dict(agent.qf2.state_dict())
    return agent


def make_batch(agent: SACAgent, b: int = 4, n: int = 10, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    s, s2 = torch.rand(b, n, IN, generator=g), torch.rand(b, n, IN, generator=g)
    mask = torch.ones(b, n, dtype=torch.bool)
    mask[0, -3:] = False  # padded points: never chosen, no probability, no value
    graph = agent.actor.graph(s, mask)
    action = torch.stack([torch.randperm(n - 3, generator=g)[:2] for _ in range(b)])
    reward = torch.rand(b, generator=g)
    done = torch.tensor([1.0, 0.0, 1.0, 0.0])[:b]
    return s, s2, mask, graph, action, reward, done


def snapshot(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def soft_value(agent: SACAgent, s2, mask, graph) -> torch.Tensor:
    """V(s') = sum over valid points of pi_i (min target q_i - alpha log pi_i), written out from the paper."""
    alpha = agent.log_alpha.exp()
    with torch.no_grad():
        logits = agent.actor(s2, mask, graph)
        logp = torch.log_softmax(logits, -1)
        p = logp.exp()
        q = torch.minimum(agent.qf1_target(s2, mask, graph), agent.qf2_target(s2, mask, graph))
        terms = torch.where(mask, p * (q - alpha * logp), torch.zeros_like(q))
    return terms.sum(-1)


def q_of_set(critic, s, mask, graph, action) -> torch.Tensor:
    return critic(s, mask, graph).gather(1, action).mean(-1)


def assert_adam_first_step(before, after, grads, lr):
    for p0, p1, g in zip(before, after, grads, strict=True):
        expect = p0 - lr * g / (g.abs() + ADAM_EPS)
        assert torch.allclose(p1, expect, rtol=1e-4, atol=1e-8), (p1 - p0, -lr * g.sign())


def test_masked_policy_is_zero_on_masked_points():
    logits = torch.tensor([[0.0, 1.0, 2.0, float("-inf")]])
    mask = torch.tensor([[True, True, True, False]])
    p, logp = masked_policy(logits, mask)
    ref = torch.softmax(logits[:, :3], -1)
    assert torch.allclose(p[:, :3], ref) and p[0, 3] == 0 and logp[0, 3] == 0
    assert torch.allclose(logp[:, :3], ref.log())


def test_critic_target_and_step_known_values():
    """Both critics regress Q(s, a) = mean q_i over the set onto r + gamma (1 - done) V(s')."""
    agent = make_agent(critic_lr=1e-3, gamma=0.9)
    s, s2, mask, graph, action, reward, done = make_batch(agent)
    target = reward + 0.9 * (1 - done) * soft_value(agent, s2, mask, graph)
    q1, q2 = copy.deepcopy(agent.qf1), copy.deepcopy(agent.qf2)
    loss = ((q_of_set(q1, s, mask, graph, action) - target) ** 2).mean() + (
        (q_of_set(q2, s, mask, graph, action) - target) ** 2).mean()
    grads = torch.autograd.grad(loss, [*q1.parameters(), *q2.parameters()])
    before = snapshot(q1) + snapshot(q2)
    with torch.no_grad():
        expect_qf1 = ((q_of_set(q1, s, mask, graph, action) - target) ** 2).mean().item()
    out = agent.update(s, s2, mask, graph, action, reward, done)
    assert out["losses/qf1"] == pytest.approx(expect_qf1, rel=1e-5)
    assert_adam_first_step(before, snapshot(agent.qf1) + snapshot(agent.qf2), grads, 1e-3)


@pytest.mark.parametrize("done", [0.0, 1.0])
def test_critic_moves_towards_its_target_with_and_without_done(done):
    """r is chosen so that the two targets lie on opposite sides of the current Q(s, a): Q rises
    towards r + gamma V(s') when the episode goes on and falls towards r when it ended."""
    agent = make_agent(critic_lr=1e-4, gamma=0.9)
    s, s2, mask, graph, action, _, _ = make_batch(agent, b=1)
    with torch.no_grad():
        q_old = q_of_set(agent.qf1, s, mask, graph, action)
    v2 = soft_value(agent, s2, mask, graph)
    assert abs(v2.item()) > 0.05  # the two cases must differ
    reward = q_old - 0.9 * v2 / 2  # done: target = Q - 0.45 V; not done: target = Q + 0.45 V
    target = reward + 0.9 * (1 - done) * v2
    agent.update(s, s2, mask, graph, action, reward, torch.tensor([done]))
    with torch.no_grad():
        q_new = q_of_set(agent.qf1, s, mask, graph, action)
    assert torch.sign(q_new - q_old) == torch.sign(target - q_old)
    assert (q_new - target).abs() < (q_old - target).abs()


def test_actor_step_known_values_and_direction():
    """The actor minimises sum_i pi_i (alpha log pi_i - min(q1, q2)_i) with the critics as they were
    before their own step; with a tiny alpha this raises the policy's expected min-Q."""
    agent = make_agent(actor_lr=1e-3, init_alpha=1e-4)
    s, s2, mask, graph, action, reward, done = make_batch(agent)
    with torch.no_grad():
        qmin = torch.minimum(agent.qf1(s, mask, graph), agent.qf2(s, mask, graph))
    actor = copy.deepcopy(agent.actor)
    logp = torch.log_softmax(torch.where(mask, actor(s, mask, graph), torch.tensor(-1e9)), -1)  # finite grads
    terms = torch.where(mask, logp.exp() * (1e-4 * logp - qmin), torch.zeros_like(qmin))
    grads = torch.autograd.grad(terms.sum(-1).mean(), list(actor.parameters()))
    before = snapshot(actor)
    with torch.no_grad():
        p_old = torch.softmax(actor(s, mask, graph), -1)
    out = agent.update(s, s2, mask, graph, action, reward, done)
    assert out["losses/actor"] == pytest.approx(terms.sum(-1).mean().item(), rel=1e-5)
    assert_adam_first_step(before, snapshot(agent.actor), grads, 1e-3)
    with torch.no_grad():
        p_new = torch.softmax(agent.actor(s, mask, graph), -1)
    q = qmin.masked_fill(~mask, 0.0)
    assert ((p_new * q).sum(-1).mean() - (p_old * q).sum(-1).mean()).item() > 1e-4


def test_actor_entropy_term_spreads_the_policy():
    """With a large alpha the entropy term dominates: one step makes the policy more uniform."""
    agent = make_agent(actor_lr=1e-2, init_alpha=100.0)
    s, s2, mask, graph, action, reward, done = make_batch(agent)

    def entropy():
        with torch.no_grad():
            p, logp = masked_policy(agent.actor(s, mask, graph), mask)
        return -(p * logp).sum(-1).mean().item()

    h0 = entropy()
    agent.update(s, s2, mask, graph, action, reward, done)
    assert entropy() > h0 + 1e-4


@pytest.mark.parametrize("scale,direction", [(0.0, -1), (2.0, 1)])
def test_temperature_moves_towards_the_entropy_target(scale, direction):
    """Target entropy 0 (below any entropy) lowers alpha; 2 log N (above log N, the maximum) raises it,
    by exactly alpha_lr in log space on Adam's first step."""
    agent = make_agent(alpha_lr=1e-2, target_entropy_scale=scale, init_alpha=0.5)
    batch = make_batch(agent)
    s, mask, graph = batch[0], batch[2], batch[3]
    with torch.no_grad():
        p, logp = masked_policy(agent.actor(s, mask, graph), mask)
    entropy = -(p * logp).sum(-1)
    gap = (entropy - scale * mask.sum(-1).float().log()).mean()
    a0 = agent.log_alpha.item()
    out = agent.update(*batch)
    assert out["losses/alpha"] == pytest.approx(0.5 * gap.item(), rel=1e-4)
    assert agent.log_alpha.item() - a0 == pytest.approx(direction * 1e-2, rel=1e-4)
    assert out["charts/alpha"] == pytest.approx(0.5)  # the update used alpha from before its own step


def test_polyak_step_of_the_target_critics():
    agent = make_agent(tau=0.25)
    for tp, p in zip(agent.qf1_target.parameters(), agent.qf1.parameters(), strict=True):
        assert torch.equal(tp, p) and not tp.requires_grad  # starts as a frozen copy
    with torch.no_grad():  # make targets and critics differ so the average is visible
        for tp in [*agent.qf1_target.parameters(), *agent.qf2_target.parameters()]:
            tp.add_(1.0)
    old = snapshot(agent.qf1_target) + snapshot(agent.qf2_target)
    agent.update(*make_batch(agent))
    new_online = snapshot(agent.qf1) + snapshot(agent.qf2)
    new_target = snapshot(agent.qf1_target) + snapshot(agent.qf2_target)
    for o, w, t in zip(old, new_online, new_target, strict=True):
        assert torch.allclose(t, 0.75 * o + 0.25 * w, atol=1e-6)


def test_replay_buffer_stores_and_wraps():
    buf = ReplayBuffer(size=5, n=4, m=2, device=torch.device("cpu"))

    def rows(k, base):
        inst = torch.arange(k) + base
        mem = (inst.float()[:, None, None] + torch.arange(12.0).view(1, 4, 3)) / 8
        return (inst, mem, -mem, torch.stack([inst % 4, (inst + 1) % 4], -1), inst.float() / 10,
                (inst % 2).bool())

    buf.add(*rows(3, 0))
    assert len(buf) == 3 and not buf.full
    buf.add(*rows(4, 3))  # 7 rows into 5 slots: 5 and 6 overwrite 0 and 1
    assert len(buf) == 5 and buf.full and buf.ptr == 2
    assert buf.inst.tolist() == [5, 6, 2, 3, 4]
    for j, i in enumerate(buf.inst.tolist()):
        ref = rows(1, i)
        assert torch.equal(buf.mem[j].float(), ref[1][0]) and torch.equal(buf.mem2[j].float(), ref[2][0])
        assert buf.action[j].tolist() == ref[3][0].tolist() and buf.reward[j].item() == pytest.approx(i / 10)
        assert buf.done[j].item() == i % 2
    inst, mem, mem2, action, reward, done, extra = buf.sample(64, torch.Generator().manual_seed(0))
    assert extra is None  # fixed pairs store no episode record
    torch.manual_seed(123)  # draws come from the given generator only
    assert torch.equal(buf.sample(64, torch.Generator().manual_seed(0))[0], inst)
    assert not torch.equal(buf.sample(64, torch.Generator().manual_seed(1))[0], inst)
    assert set(inst.tolist()) == {2, 3, 4, 5, 6}  # every stored row is drawn, nothing else
    for i, me, me2, a, r, d in zip(inst.tolist(), mem, mem2, action, reward, done, strict=True):
        ref = rows(1, i)
        assert torch.equal(me, ref[1][0]) and torch.equal(me2, ref[2][0]) and a.tolist() == ref[3][0].tolist()
        assert r.item() == pytest.approx(i / 10) and d.item() == i % 2


def line_data(n_inst=8, n_points=20, seed=3):
    task = LineTask()
    batch = to_batch(generate(LineDataConf(outlier_rate=0.5, n_instances=n_inst, n_points=n_points, seed=seed)))
    batch["features"] = task.features(batch)
    return task, batch


def collect(env_conf: EnvConf, total_steps: int, **sac):
    """Roll the training loop without any update (learning_starts out of reach) -> its buffer."""
    task, data = line_data()
    agent = make_agent(total_steps=total_steps, num_envs=4, learning_starts=10**6, buffer_size=1000, **sac)
    logs = []
    buf = train_loop(agent, task, data, env_conf, 0, torch.Generator().manual_seed(0),
                     log=lambda m, step: logs.append(m))
    return task, data, buf, logs


def test_training_loop_stores_the_transition_the_env_made():
    """Each stored transition: s = memory before the step, s' = after it (action channel +1 exactly on
    the stored set, history one higher there, residuals to the line through it), reward = that line's
    inlier ratio."""
    task, data, buf, _ = collect(EnvConf(), 12)
    n = len(buf)
    assert n >= 12 * 4 * 0.5  # episodes stop early (kappa, varsigma) but most steps act
    onehot = torch.zeros(n, 20, dtype=torch.bool).scatter_(1, buf.action[:n], True)
    mem, mem2 = buf.mem[:n].float(), buf.mem2[:n].float()
    assert torch.equal(mem2[..., 0], onehot.float() * 2 - 1)
    assert torch.equal(mem2[..., 2], mem[..., 2] + onehot.float())
    assert not torch.equal(mem[..., 0], mem2[..., 0])
    coords = data["coords"][buf.inst[:n]]
    hyp, valid = task.solve(torch.gather(coords, 1, buf.action[:n, :, None].expand(-1, -1, 2)))
    assert valid.all()
    res = task.residuals(hyp, coords)
    assert torch.allclose(mem2[..., 1], (res / 0.1).clamp(max=5.0) / 5.0, atol=2e-3)  # stored in float16
    ratio = (res <= 0.1).float().mean(-1)
    assert torch.allclose(buf.reward[:n], ratio)
    assert ((mem[..., 2].sum(-1) / 2) >= 1).all()  # s already holds the episode's random first set


@pytest.mark.parametrize("bootstrap", [False, True])
def test_psi_cut_is_terminal_unless_bootstrap_truncation(bootstrap):
    """psi = 3 and kappa/varsigma out of reach: every episode is 2 transitions (the first set is random)
    ending at the psi cut: done unless sac.bootstrap_truncation."""
    _, _, buf, logs = collect(EnvConf(steps_per_episode=3, kappa=100, varsigma=100), 6,
                              bootstrap_truncation=bootstrap)
    assert len(buf) == 24 and [m["charts/episode_length"] for m in logs] == [2, 2, 2]
    expect = torch.zeros(24) if bootstrap else torch.tensor([0.0, 0, 0, 0, 1, 1, 1, 1] * 3)
    assert torch.equal(buf.done[:24], expect)


def test_kappa_varsigma_stops_stay_terminal_with_bootstrap_truncation():
    conf = EnvConf(steps_per_episode=50, kappa=1, varsigma=1)
    runs = [collect(conf, 8, bootstrap_truncation=b)[2] for b in (False, True)]
    n = len(runs[0])
    assert n == len(runs[1]) and runs[0].done[:n].sum() >= 4
    assert torch.equal(runs[0].done[:n], runs[1].done[:n])


def test_replay_buffer_state_dict_round_trip():
    src = ReplayBuffer(size=4, n=3, m=2, device=torch.device("cpu"))
    mem = torch.arange(18.0).view(2, 3, 3) / 4
    src.add(torch.tensor([7, 8]), mem, -mem, torch.tensor([[0, 1], [1, 2]]), torch.tensor([0.5, 0.25]),
            torch.tensor([False, True]))
    st = src.state_dict()
    assert st["inst"].tolist() == [7, 8] and st["ptr"] == 2 and st["full"] is False  # the filled part only
    # ... also on disk: a saved slice would carry the whole 4-row storage (issue #28: 124 MB for 803 transitions)
    for k in ("inst", "mem", "mem2", "action", "reward", "done"):
        assert st[k].untyped_storage().nbytes() == st[k].numel() * st[k].element_size(), k
    dst = ReplayBuffer(size=4, n=3, m=2, device=torch.device("cpu"))
    dst.load_state_dict(st)
    assert len(dst) == 2 and dst.ptr == 2 and not dst.full
    for k in ("inst", "mem", "mem2", "action", "reward", "done"):
        assert torch.equal(getattr(dst, k), getattr(src, k)), k
    src.add(torch.tensor([1, 2, 3]), mem[[0, 1, 0]], mem[[0, 1, 0]], torch.tensor([[0, 2]] * 3), torch.zeros(3),
            torch.zeros(3, dtype=torch.bool))  # wraps: full
    dst = ReplayBuffer(size=4, n=3, m=2, device=torch.device("cpu"))
    dst.load_state_dict(src.state_dict())
    assert len(dst) == 4 and dst.full and dst.ptr == 1 and torch.equal(dst.inst, src.inst)
    for size, n, m in ((5, 3, 2), (4, 2, 2), (4, 3, 3)):
        with pytest.raises(ValueError, match="does not fit"):
            ReplayBuffer(size=size, n=n, m=m, device=torch.device("cpu")).load_state_dict(src.state_dict())


def test_warm_start_actor_step_is_cross_entropy_on_true_inliers():
    """With labels the actor step minimises the mean over rows with inliers of -mean log pi over them."""
    agent = make_agent(actor_lr=1e-3)
    s, s2, mask, graph, action, reward, done = make_batch(agent)
    labels = torch.zeros(4, 10, dtype=torch.bool)
    labels[0, [0, 2]] = labels[1, [1, 4, 5]] = labels[3, 9] = True  # row 2 has none: left out
    actor = copy.deepcopy(agent.actor)
    logp = torch.log_softmax(torch.where(mask, actor(s, mask, graph), torch.tensor(-1e9)), -1)
    rows = [logp[0, [0, 2]].mean(), logp[1, [1, 4, 5]].mean(), logp[3, [9]].mean()]
    loss = -torch.stack(rows).mean()
    grads = torch.autograd.grad(loss, list(actor.parameters()))
    before = snapshot(actor)
    out = agent.update(s, s2, mask, graph, action, reward, done, labels)
    assert out["losses/actor"] == pytest.approx(loss.item(), rel=1e-5)
    assert_adam_first_step(before, snapshot(agent.actor), grads, 1e-3)


def test_training_loop_warm_starts_the_first_updates_then_counts_on():
    task, data = line_data()
    data["labels"] = task.true_inliers(data)
    agent = make_agent(total_steps=6, num_envs=4, learning_starts=8, batch_size=8, updates_per_step=2,
                       warm_start_updates=3)
    supervised, real = [], agent.update

    def update(*args):
        supervised.append(args[7] is not None)
        return real(*args)

    agent.update = update
    train_loop(agent, task, data, EnvConf(), 0, torch.Generator().manual_seed(0), log=lambda m, step: None)
    n = len(supervised)
    assert n >= 6 and supervised == [True] * 3 + [False] * (n - 3) and int(agent.n_updates) == n


def test_training_loop_callbacks_and_masked_graph():
    """From a resumed step: validation every val_every steps, a checkpoint at the first episode end at or
    after every ckpt_every steps (episodes of 2 steps here, ending at steps 3, 5, 7); the actor's graph
    never links a valid point to a padded one."""
    task, data = line_data()
    data["mask"] = data["mask"].clone()
    data["mask"][::2, -5:] = False  # padded points on half the instances
    agent = make_agent(total_steps=8, num_envs=4, learning_starts=10**6)
    seen, calls = [], []
    hook = agent.actor.register_forward_hook(lambda m, args, out: seen.append((args[1], args[2])))
    train_loop(agent, task, data, EnvConf(steps_per_episode=3, kappa=100, varsigma=100), 1,
               torch.Generator().manual_seed(0), log=lambda m, step: None,
               validate=lambda step: calls.append(("val", step)) or {}, val_every=2,
               checkpoint=lambda step, buf: calls.append(("ckpt", step)), ckpt_every=3)
    hook.remove()
    assert calls == [("val", 2), ("ckpt", 3), ("val", 4), ("val", 6), ("ckpt", 7), ("val", 8)]
    assert len(seen) == 7
    for mask, graph in seen:
        linked = torch.gather(mask, 1, graph.flatten(1)).view(graph.shape)
        assert linked[mask].all() and not mask.all()


def test_update_reports_every_loss_and_chart():
    agent = make_agent(batch_size=4)
    s, s2, mask, graph, action, reward, done = make_batch(agent)
    m = agent.update(s, s2, mask, graph, action, reward, done)
    assert set(m) == {"losses/qf1", "losses/qf2", "losses/qf1_values", "losses/actor", "losses/alpha",
                      "charts/alpha", "charts/entropy"}
    assert m["losses/qf1"] != m["losses/qf2"]  # two critics, two losses


@pytest.mark.parametrize("sampling, sample", [("prob", True), ("max", False)])
def test_training_loop_samples_as_train_sampling_says(monkeypatch, sampling, sample):
    from rlsac.rl.env import SampleConsensusEnv

    seen = []
    real = SampleConsensusEnv.select

    def spy(self, logits, sample=False, random=False):
        if not random:  # reset draws each episode's first set at random
            seen.append(sample)
        return real(self, logits, sample=sample, random=random)

    monkeypatch.setattr(SampleConsensusEnv, "select", spy)
    collect(EnvConf(), 4, train_sampling=sampling)
    assert seen and all(x is sample for x in seen)


def test_training_loop_logs_update_metrics_every_50_steps():
    """Steps 50 and 100 log the update's metrics with throughput: updates / transitions per second, whose
    ratio is the number of updates over the transitions stored, whatever the elapsed time."""
    task, data = line_data()
    agent = make_agent(total_steps=101, num_envs=4, learning_starts=8, batch_size=8, buffer_size=1000)
    buf = ReplayBuffer(1000, 20, task.sample_size, "cpu")
    logged = []

    def log(m, step):
        if "charts/updates_per_s" in m:
            logged.append((step, dict(m), int(agent.n_updates), len(buf)))

    train_loop(agent, task, data, EnvConf(), 0, torch.Generator().manual_seed(0), log=log, buffer=buf)
    assert [s for s, *_ in logged] == [50, 100]
    for _, m, n_upd, n_trans in logged:
        assert {"losses/qf1", "losses/qf2", "charts/alpha", "charts/transitions_per_s"} <= set(m)
        assert m["charts/updates_per_s"] / m["charts/transitions_per_s"] == pytest.approx(n_upd / n_trans)
