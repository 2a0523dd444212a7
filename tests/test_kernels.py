"""The SAC update's dense products (rlsac.rl.kernels): oneDNN's compute ATen's function, forward and backward, and an
update with them the same losses on the same batch; the option is stored only when it departs from the record's."""

import copy

import pytest
import torch
import torch.nn.functional as F

from rlsac.errors import RlsacError
from rlsac.evaluation.train import TrainConf, check, stored_conf
from rlsac.rl.kernels import linear_for, onednn_linear
from rlsac.rl.policy import PolicyConf, knn
from rlsac.rl.sac import SACAgent, SACConf


def test_onednn_linear_is_atens_linear_forward_and_backward():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(3, 50, 20, generator=gen, requires_grad=True)
    w = torch.randn(7, 20, generator=gen, requires_grad=True)
    b = torch.randn(7, generator=gen, requires_grad=True)
    g = torch.randn(3, 50, 7, generator=gen)
    grads = []
    for lin in (F.linear, onednn_linear):
        y = lin(x, w, b)
        y.backward(g)
        grads.append((y.detach(), x.grad.clone(), w.grad.clone(), b.grad.clone()))
        x.grad = w.grad = b.grad = None
    for a, o in zip(*grads, strict=True):
        assert a.shape == o.shape
        torch.testing.assert_close(o, a, rtol=1e-5, atol=1e-5)
    assert onednn_linear(x, w).shape == (3, 50, 7)  # no bias
    with pytest.raises(ValueError, match="aten, onednn"):
        linear_for("mkl")


def _batch(gen, b=6, n=20, c=9, m=8):
    s = torch.rand(b, n, c, generator=gen)
    s2 = s.clone()
    s2[..., -3:] = torch.rand(b, n, 3, generator=gen)
    mask = torch.ones(b, n, dtype=torch.bool)
    mask[0, -3:] = False
    graph = knn(s[..., :2], 5, mask)
    action = torch.multinomial(mask.float(), m, generator=gen)
    return s, s2, mask, graph, action, torch.rand(b, generator=gen), torch.zeros(b)


def test_an_update_with_onednn_computes_the_same_losses_on_the_same_batch():
    torch.manual_seed(0)
    ref = SACAgent(9, PolicyConf(k=5, widths=[8, 8], global_width=8, head_width=8), SACConf(batch_size=6))
    fast = copy.deepcopy(ref).set_kernels("onednn")
    assert fast.qf1_target.linear is onednn_linear and ref.actor.linear is F.linear
    gen = torch.Generator().manual_seed(1)
    for _ in range(3):
        batch = _batch(gen)
        m_ref, m_fast = ref.update(*batch), fast.update(*batch)
        for key in ("losses/qf1", "losses/qf2", "losses/actor", "losses/alpha"):
            assert m_fast[key] == pytest.approx(m_ref[key], rel=1e-5, abs=1e-7)
    for p, q in zip(ref.parameters(), fast.parameters(), strict=True):
        torch.testing.assert_close(q, p, rtol=0, atol=1e-3)  # Adam's steps: lr-sized at most


def test_the_option_is_stored_only_off_its_default_and_checked(tmp_path):
    base = {"task": "line", "data": str(tmp_path / "x.h5"), "out": str(tmp_path / "m.pt")}
    assert "kernels" not in stored_conf(TrainConf())  # the record's checkpoints keep their bytes
    assert stored_conf(TrainConf(kernels="onednn"))["kernels"] == "onednn"
    with pytest.raises(RlsacError, match="kernels"):
        check({**base, "kernels": "mkl"}, track=False)


def test_the_compiled_neighbour_max_has_the_eager_ones_bytes_forward_and_backward():
    """The same values and the same gradient bytes, a tied maximum's gradient to its first neighbour included."""
    from rlsac.rl.kernels import neighbour_max_for

    eager, compiled = neighbour_max_for("eager"), neighbour_max_for("compiled")
    g = torch.Generator().manual_seed(0)
    P, C, k = 40, 6, 5
    b = torch.randn(P, C, generator=g)
    b[:8] = 0.5  # ties between neighbours
    nbr = torch.randint(P, (k * P,), generator=g)
    w = torch.randn(P, C, generator=g)
    out = []
    for fn in (eager, compiled):
        x = b.clone().requires_grad_(True)
        y = fn(x, nbr, k)
        (y * w).sum().backward()
        out.append((y.detach(), x.grad))
    assert torch.equal(out[0][0], out[1][0]) and torch.equal(out[0][1], out[1][1])
    t = torch.tensor([[1.0], [1.0], [0.0]], requires_grad=True)
    order = torch.tensor([[2, 1, 0, 1], [2, 2, 2, 2], [2, 2, 2, 2]]).T.reshape(-1)  # point 0's neighbours 2, 1, 0, 1
    compiled(t, order, 4)[0].sum().backward()
    assert t.grad[:, 0].tolist() == [0.0, 1.0, 0.0]  # the first neighbour reaching the max: row 1
    with pytest.raises(ValueError, match="eager, compiled"):
        neighbour_max_for("fused")


def test_updates_with_the_compiled_neighbour_max_leave_the_same_weights():
    torch.manual_seed(0)
    ref = SACAgent(9, PolicyConf(k=5, widths=[8, 8], global_width=8, head_width=8), SACConf(batch_size=6))
    fast = copy.deepcopy(ref).set_kernels("aten", "compiled")
    gen = torch.Generator().manual_seed(1)
    for _ in range(3):
        batch = _batch(gen)
        assert fast.update(*batch) == ref.update(*batch)
    for p, q in zip(ref.parameters(), fast.parameters(), strict=True):
        assert torch.equal(p, q)


def test_the_neighbour_max_is_a_speed_setting_never_stored_and_checked(tmp_path, monkeypatch):
    import shutil

    base = {"task": "line", "data": str(tmp_path / "x.h5"), "out": str(tmp_path / "m.pt")}
    assert stored_conf(TrainConf(neighbour_max="compiled")) == stored_conf(TrainConf())  # the same checkpoint bytes
    with pytest.raises(RlsacError, match="neighbour_max"):
        check({**base, "neighbour_max": "fused"}, track=False)
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(RlsacError, match="C\\+\\+ compiler"):
        check({**base, "neighbour_max": "compiled"}, track=False)
