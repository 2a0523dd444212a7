"""What a training episode sees (rlsac.rl.episodes, issue #46): fixed pairs, or a fresh draw of the pool with the images
swapped at random; the replay buffer rebuilds each transition's input from what it stored."""

from __future__ import annotations

import pytest
import torch

from rlsac.evaluation.train import LATER_DEFAULTS, TrainConf, stored_conf
from rlsac.maths import geometry
from rlsac.rl.episodes import FixedPairs, RedrawnPairs, _swap_features, pool_tensors
from rlsac.rl.policy import Actor, PolicyConf
from rlsac.rl.rollout import in_channels
from rlsac.rl.sac import ReplayBuffer
from rlsac.tasks.fundamental import FundamentalTask
from tests.test_speed_equivalence import two_view_batch

POLICY = PolicyConf(k=6, widths=[8], global_width=8, head_width=8, graph_dims=4)


def _pool(pad: int = 0):
    task = FundamentalTask()
    b = two_view_batch(3, N=40, pad=pad, seed=2)
    b["features"][0, 5:10, 5] = 7.0  # descriptor 1 marked on a few points: the swap must move it to descriptor 2
    return task, pool_tensors(b, "cpu"), Actor(in_channels(task), POLICY)


def test_swapping_the_images_moves_every_channel_and_twice_is_identity():
    raw = torch.arange(2 * 261, dtype=torch.float32).view(1, 2, 261)
    sw = _swap_features(raw)
    assert torch.equal(sw[..., :5], raw[..., [2, 3, 0, 1, 4]])
    assert torch.equal(sw[..., 5:133], raw[..., 133:261]) and torch.equal(sw[..., 133:], raw[..., 5:133])
    assert torch.equal(_swap_features(sw), raw)


