"""The EdgeConv policy and the test-time rollout: EdgeConv against its textbook formula, the policy's
dependence on neighbours and on each memory channel, and what the real rollout feeds the actor and
does with its logits (max = top-m logits, the memory channels of the state, the checkpoint's env)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from rlsac.config import build, to_dict
from rlsac.data.lines import LineDataConf, generate, to_batch, write
from rlsac.errors import RlsacError
from rlsac.estimation.sampling import set_keys
from rlsac.evaluation.evaluate import evaluate
from rlsac.evaluation.train import TrainConf
from rlsac.rl.checkpoint import env_conf, load_actor
from rlsac.rl.policy import Actor, Critic, EdgeConv, PolicyConf, knn
from rlsac.rl.rollout import rlsac_estimate
from rlsac.tasks.line import LineTask

PCONF = PolicyConf(k=4, widths=[8, 8], global_width=8, head_width=8)


def make_actor(seed: int = 0, cls=Actor) -> Actor:
    torch.manual_seed(seed)
    net = cls(5, PCONF)
    with torch.no_grad():
        net.head[-1].weight.mul_(20.0)  # a fresh network's logits are nearly flat: spread them
    return net.eval()


def states(r=3, n=12, seed=1):
    g = torch.Generator().manual_seed(seed)
    s = torch.rand(r, n, 5, generator=g)
    s[..., 2] = torch.where(torch.rand(r, n, generator=g) < 0.2, 1.0, -1.0)  # action channel +-1
    return s


def test_edgeconv_is_max_over_neighbours_of_the_edge_function():
    """h_i = max_{j in N(i)} leaky_relu(W1 x_i + b + W2 (x_j - x_i)), computed edge by edge."""
    torch.manual_seed(0)
    conv = EdgeConv(5, 7)
    x = states(r=2, n=9)
    idx = knn(x[..., :2], 4, None)
    xi = x[:, :, None, :].expand(-1, -1, 4, -1)
    xj = torch.stack([x[b][idx[b]] for b in range(2)])  # (R, N, k, C)
    edge = conv.centre(xi) + xj @ conv.neigh.weight.T - xi @ conv.neigh.weight.T
    ref = torch.nn.functional.leaky_relu(edge, 0.2).amax(dim=2)
    assert torch.allclose(conv(x, idx), ref, atol=1e-6)


def test_edgeconv_output_changes_only_with_its_neighbours():
    torch.manual_seed(0)
    conv = EdgeConv(5, 7)
    x = states(r=1, n=9)
    idx = knn(x[..., :2], 3, None)
    i = 0
    neigh = [j for j in idx[0, i].tolist() if j != i]
    far = [j for j in range(9) if j not in idx[0, i].tolist()]
    base = conv(x, idx)[0, i]
    moved = x.clone()
    moved[0, neigh, 2:] += 3.0  # a neighbour's features (not its coordinates: the graph stays)
    assert not torch.allclose(conv(moved, idx)[0, i], base)
    moved = x.clone()
    moved[0, far, 2:] += 3.0
    assert torch.allclose(conv(moved, idx)[0, i], base)


def naive_pointnet(net, state, mask, graph):
    """The network written out edge by edge: EdgeConv layers (the given graph first, then, for a dynamic
    network, the kNN graph of each layer's input features), global max pool over valid points, head."""
    x, feats = state, []
    for i, conv in enumerate(net.convs):
        if i > 0 and net.conf.dynamic:
            graph = knn(x, net.conf.k, mask)
        xi = x[:, :, None, :].expand(-1, -1, graph.shape[-1], -1)
        xj = torch.stack([x[r][graph[r]] for r in range(x.shape[0])])
        edge = conv.centre(xi) + (xj - xi) @ conv.neigh.weight.T
        x = torch.nn.functional.leaky_relu(edge, 0.2).amax(dim=2)
        feats.append(x)
    local = torch.cat(feats, -1)
    g = net.glob(local).masked_fill(~mask[..., None], float("-inf")).amax(1, keepdim=True)
    out = net.head(torch.cat([local, g.expand(-1, local.shape[1], -1)], -1)).squeeze(-1)
    return out.masked_fill(~mask, float("-inf")) if isinstance(net, Actor) else out


def random_graph(mask, k, seed=0):
    """Each point's neighbours: itself, then k - 1 random valid points (not its kNN)."""
    R, N = mask.shape
    keys = torch.rand(R, N, N, generator=torch.Generator().manual_seed(seed)).masked_fill(~mask[:, None, :], -1.0)
    keys = keys + 2 * torch.eye(N)
    return keys.topk(k, dim=-1).indices


def same(out, ref, valid):
    return torch.allclose(out[valid], ref[valid], atol=1e-5) and torch.equal(out.isinf(), ref.isinf())


@pytest.mark.parametrize("dynamic", [False, True], ids=["static", "dynamic"])
@pytest.mark.parametrize("cls", [Actor, Critic])
def test_every_forward_path_is_the_edge_by_edge_network(cls, dynamic):
    """forward (training), reference_forward, and precompute + forward_memory (test-time rollouts)."""
    torch.manual_seed(0)
    net = cls(5, dataclasses.replace(PCONF, dynamic=dynamic))
    s = states(r=4)
    mask = torch.ones(4, 12, dtype=torch.bool)
    mask[1, 9:] = False
    graph = random_graph(mask, PCONF.k)  # a given graph is used as given
    ref = naive_pointnet(net, s, mask, graph)
    valid = mask if cls is Actor else torch.ones_like(mask)
    for out in (net(s, mask, graph), net.reference_forward(s, mask, graph)):
        assert same(out, ref, valid)
    ref = naive_pointnet(net, s, mask, net.graph(s, mask))  # no graph: the coordinates' kNN graph
    for out in (net(s, mask), net.reference_forward(s, mask)):
        assert same(out, ref, valid)
    ref = naive_pointnet(net, s, torch.ones_like(mask), net.graph(s))  # no mask: every point valid
    for out in (net(s), net.reference_forward(s)):
        assert same(out, ref, torch.ones_like(mask))
    # rollout layout: 2 instances x 2 episodes sharing data channels and graph, memory per row
    s[1, ..., :2], s[3, ..., :2] = s[0, ..., :2], s[2, ..., :2]
    mask[1] = mask[0]
    ref = naive_pointnet(net, s, mask, net.graph(s, mask))
    for chunk in (8192, 24, 12):  # one chunk; one instance per chunk; one episode per chunk
        prep = net.precompute(s[::2, ..., :2], mask[::2], episodes=2, chunk_points=chunk)
        assert same(net.forward_memory(prep, s[..., 2:]), ref, mask if cls is Actor else torch.ones_like(mask))
    prep = net.precompute(s[::2, ..., :2], None, episodes=2)
    ref = naive_pointnet(net, s, torch.ones_like(mask), net.graph(s))
    assert same(net.forward_memory(prep, s[..., 2:]), ref, torch.ones_like(mask))


def test_knn_graph_uses_coordinates_and_skips_masked_points():
    x = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.1, 0.0], [5.0, 0.0]]])
    mask = torch.tensor([[True, True, False, True]])
    assert knn(x, 2, mask)[0].tolist()[:2] == [[0, 1], [1, 0]]  # point 2 is nearest to 0 but masked
    actor = make_actor()
    s = states()
    moved = s.clone()
    moved[..., 2:] = torch.rand_like(moved[..., 2:])  # memory channels do not move the first graph
    assert torch.equal(actor.graph(s), actor.graph(moved))
    four = Actor(5, dataclasses.replace(PCONF, graph_dims=4))
    assert torch.equal(four.graph(s), knn(s[..., :4], 4, None))


