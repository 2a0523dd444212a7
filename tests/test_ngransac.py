"""NG-RANSAC (rlsac.rl.ngransac): its gradient on a toy problem with a known optimum, a short training run that beats
its own untrained network on held-out lines, sampling that follows the network, the same seed -> the same
checkpoint bytes, the supervised signal, and the CLI (train + evaluate, and the one-line errors)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from test_cli import assert_user_error  # tests/ is on sys.path (pytest prepend mode)
from test_fundamental import make_batch

from rlsac.cli import cli
from rlsac.config import build
from rlsac.data.lines import LineDataConf, generate, write
from rlsac.estimation import baselines
from rlsac.estimation.sampling import set_log_prob, weighted_minimal_sets
from rlsac.evaluation.train import train
from rlsac.rl import checkpoint, ngransac
from rlsac.rl.policy import Actor, PolicyConf
from rlsac.tasks import get_task
from rlsac.tasks.line import LineTask

SMALL_NET = {"k": 8, "widths": [16, 16], "global_width": 16, "head_width": 16}


class FreeLogits(torch.nn.Module):
    """A 'network' whose per-point logits are free parameters (B, N): the toy problem of the gradient test."""

    def __init__(self, B: int, N: int):
        super().__init__()
        self.logits = torch.nn.Parameter(torch.zeros(B, N))

    def forward(self, feats, mask):
        return self.logits.masked_fill(~mask, float("-inf"))


class FixedLogits(torch.nn.Module):
    """A network that returns the given logits whatever the input (the sampling test)."""

    def __init__(self, logits: torch.Tensor):
        super().__init__()
        self.fixed = logits

    def forward(self, feats, mask):
        return self.fixed.masked_fill(~mask, float("-inf"))


def lines(path, seed: int, n: int, rate: float = 0.7, points: int = 40) -> str:
    conf = LineDataConf(outlier_rate=rate, n_instances=n, n_points=points, seed=seed)
    write(path, generate(conf), conf)
    return str(path)


def line_batch(seed: int, n: int, rate: float = 0.7) -> dict:
    data = generate(LineDataConf(outlier_rate=rate, n_instances=n, n_points=40, seed=seed))
    return LineTask.to_batch(data)


def inlier_mass(net, task, batch) -> float:
    """Mean probability the network puts on the true inliers of a batch."""
    with torch.no_grad():
        p = torch.softmax(ngransac.logits_of(net, task, batch), -1)
    return float((p * task.true_inliers(batch)).sum(-1).mean())


# ------------------------------------------------------------------------------ the gradient
@pytest.mark.parametrize("signal,hypotheses", [("inliers", 1), ("pose", 1), ("inliers", 4), ("pose", 4)])
def test_one_update_raises_the_probability_of_the_true_inliers(signal, hypotheses):
    """Toy problem, known optimum: free per-point logits, uniform at the start; the loss is lowest for sets of true
    inliers (the line's consensus), so one step along the estimated gradient of the expected loss (score function
    with the mean-loss baseline) must raise the total probability of the true inliers, in every instance: with sets
    scored alone (M = 1) and with the paper's hypothesis pools (M = 4, each pool's loss its best hypothesis's)."""
    task = LineTask()
    batch = line_batch(seed=11, n=4, rate=0.6)
    net = FreeLogits(*batch["mask"].shape)
    before = inlier_mass(net, task, batch)
    objective, mean_loss = ngransac.loss(task, net, batch, samples=256 // hypotheses, signal=signal,
                                         generator=torch.Generator().manual_seed(0), hypotheses=hypotheses)
    objective.backward()
    truth = task.true_inliers(batch)
    with torch.no_grad():
        # the gradient points away from the inliers: descending it raises every inlier's logit relative to the rest
        g = net.logits.grad
        assert (g[truth].mean() < g[~truth].mean())
        net.logits -= 1.0 * g / g.abs().max()
    after = inlier_mass(net, task, batch)
    p = torch.softmax(net.logits.detach(), -1)
    per_row = (p * truth).sum(-1)
    assert after > before + 0.02 and bool((per_row > truth.float().mean(-1)).all()), (before, after, per_row)
    assert (-1.0 <= float(mean_loss) <= 0.0) if signal == "inliers" else (0.0 <= float(mean_loss) <= 1.0)


