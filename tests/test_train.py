"""A tiny train + evaluate run of RLSAC, resume, and seed determinism."""

import json

import torch
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.data.lines import LineDataConf, generate, write
from rlsac.evaluation.train import train

TINY = {"threads": 1, "val_instances": 8, "val_every": 10, "ckpt_every": 10,
        "sac": {"total_steps": 20, "num_envs": 4, "batch_size": 8, "learning_starts": 16}}


def tiny_lines(path, seed, n):
    conf = LineDataConf(outlier_rate=0.5, n_instances=n, n_points=40, seed=seed)
    write(path, generate(conf), conf)
    return str(path)


def test_train_then_evaluate_cli(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path}/mlflow.db")
    tr, va, te = tiny_lines(tmp_path / "tr.h5", 1, 32), tiny_lines(tmp_path / "va.h5", 2, 8), tiny_lines(
        tmp_path / "te.h5", 3, 16)
    runner = CliRunner()
    args = ["train", "--task", "line", "--data", tr, "--val-data", va, "--out", "ck/line.pt", "--device", "cpu",
            "--params", ""]
    for k, v in (("threads", 1), ("val_instances", 8), ("val_every", 10), ("sac.total_steps", 20),
                 ("sac.num_envs", 4), ("sac.batch_size", 8), ("sac.learning_starts", 16)):
        args += ["--set", f"{k}={v}"]
    res = runner.invoke(cli, args)
    assert res.exit_code == 0, res.output
    ckpt = torch.load(tmp_path / "ck/line.pt", weights_only=False)
    assert ckpt["in_channels"] == 5 and ckpt["conf"]["sac"]["total_steps"] == 20
    assert (tmp_path / "ck/line.state.pt").is_file()

    res = runner.invoke(cli, ["evaluate", "--task", "line", "--method", "rlsac", "--checkpoint", "ck/line.pt",
                              "--data", te, "--iterations", "30", "--out-dir", "ev", "--device", "cpu"])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "ev/summary.json").read_text())
    assert summary["method"] == "rlsac" and summary["n_instances"] == 16 and 0.0 <= summary["mAA"] <= 1.0

    # resuming a finished run with a larger budget continues from the saved step
    args2 = [a if a != "sac.total_steps=20" else "sac.total_steps=30" for a in args] + ["--resume"]
    res = runner.invoke(cli, args2)
    assert res.exit_code == 0, res.output
    assert torch.load(tmp_path / "ck/line.state.pt", weights_only=False)["step"] == 30


def test_same_seed_same_weights(tmp_path):
    tr = tiny_lines(tmp_path / "tr.h5", 1, 32)
    outs = []
    for name in ("a", "b"):
        train({**TINY, "data": tr, "out": str(tmp_path / f"{name}.pt"), "device": "cpu", "seed": 7}, track=False)
        outs.append(torch.load(tmp_path / f"{name}.pt", weights_only=False)["actor"])
    assert all(torch.equal(outs[0][k], outs[1][k]) for k in outs[0])


def test_bad_training_data_is_one_line_error(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.h5").write_text("not hdf5")
    res = CliRunner().invoke(cli, ["train", "--task", "line", "--data", "bad.h5", "--out", "x.pt", "--no-tracking"])
    assert res.exit_code == 2
    assert "Traceback" not in res.output and not (tmp_path / "x.pt").exists()


def test_init_starts_from_another_runs_networks_and_nothing_else(tmp_path, monkeypatch):
    """Issue #46's pretraining: ``init`` loads a state's networks; with no update before the end (learning_starts
    past the run's transitions) the kept actor is that state's actor exactly, whatever the seed; the optimisers,
    buffer and step are this run's own (step 0: it trains its full length)."""
    tr = tiny_lines(tmp_path / "tr.h5", 1, 32)
    train({**TINY, "data": tr, "out": str(tmp_path / "pre.pt"), "device": "cpu", "seed": 7}, track=False)
    pre = torch.load(tmp_path / "pre.state.pt", weights_only=False)
    want = {k[len("actor."):]: v for k, v in pre["agent"].items() if k.startswith("actor.")}
    frozen = {**TINY, "selection": "last", "sac": {**TINY["sac"], "total_steps": 2, "learning_starts": 10_000}}
    for name, init in (("a", str(tmp_path / "pre.state.pt")), ("b", "")):
        train({**frozen, "data": tr, "out": str(tmp_path / f"{name}.pt"), "device": "cpu", "seed": 3, "init": init},
              track=False)
    a, b = (torch.load(tmp_path / f"{n}.pt", weights_only=False) for n in ("a", "b"))
    assert a["step"] == 2 and a["conf"]["init"] == str(tmp_path / "pre.state.pt") and "init" not in b["conf"]
    assert all(torch.equal(a["actor"][k], want[k]) for k in want) and set(a["actor"]) == set(want)
    assert not all(torch.equal(b["actor"][k], want[k]) for k in want)  # random initialisation otherwise

    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(cli, ["train", "--task", "line", "--data", tr, "--out", "c.pt", "--no-tracking",
                                   "--params", "", "--set", "init=missing.state.pt"])
    assert res.exit_code == 2 and "missing.state.pt: no such training state" in res.output
    assert not (tmp_path / "c.pt").exists()


def test_init_is_refused_where_it_would_do_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    tr = tiny_lines(tmp_path / "tr.h5", 1, 8)
    res = CliRunner().invoke(cli, ["train", "--task", "line", "--method", "ngransac", "--data", tr, "--out", "n.pt",
                                   "--no-tracking", "--params", "", "--set", "init=x.state.pt"])
    assert res.exit_code == 2 and "does not read it" in res.output and not (tmp_path / "n.pt").exists()