@pytest.mark.parametrize("cls", [Actor, Critic])
def test_output_depends_on_the_neighbourhood_graph(cls):
    net = make_actor(cls=cls)
    s = states()
    self_only = torch.arange(12).view(1, 12, 1).expand(3, 12, PCONF.k)  # every edge a self-loop
    assert (net(s, None, net.graph(s)) - net(s, None, self_only)).abs().max() > 1e-2


@pytest.mark.parametrize("cls", [Actor, Critic])
@pytest.mark.parametrize("channel", [2, 3, 4], ids=["action", "residual", "history"])
def test_output_depends_on_each_memory_channel(cls, channel):
    net = make_actor(cls=cls)
    s = states()
    graph = net.graph(s)
    moved = s.clone()
    moved[0, :6, channel] = -moved[0, :6, channel] + 0.5  # row 0 only: rows are independent
    diff = (net(s, None, graph) - net(moved, None, graph)).abs()
    assert diff[0].max() > 1e-2 and diff[1:].max() == 0


def test_actor_masks_padded_points():
    actor = make_actor()
    s = states()
    mask = torch.ones(3, 12, dtype=torch.bool)
    mask[1, 8:] = False
    logits = actor(s, mask)
    assert torch.isinf(logits[1, 8:]).all() and torch.isfinite(logits[mask]).all()
    moved = s.clone()
    moved[1, 8:] += 5.0  # padded points influence nothing
    assert torch.allclose(actor(moved, mask)[1, :8], logits[1, :8], atol=1e-6)