def test_the_swapped_pair_scores_every_hypothesis_alike():
    """F on (x1, x2) and F^T on (x2, x1): the same Sampson error, so the reward of an episode is the same."""
    b = two_view_batch(2, N=30, seed=4)
    F, _ = geometry.eight_point(b["coords"][:, :8].double())
    coords = b["coords"].double()
    r = geometry.sampson_distance(F, coords, squared=True)
    r_sw = geometry.sampson_distance(F.transpose(1, 2), coords[..., [2, 3, 0, 1]], squared=True)
    assert torch.allclose(r, r_sw, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("swap", [False, True])
def test_a_draw_takes_valid_points_and_the_buffer_rebuilds_it(swap):
    task, pool, actor = _pool(pad=15)  # instance 0 has 25 valid points of 40
    src = RedrawnPairs(task, pool, actor, points=20, swap=swap)
    inst = torch.tensor([0, 1, 2, 0, 1, 2, 0, 0])
    gen = torch.Generator().manual_seed(3)
    batch, feats, graph, extra = src.draw(inst, gen)
    idx, flip = extra[:, :-1], extra[:, -1].bool()
    assert idx.shape == (8, 20) and bool((idx.diff(dim=-1) > 0).all())  # distinct, kept in SNN (file) order
    assert bool(pool["mask"][inst].gather(1, idx).all())  # 20 of instance 0's 25 valid points, never padding
    assert bool(flip.any()) == swap and (not swap or not bool(flip.all()))
    again = src.draw(inst, torch.Generator().manual_seed(3))
    assert torch.equal(again[3], extra)  # seeded
    r_feats, r_mask, r_graph = src.lookup(inst, extra)  # what an update sees of these transitions
    assert torch.equal(r_feats, feats) and torch.equal(r_mask, batch["mask"]) and torch.equal(r_graph, graph)
    row = int(torch.nonzero(flip)[0]) if swap else 0
    x = batch["coords"][row]
    orig = pool["coords"][inst[row]][idx[row]]
    assert torch.equal(x, orig[:, [2, 3, 0, 1]] if swap else orig)


def test_fixed_pairs_are_the_training_file_itself():
    task, pool, actor = _pool()
    data = {"coords": pool["coords"], "mask": pool["mask"], "features": task.features(pool)}
    src = FixedPairs(task, data, actor)
    batch, feats, graph, extra = src.draw(torch.tensor([2, 0]), torch.Generator())
    assert extra is None and torch.equal(feats, data["features"][[2, 0]]) and src.extra_width == 0


def test_the_buffer_keeps_the_draws_for_a_resume():
    buf = ReplayBuffer(size=4, n=3, m=2, device=torch.device("cpu"), extra=4)
    z = torch.zeros
    buf.add(torch.tensor([1, 2]), z(2, 3, 3), z(2, 3, 3), z(2, 2, dtype=torch.long), z(2), z(2, dtype=torch.bool),
            torch.tensor([[0, 5, 9, 1], [2, 3, 4, 0]]))
    st = buf.state_dict()
    dst = ReplayBuffer(size=4, n=3, m=2, device=torch.device("cpu"), extra=4)
    dst.load_state_dict(st)
    assert torch.equal(dst.extra[:2], torch.tensor([[0, 5, 9, 1], [2, 3, 4, 0]], dtype=torch.int16))
    with pytest.raises(ValueError, match="redrawn episodes"):
        ReplayBuffer(size=4, n=3, m=2, device=torch.device("cpu")).load_state_dict(st)


def test_the_records_checkpoints_keep_their_configuration():
    """Options added for the scale study stay out of a stored configuration at their defaults (the record's
    checkpoint bytes); set, they are stored."""
    conf = stored_conf(TrainConf(task="fundamental"))
    assert not set(LATER_DEFAULTS) & set(conf)
    conf = stored_conf(TrainConf(task="fundamental", snapshot_steps=[5], episodes={"pool": "p.h5"}))
    assert conf["snapshot_steps"] == [5] and conf["episodes"]["pool"] == "p.h5"
    assert "prefilter" not in conf["episodes"]  # a section key added later: out at its default (states resume)
    conf = stored_conf(TrainConf(task="fundamental", episodes={"pool": "p.h5", "prefilter": [0.8, 1.0]}))
    assert conf["episodes"]["prefilter"] == [0.8, 1.0]


def test_a_pre_filtered_episode_masks_what_the_evaluation_masks_and_the_buffer_rebuilds_it():
    """episodes.prefilter: each episode's points masked where the SNN ratio is above the episode's drawn ratio (as
    rlsac.tasks.prefiltered), unless fewer than the minimal sample would remain; 1.0 masks nothing."""
    from rlsac.tasks import prefiltered

    task, pool, actor = _pool()
    pool["features"][..., 4] = torch.linspace(0.0, 1.0, 40).expand(3, 40)  # SNN ratios 0 .. 1 along the points
    pool["features"][2, :, 4] = 0.99  # instance 2: every point above 0.8 -> the filter would leave nothing
    src = RedrawnPairs(task, pool, actor, points=20, swap=False, prefilter=[0.5, 1.0])
    assert src.extra_width == 22
    inst = torch.tensor([0, 1, 2, 0, 1, 2, 0, 1])
    batch, feats, graph, extra = src.draw(inst, torch.Generator().manual_seed(3))
    ratio = torch.tensor([0.5, 1.0])[extra[:, -1]]
    assert ratio[[2, 5]].tolist() == [0.5, 1.0]  # instance 2 once filtered (nothing would be left), once not
    idx = extra[:, :20]
    raw = {"features": pool["features"][inst].gather(1, idx[..., None].expand(-1, -1, 261)),
           "coords": pool["coords"][inst].gather(1, idx[..., None].expand(-1, -1, 4)),
           "mask": torch.ones(8, 20, dtype=torch.bool)}
    for e in range(8):
        want = prefiltered(task, {k: v[e:e + 1] for k, v in raw.items()}, float(ratio[e]))["mask"][0]
        if int(inst[e]) == 2 and float(ratio[e]) < 1.0:
            want = torch.ones(20, dtype=torch.bool)  # nothing left: the episode keeps its points
        assert torch.equal(batch["mask"][e], want), e
    r_feats, r_mask, r_graph = src.lookup(inst, extra)
    assert torch.equal(r_mask, batch["mask"]) and torch.equal(r_feats, feats) and torch.equal(r_graph, graph)
    plain = RedrawnPairs(task, pool, actor, points=20, swap=False).draw(inst, torch.Generator().manual_seed(3))[3]
    assert torch.equal(plain, extra[:, :21])  # the pre-filter's draw comes after the redraw's: same points