def test_a_pool_takes_the_loss_of_its_hypothesis_with_the_most_inliers():
    """The paper's sample is one RANSAC run: a pool of an outlier set and a true-inlier set has the inlier set's loss
    (whichever comes first), a pool of two outlier sets the better one's; the pool's log-probability in ``loss`` is
    the sum of its sets' (the objective rebuilt from the same draws)."""
    task = LineTask()
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 10, 10)
    on_line = np.stack([x, 0.5 * x + 1], -1)
    coords = np.concatenate([on_line, rng.uniform(0, 10, (10, 2))])[None].astype(np.float32)
    normal = np.array([-0.5, 1.0]) / np.hypot(0.5, 1.0)
    batch = {"coords": torch.from_numpy(coords), "mask": torch.ones(1, 20, dtype=torch.bool),
             "line": np.array([[*normal, -normal[1]]])}
    inlier_set, out_a, out_b = [int(x.argmin()), int(x.argmax())], [10, 11], [12, 13]
    for signal in ("inliers", "pose"):
        alone = ngransac.set_losses(task, batch, torch.tensor([[inlier_set, out_a, out_b]]), signal)[0]
        assert float(alone[0]) < float(alone[1]) and float(alone[0]) < float(alone[2])
        pools = torch.tensor([[[out_a, inlier_set], [inlier_set, out_a], [out_a, out_b]]])  # (1, K=3, M=2, 2)
        got = ngransac.pool_losses(task, batch, pools, signal)[0]
        counts = {"a": float(alone[1]), "b": float(alone[2])}
        assert float(got[0]) == float(got[1]) == float(alone[0]), (signal, got, alone)
        if signal == "inliers":  # the better of two outlier sets: the lower loss (more inliers)
            assert float(got[2]) == min(counts.values())
    # the inlier set spans the true line exactly: its loss is minus the share of points within the threshold of it
    near = np.abs(coords[0] @ normal - normal[1]) <= task.threshold
    assert near[:10].all() and float(ngransac.pool_losses(task, batch, pools, "inliers")[0, 0]) == pytest.approx(
        -near.mean(), abs=1e-6)
    net = FreeLogits(1, 20)
    with torch.no_grad():
        net.logits.copy_(torch.linspace(-1, 1, 20))
    objective, mean_loss = ngransac.loss(task, net, batch, 3, "inliers", torch.Generator().manual_seed(7), 5)
    idx = weighted_minimal_sets(net.logits.detach(), batch["mask"], 2, 15, torch.Generator().manual_seed(7))
    losses = ngransac.pool_losses(task, batch, idx.view(1, 3, 5, 2), "inliers")
    log_p = set_log_prob(net.logits.detach(), batch["mask"], idx).view(1, 3, 5).sum(-1)
    assert float(objective.detach()) == pytest.approx(float(((losses - losses.mean()) * log_p).mean()), abs=1e-6)
    assert float(mean_loss) == pytest.approx(float(losses.mean()), abs=1e-7)


def test_set_log_prob_is_the_law_of_the_draws():
    """log P(set) of ordered draws without replacement: exact on a 3-point example, and the draws follow it."""
    logits = torch.log(torch.tensor([[0.5, 0.3, 0.2, 0.0]]))
    mask = torch.tensor([[True, True, True, False]])
    lp = set_log_prob(logits, mask, torch.tensor([[[0, 1], [2, 0]]]))
    assert torch.allclose(lp.exp(), torch.tensor([[0.5 * 0.3 / 0.5, 0.2 * 0.5 / 0.8]]), atol=1e-6)
    idx = weighted_minimal_sets(logits, mask, 2, 20000, torch.Generator().manual_seed(0))[0]  # (k, 2)
    freq = torch.bincount(idx[:, 0], minlength=4).float() / idx.shape[0]
    assert torch.allclose(freq, torch.tensor([0.5, 0.3, 0.2, 0.0]), atol=0.02)
    assert bool((idx[:, 0] != idx[:, 1]).all()) and not bool((idx == 3).any())