# ---------------------------------------------------------------- the real test-time rollout
def line_batch(n_inst=10, n_points=30, seed=5):
    return to_batch(generate(LineDataConf(outlier_rate=0.5, n_instances=n_inst, n_points=n_points, seed=seed)))


class Spy:
    """Records the full state (data + memory channels) and the logits of every actor evaluation of a
    rollout, on whichever path it takes (forward, reference_forward, precompute + forward_memory);
    the real network computes every value."""

    def __init__(self, monkeypatch):
        self.calls, self.feats = [], None
        fwd, ref, pre, mem = Actor.forward, Actor.reference_forward, Actor.precompute, Actor.forward_memory

        def forward(net, state, mask=None, graph=None):
            out = fwd(net, state, mask, graph)
            self.calls.append((state.clone(), out.clone()))
            return out

        def reference_forward(net, state, mask=None, graph=None):
            out = ref(net, state, mask, graph)
            self.calls.append((state.clone(), out.clone()))
            return out

        def precompute(net, features, mask=None, episodes=1, *args, **kwargs):
            self.feats = features.repeat_interleave(int(episodes), 0)
            return pre(net, features, mask, episodes, *args, **kwargs)

        def forward_memory(net, prep, memory):
            out = mem(net, prep, memory)
            self.calls.append((torch.cat([self.feats, memory], -1), out.clone()))
            return out

        for name, f in (("forward", forward), ("reference_forward", reference_forward),
                        ("precompute", precompute), ("forward_memory", forward_memory)):
            monkeypatch.setattr(Actor, name, f)


def run(monkeypatch, sampling=None, seed=0, iterations=15):
    actor, task, batch = make_actor(), LineTask(), line_batch()
    spy = Spy(monkeypatch)
    kw = {} if sampling is None else {"sampling": sampling}
    out = rlsac_estimate(task, batch, actor, iterations, generator=torch.Generator().manual_seed(seed),
                         record=True, **kw)
    return task, batch, spy.calls, out


def chosen_vs_top(calls, steps):
    """Per actor call t and row: was the top-m of its logits unused, and was it the next set chosen?"""
    unused_top, took_top = [], []
    used = [set_keys(steps[0]["minimal_set"], 30)]
    for t, (_, logits) in enumerate(calls):
        top = set_keys(logits.topk(2, dim=-1).indices, 30)
        nxt = set_keys(steps[t + 1]["minimal_set"], 30)
        free = ~(torch.stack(used, -1) == top[:, None]).any(-1)
        unused_top.append(free)
        took_top.append(nxt == top)
        used.append(nxt)
    return torch.stack(unused_top), torch.stack(took_top)


def test_max_sampling_takes_the_top_m_logits(monkeypatch):
    """Default test-time sampling (the paper's max): whenever the top-2 logits form an unused set, that
    set is the next hypothesis; used sets fall back to other candidates."""
    _, _, calls, out = run(monkeypatch)
    assert len(calls) == 14 and int(out["hypotheses"].sum()) == 150
    free, took = chosen_vs_top(calls, out["steps"])
    assert free.sum() >= 10 and took[free].all()
    assert not took[~free].any()  # a used set is never repeated (de-duplication)


def test_prob_sampling_draws_from_the_softmax(monkeypatch):
    _, _, calls, out = run(monkeypatch, "prob")
    free, took = chosen_vs_top(calls, out["steps"])
    assert took[free].float().mean() < 0.5  # the top-2 logits are one plausible set among many
    assert len({tuple(sorted(r)) for s in out["steps"][1:] for r in s["minimal_set"].tolist()}) > 100


def test_rollout_feeds_the_actor_the_current_memory_channels(monkeypatch):
    """At call t the state holds the set and hypothesis of step t (action +1 on its 2 points, residuals
    to its line clipped at 5 thresholds), the history of all t + 1 sets, and the data features."""
    task, batch, calls, out = run(monkeypatch)
    assert len(calls) == 14
    coords = batch["coords"]
    for t, (state, _) in enumerate(calls):
        step = out["steps"][t]
        onehot = torch.zeros(10, 30, dtype=torch.bool).scatter_(1, step["minimal_set"], True)
        assert torch.equal(state[..., :2], coords / 10)
        assert torch.equal(state[..., 2], onehot.float() * 2 - 1)
        res = (task.residuals(step["hyp"], coords) / 0.1).clamp(max=5.0) / 5.0
        assert torch.allclose(state[..., 3], res, atol=1e-5)
        assert torch.equal(state[..., 4].sum(-1), torch.full((10,), 2.0 * (t + 1)))
        # the recorded step: its hypothesis' inliers and their count
        assert torch.equal(step["inliers"], task.residuals(step["hyp"], coords) <= 0.1)
        assert torch.equal(step["count"], step["inliers"].sum(-1))


def test_uniform_control_runs_the_same_environment_without_the_actor(monkeypatch):
    task, batch = LineTask(), line_batch()
    spy = Spy(monkeypatch)
    g = torch.Generator().manual_seed(0)
    uni = rlsac_estimate(task, batch, None, 40, generator=g, record=True)
    assert spy.calls == [] and int(uni["hypotheses"].sum()) == 10 * 40 and uni["valid"].all()
    assert (uni["inliers"].sum(-1) >= 2).all()


# ---------------------------------------------------------------- the checkpoint's environment
def save_checkpoint(path, actor, env: dict):
    conf = to_dict(build(TrainConf, {"task": "line", "env": env, "policy": dataclasses.asdict(PCONF)}))
    torch.save({"actor": actor.state_dict(), "conf": conf, "in_channels": 5, "step": 0, "val": {}}, path)


def residual_clip_seen(state: torch.Tensor) -> float:
    """From a state alone: the clip c with residual channel = min(r / eps, c) / c for the line through
    the two +1 points (r from the coordinates channels); -> c fitted over unsaturated points."""
    task = LineTask()
    coords = state[..., :2] * 10
    pair = (state[..., 2] > 0).float().topk(2, dim=-1).indices
    hyp, _ = task.solve(torch.gather(coords, 1, pair[..., None].expand(-1, -1, 2)))
    r = task.residuals(hyp, coords) / 0.1
    ch = state[..., 3]
    keep = (ch < 0.999) & (r > 0.05)
    assert (ch[r > 6.0] == 1.0).all()  # far points saturate for either clip
    return float((r[keep] / ch[keep]).median())


def test_checkpoint_env_settings_drive_the_real_test_time_rollout(workdir, monkeypatch):
    """Two checkpoints with the same actor and different env sections, evaluated by `evaluate` through the
    real rollout: psi sets the actor calls per episode, residual_clip the residual channel it sees."""
    conf = LineDataConf(outlier_rate=0.5, n_instances=6, n_points=30, seed=9)
    write(workdir / "d.h5", generate(conf), conf)
    actor = make_actor()
    save_checkpoint(workdir / "a.pt", actor, {"steps_per_episode": 5, "residual_clip": 2.0, "candidates": 4})
    save_checkpoint(workdir / "b.pt", actor, {})
    seen = {}
    for name in ("a", "b"):
        loaded, ck = load_actor(workdir / f"{name}.pt")
        assert env_conf(ck).steps_per_episode == (5 if name == "a" else 15)
        with monkeypatch.context() as mp:
            spy = Spy(mp)
            s = evaluate({"task": "line", "method": "rlsac", "data": "d.h5", "checkpoint": f"{name}.pt",
                          "iterations": 20, "device": "cpu", "out_dir": f"ev_{name}"}, track=False)
        seen[name] = (s["steps_per_episode"], len(spy.calls), [residual_clip_seen(c) for c, _ in spy.calls])
    assert seen["a"][:2] == (5, 4) and seen["b"][:2] == (15, 14)
    assert np.allclose(seen["a"][2], 2.0, rtol=1e-3) and np.allclose(seen["b"][2], 5.0, rtol=1e-3)


def test_checkpoint_env_reads_the_env_section_and_overrides_psi():
    conf = {"env": {"steps_per_episode": 5, "residual_clip": 2.0, "kappa": 4}}
    env = env_conf(conf)
    assert (env.steps_per_episode, env.residual_clip, env.kappa, env.candidates) == (5, 2.0, 4, 16)
    env = env_conf(conf, steps_per_episode=7.0)
    assert env.steps_per_episode == 7 and isinstance(env.steps_per_episode, int) and env.residual_clip == 2.0
    assert conf["env"]["steps_per_episode"] == 5  # the checkpoint's conf is not modified
    assert env_conf({}) == env_conf(None) == build(type(env), {})
    with pytest.raises(RlsacError, match=r"unknown config key.*\['bogus'\] in checkpoint env"):
        env_conf({"env": {"bogus": 1}})