# ------------------------------------------------------------------------------ sampling follows the network
def test_every_set_is_drawn_where_the_network_puts_its_mass(monkeypatch):
    """With logits strongly favouring a subset, every minimal set NG-RANSAC scores lies in it (uniform sets would
    leave it in almost every draw): the method samples from the network, through the one RANSAC loop."""
    task = LineTask()
    batch = line_batch(seed=5, n=3)
    B, N = batch["mask"].shape
    favoured = torch.zeros(B, N, dtype=torch.bool)
    favoured[:, [3, 7, 19, 30, 33]] = True
    net = FixedLogits(torch.where(favoured, 0.0, -40.0))
    seen = []
    real = baselines.gather_points
    monkeypatch.setattr(baselines, "gather_points", lambda coords, idx: seen.append(idx) or real(coords, idx))
    out = ngransac.estimate(task, net, batch, 100, torch.Generator().manual_seed(1))
    idx = torch.cat(seen, dim=1)  # (B, 100, m)
    assert idx.shape == (B, 100, 2) and out["hypotheses"].tolist() == [100] * B
    assert bool(favoured.gather(1, idx.flatten(1)).all())
    assert bool((idx[..., 0] != idx[..., 1]).all())  # distinct points within a set


# ------------------------------------------------------------------------------ training
def test_short_training_beats_its_untrained_network(tmp_path):
    """A few seconds of NG-RANSAC training (self-supervised inlier signal) on synthetic lines: on held-out lines the
    trained network puts more probability on the true inliers than the same network before training, and its
    RANSAC at a small budget finds hypotheses with more inliers."""
    opts = {"task": "line", "method": "ngransac", "data": lines(tmp_path / "tr.h5", 1, 64),
            "val_data": lines(tmp_path / "va.h5", 2, 16), "out": str(tmp_path / "ng.pt"), "device": "cpu", "seed": 0,
            "threads": 1, "selection": "last", "val_instances": 16, "val_iterations": 10, "val_every": 100,
            "policy": SMALL_NET, "ngransac": {"steps": 200, "batch_size": 8, "samples": 16, "lr": 1e-3}}
    summary = train(opts, track=False)
    assert summary["method"] == "ngransac" and summary["steps"] == 200
    task = LineTask()
    test = line_batch(seed=3, n=64)
    trained, conf = ngransac.load(tmp_path / "ng.pt")
    torch.manual_seed(0)  # the training's seed: the untrained network it started from
    untrained = ngransac.network(task, build(PolicyConf, conf["policy"])).eval()
    ratio = {}
    for name, net in (("trained", trained), ("untrained", untrained)):
        res = ngransac.estimate(task, net, test, 3, torch.Generator().manual_seed(5))
        ratio[name] = float((res["inliers"].sum(-1).float() / test["mask"].sum(-1)).mean())
    mass = {"trained": inlier_mass(trained, task, test), "untrained": inlier_mass(untrained, task, test)}
    assert mass["trained"] > mass["untrained"] + 0.1, mass
    assert ratio["trained"] > ratio["untrained"] + 0.02, ratio


def test_same_seed_same_checkpoint_bytes(tmp_path, monkeypatch):
    tr, va = lines(tmp_path / "tr.h5", 1, 16), lines(tmp_path / "va.h5", 2, 8)
    data = []
    for name, seed in (("a", 4), ("b", 4), ("c", 5)):  # the same relative out path (the conf it holds is the same)
        (tmp_path / name).mkdir()
        monkeypatch.chdir(tmp_path / name)
        train({"task": "line", "method": "ngransac", "data": tr, "val_data": va, "out": "ng.pt", "device": "cpu",
               "seed": seed, "threads": 1, "val_instances": 8, "val_iterations": 10, "val_every": 5,
               "policy": SMALL_NET, "ngransac": {"steps": 10, "lr": 1e-3}}, track=False)
        data.append((tmp_path / name / "ng.pt").read_bytes())
    assert data[0] == data[1] and data[0] != data[2]
    ckpt = checkpoint.read(tmp_path / "a" / "ng.pt")
    assert checkpoint.kind_of(ckpt) == "ngransac" and ckpt["in_channels"] == 2 and ckpt["history"]


def test_pose_signal_ranks_true_inlier_sets_first():
    """The supervised signal: a set of true inliers has a small pose error, a set of outliers the clipped maximum;
    on two-view data (fundamental) both signals give finite losses in range and a finite gradient."""
    task = LineTask()
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 10, 10)
    on_line = np.stack([x, 0.5 * x + 1 + rng.uniform(-0.01, 0.01, 10)], -1)  # y = x / 2 + 1, barely disturbed
    coords = np.concatenate([on_line, rng.uniform(0, 10, (10, 2))])[None].astype(np.float32)
    normal = np.array([-0.5, 1.0]) / np.hypot(0.5, 1.0)
    batch = {"coords": torch.from_numpy(coords), "mask": torch.ones(1, 20, dtype=torch.bool),
             "line": np.array([[*normal, -normal[1]]])}
    idx = torch.tensor([[[int(x.argmin()), int(x.argmax())], [10, 11]]])  # two inliers far apart; two outliers
    loss = ngransac.set_losses(task, batch, idx, "pose")
    assert float(loss[0, 0]) < 0.5 and float(loss[0, 1]) > float(loss[0, 0]), loss

    fb = make_batch(B=2, N=60, outlier_rate=0.3, noise=0.5, seed=1)
    for name in ("fundamental", "essential"):  # the same file for every task: the plug-in point is the Task API
        two_view = get_task(name)
        net = Actor(two_view.feature_dim, build(PolicyConf, {**SMALL_NET, "graph_dims": 4}))
        for signal in ("inliers", "pose"):
            net.zero_grad()
            objective, mean_loss = ngransac.loss(two_view, net, fb, 4, signal, torch.Generator().manual_seed(0))
            objective.backward()
            assert torch.isfinite(objective) and -1.0 <= float(mean_loss) <= 1.0
            assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
        res = ngransac.estimate(two_view, net, fb, 20, torch.Generator().manual_seed(0))
        assert res["hyp"].shape == (2, 3, 3) and res["hypotheses"].tolist() == [20, 20]


# ------------------------------------------------------------------------------ CLI
def _train_args(tr, va, out, *sets):
    args = ["train", "--task", "line", "--method", "ngransac", "--data", tr, "--val-data", va, "--out", out,
            "--device", "cpu", "--params", ""]
    for s in ("threads=1", "val_instances=8", "val_iterations=10", "val_every=5", "ngransac.steps=10",
              "policy.k=8", "policy.widths=[16, 16]", *sets):
        args += ["--set", s]
    return args


def test_train_then_evaluate_cli(workdir):
    """`rlsac train --method ngransac` then `rlsac evaluate --method ngransac` / `ngransac-lo` on its checkpoint."""
    tr, va, te = lines(workdir / "tr.h5", 1, 16), lines(workdir / "va.h5", 2, 8), lines(workdir / "te.h5", 3, 8)
    runner = CliRunner()
    res = runner.invoke(cli, _train_args(tr, va, "ck/ng.pt"))
    assert res.exit_code == 0, res.output
    assert checkpoint.kind_of(checkpoint.read(workdir / "ck/ng.pt")) == "ngransac"
    for method in ("ngransac", "ngransac-lo"):
        res = runner.invoke(cli, ["evaluate", "--task", "line", "--method", method, "--checkpoint", "ck/ng.pt",
                                  "--data", te, "--iterations", "20", "--out-dir", f"ev/{method}", "--device", "cpu",
                                  "--params", "", "--no-tracking"])
        assert res.exit_code == 0, res.output
        summary = json.loads((workdir / f"ev/{method}/summary.json").read_text())
        assert summary["method"] == method and summary["n_instances"] == 8 and 0.0 <= summary["mAA"] <= 1.0