def test_load_actor_errors_are_one_line(tmp_path):
    with pytest.raises(RlsacError, match=r"nope\.pt: no such checkpoint"):
        load_actor(tmp_path / "nope.pt")
    torch.save({"actor": {}, "conf": {"policy": {}}}, tmp_path / "bad.pt")  # no in_channels
    with pytest.raises(RlsacError, match=r"bad\.pt: not an rlsac checkpoint \(KeyError: 'in_channels'\)$"):
        load_actor(tmp_path / "bad.pt")
    actor = make_actor()
    save_checkpoint(tmp_path / "w.pt", actor, {})
    state = torch.load(tmp_path / "w.pt", weights_only=False)
    state["actor"]["head.0.weight"] = torch.zeros(3, 3)
    torch.save(state, tmp_path / "w.pt")
    with pytest.raises(RlsacError) as e:
        load_actor(tmp_path / "w.pt")
    msg = str(e.value)
    assert msg.startswith(f"{tmp_path / 'w.pt'}: not an rlsac checkpoint (RuntimeError: ")
    assert len(msg) == len(f"{tmp_path / 'w.pt'}: not an rlsac checkpoint (RuntimeError: )") + 80  # cut at 80


@pytest.mark.parametrize("sampling", ["max", "prob"])
def test_rollout_draws_only_from_its_generator(sampling):
    """Same generator seed, same minimal sets whatever the global RNG; another seed, other sets (with 2
    episodes per instance the max policy's duplicates fall back to random candidates)."""
    actor, task, batch = make_actor(), LineTask(), line_batch()
    sets = []
    for seed, global_seed in ((0, 1), (0, 2), (1, 1)):
        torch.manual_seed(global_seed)
        out = rlsac_estimate(task, batch, actor, 30, sampling=sampling, generator=torch.Generator().manual_seed(seed),
                             record=True)
        sets.append(torch.stack([s["minimal_set"].sort(-1).values for s in out["steps"]]))
    assert torch.equal(sets[0], sets[1]) and not torch.equal(sets[0], sets[2])


def test_rollout_forward_one_neighbour_at_a_time_is_the_same_network(monkeypatch):
    """The large-chunk path of the rollout's neighbour max (k gathers into scratch buffers, taken when a gather
    exceeds GATHER_AT_ONCE floats) computes what the one-gather path does."""
    from rlsac.rl import policy

    torch.manual_seed(0)
    net = Actor(5, PCONF)
    s = states(r=4)
    mask = torch.ones(4, 12, dtype=torch.bool)
    mask[1, 9:] = False
    s[1, ..., :2], s[3, ..., :2] = s[0, ..., :2], s[2, ..., :2]
    mask[1] = mask[0]
    ref = naive_pointnet(net, s, mask, net.graph(s, mask))
    monkeypatch.setattr(policy, "GATHER_AT_ONCE", 0)
    prep = net.precompute(s[::2, ..., :2], mask[::2], episodes=2)
    assert same(net.forward_memory(prep, s[..., 2:]), ref, mask)


def test_neighbour_max_gradient_goes_to_the_winning_neighbour():
    """NeighbourMax's backward equals autograd through gather + amax when there are no ties, and gives a
    tied maximum's whole gradient to the first neighbour (in neighbour order) that reaches it."""
    from rlsac.rl.kernels import NeighbourMax

    g = torch.Generator().manual_seed(0)
    P, C, k = 7, 3, 4
    b = torch.randn(P, C, generator=g, requires_grad=True)
    nbr = torch.randint(P, (k * P,), generator=g)
    w = torch.randn(P, C, generator=g)
    (NeighbourMax.apply(b, nbr, k) * w).sum().backward()
    b2 = b.detach().clone().requires_grad_(True)
    (b2.index_select(0, nbr).view(k, P, C).amax(0) * w).sum().backward()
    assert torch.allclose(b.grad, b2.grad)
    # ties: rows 0 and 1 are equal; point 0's neighbours are [2, 1, 0, 1]: the gradient goes to row 1
    t = torch.tensor([[1.0], [1.0], [0.0]], requires_grad=True)
    order = torch.tensor([[2, 1, 0, 1], [2, 2, 2, 2], [2, 2, 2, 2]]).T.reshape(-1)  # neighbour-major
    NeighbourMax.apply(t, order, 4)[0].sum().backward()
    assert t.grad[:, 0].tolist() == [0.0, 1.0, 0.0]