def test_cli_errors_before_any_work(workdir):
    """A checkpoint of the wrong kind, an unknown option, a bad value: `error: <one line>`, exit 2, nothing written."""
    tr, va, te = lines(workdir / "tr.h5", 1, 8), lines(workdir / "va.h5", 2, 8), lines(workdir / "te.h5", 3, 8)
    task = LineTask()
    rl = Actor(task.feature_dim + 3, build(PolicyConf, SMALL_NET))
    checkpoint.write(workdir / "rl.pt", checkpoint.actor_payload(rl, {"task": "line", "policy": SMALL_NET}, 5, 1, {},
                                                                 "last", []))
    ng = ngransac.network(task, build(PolicyConf, SMALL_NET))
    checkpoint.write(workdir / "ng.pt", ngransac.payload(ng, {"task": "line", "policy": SMALL_NET}, 2, 1, {}, "last",
                                                         []))
    runner = CliRunner()
    for method, ckpt, words in (("ngransac", "rl.pt", "rlsac checkpoint, not an ngransac one"),
                                ("ngransac-lo", "rl.pt", "not an ngransac one"),
                                ("rlsac", "ng.pt", "ngransac checkpoint, not an rlsac one")):
        res = runner.invoke(cli, ["evaluate", "--task", "line", "--method", method, "--checkpoint", ckpt, "--data", te,
                                  "--out-dir", "ev", "--device", "cpu", "--params", "", "--no-tracking"])
        assert_user_error(res, words)
        assert not (workdir / "ev").exists()
    for sets, words in ((("ngransac.bogus=1",), "unknown config key"), (("ngransac.signal=guess",), "signal"),
                        (("ngransac.samples=1",), "samples"), (("method=sac",), "method")):
        res = runner.invoke(cli, _train_args(tr, va, "x.pt", *sets) + ["--no-tracking"])
        assert_user_error(res, words)
        assert not (workdir / "x.pt").exists()
    res = runner.invoke(cli, _train_args(tr, va, "x.pt") + ["--resume", "--no-tracking"])
    assert_user_error(res, "no --resume")
    assert not (workdir / "x.pt").exists()
    res = runner.invoke(cli, ["train", "--task", "line", "--method", "sac", "--data", tr])
    assert_user_error(res, "sac")


# ------------------------------------------------------------------------------ format and pipeline
def test_rlsac_checkpoints_keep_their_conf(tmp_path):
    """An RLSAC checkpoint (and its training state) stores the conf it stored before NG-RANSAC (no method / ngransac
    keys: retrained committed checkpoints keep their bytes); an NG-RANSAC one its own sections (no env / sac)."""
    from rlsac.evaluation.train import TrainConf, stored_conf

    rl, ng = stored_conf(build(TrainConf, {})), stored_conf(build(TrainConf, {"method": "ngransac"}))
    assert not {"method", "ngransac"} & set(rl) and {"env", "sac"} <= set(rl)
    assert {"method", "ngransac", "policy"} <= set(ng) and not {"env", "sac"} & set(ng)
    train({"task": "line", "data": lines(tmp_path / "tr.h5", 1, 8), "out": str(tmp_path / "rl.pt"), "device": "cpu",
           "threads": 1, "policy": SMALL_NET, "ckpt_every": 4,
           "sac": {"total_steps": 4, "num_envs": 2, "batch_size": 4, "learning_starts": 2}}, track=False)
    for path in ("rl.pt", "rl.state.pt"):
        stored = torch.load(tmp_path / path, weights_only=False)["conf"]
        given = {k: stored[k] for k in ("data", "out", "device", "threads", "ckpt_every", "policy", "sac")}
        assert stored == rl | given and list(stored) == list(rl)


def test_fold_models_of_method_ngransac():
    """A folds.train recipe with method ngransac is a fold model whose rows (itself, its seeds, its -lo) evaluate
    with the ngransac methods; the RLSAC-only rows (-fast, -prob) refuse it."""
    from rlsac.config import load_params
    from rlsac.errors import RlsacError
    from rlsac.experiments.folds import protocol, rows

    params = load_params(Path(__file__).parents[1] / "experiments" / "quick" / "params.yaml")
    p = protocol(params)
    r = rows(p, "fountain", "hard")
    assert (r["ngransac"]["method"], r["ngransac-s1"]["method"], r["ngransac-lo"]["method"]) == (
        "ngransac", "ngransac", "ngransac-lo")
    assert r["ngransac-s1"]["checkpoint"].name == "ngransac-s1.pt" and r["rlsac"]["method"] == "rlsac"
    for key in ("fast", "prob_models"):
        bad = {**params, "folds": {**params["folds"], key: ["ngransac"]}}
        with pytest.raises(RlsacError, match="only RLSAC models"):
            protocol(bad)
    for method in ("ngransac", "ngransac-lo"):  # a trained method is a model, not a baseline row
        bad = {**params, "folds": {**params["folds"], "methods": ["ransac", method]}}
        with pytest.raises(RlsacError, match="not a baseline"):
            protocol(bad)
