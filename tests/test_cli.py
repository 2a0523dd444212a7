"""End to end through the click CLI on tiny budgets, in a tmp working directory."""

import json
import os
import re
import subprocess
import sys
import types

import h5py
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from rlsac import commands
from rlsac.cli import cli
from rlsac.errors import RlsacError
from rlsac.evaluation.evaluate import evaluate, task_from

COMMANDS = ["synth-lines", "import-scenes", "prepare-cvpr2020", "train", "evaluate", "ablate", "plot",
            "calibrate-lines", "pipeline"]


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def assert_user_error(result, *fragments):
    assert result.exit_code == 2, result.output
    err = result.stderr.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    assert "Traceback" not in result.output
    for f in fragments:
        assert f in err, err


def synth(path="d.h5", n=12, rate=0.3, *extra):
    r = invoke("synth-lines", "--outlier", rate, "--n-instances", n, "--seed", 1, "--out", path, "--no-tracking",
               *extra)
    assert r.exit_code == 0, r.output
    return r


def test_help_lists_all_subcommands():
    r = invoke("--help")
    assert r.exit_code == 0
    for c in COMMANDS:
        assert c in r.output


def test_evaluate_offers_every_registered_method():
    """The CLI's --method choices are rlsac.evaluation.methods.METHODS, the list evaluate builds estimators for."""
    from rlsac.evaluation.methods import METHODS

    choices = next(p for p in cli.commands["evaluate"].params if p.name == "method").type.choices
    assert list(choices) == list(METHODS) and {"guided", "prosac", "uniform"} <= set(choices)


def test_console_script_help_and_error(tmp_path):
    r = subprocess.run([sys.executable, "-c", "from rlsac.cli import main; main()", "evaluate", "--task", "line",
                        "--method", "ransac", "--data", str(tmp_path / "missing.h5"), "--no-tracking"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and r.stderr.startswith("error: ") and "no such file" in r.stderr


def test_synth_lines_writes_a_valid_file(workdir):
    r = synth("data/x.h5", 12, 0.3, "--n-points", 40)
    assert "data/x.h5" in r.stdout and "12 instances" in r.stdout
    from rlsac.data.lines import read

    data, attrs = read("data/x.h5")
    assert data["points"].shape == (12, 40, 2) and attrs["outlier_rate"] == 0.3 and attrs["seed"] == 1
    assert sorted(p.name for p in (workdir / "data").iterdir()) == ["x.h5"]


def test_synth_lines_default_path(workdir):
    r = invoke("synth-lines", "--outlier", 0.2, "--n-instances", 3, "--seed", 5, "--no-tracking")
    assert r.exit_code == 0, r.output
    assert (workdir / "data/lines/lines_o0.2_s5.h5").is_file()


@pytest.mark.parametrize("args,fragment", [
    (["--outlier", "1.0"], "outlier rate"),
    (["--outlier", "-0.2"], "outlier rate"),
    (["--n-instances", "0"], "counts must be positive"),
    (["--n-points", "-3"], "counts must be positive"),
])
def test_synth_lines_bad_input(workdir, args, fragment):
    r = invoke("synth-lines", *args, "--out", "out/x.h5")
    assert_user_error(r, fragment)
    assert not (workdir / "out").exists()
    assert not (workdir / "mlflow.db").exists()  # validated before any run is opened


def test_evaluate_ransac_writes_csv_json_and_mlflow_run(workdir):
    synth("d.h5", 12)
    r = invoke("evaluate", "--task", "line", "--method", "ransac", "--data", "d.h5", "--iterations", 30,
               "--batch-size", 5, "--out-dir", "ev", "--device", "cpu")
    assert r.exit_code == 0, r.output
    assert "mAA=" in r.stdout
    frame = pd.read_csv(workdir / "ev/errors.csv")
    assert list(frame.columns) == ["instance", "err_deg", "n_hypotheses", "n_inliers"] and len(frame) == 12
    assert (frame["n_hypotheses"] == 30).all()  # RANSAC scores every set of its budget
    assert frame["instance"].tolist() == list(range(12))
    summary = json.loads((workdir / "ev/summary.json").read_text())
    assert summary["method"] == "ransac" and summary["iterations"] == 30 and summary["n_instances"] == 12
    assert 0 <= summary["mAA"] <= 1
    assert summary["median_deg"] == pytest.approx(float(np.median(frame["err_deg"])), rel=1e-4)
    # timings go to the untracked sidecar (and MLflow), never into the committed summary: a re-run gives the same bytes
    assert not any("seconds" in k or "time" in k for k in summary)
    assert json.loads((workdir / "ev/timing.json").read_text())["seconds_per_instance"] > 0
    first = {f: (workdir / "ev" / f).read_bytes() for f in ("errors.csv", "summary.json", "config.json")}
    r = invoke("evaluate", "--task", "line", "--method", "ransac", "--data", "d.h5", "--iterations", 30,
               "--batch-size", 5, "--out-dir", "ev", "--device", "cpu", "--no-tracking")
    assert r.exit_code == 0, r.output
    assert {f: (workdir / "ev" / f).read_bytes() for f in first} == first

    import mlflow

    runs = mlflow.search_runs(experiment_names=["lines"], output_format="list")
    assert len(runs) == 1
    run = runs[0]
    assert run.info.status == "FINISHED"
    assert run.data.params["method"] == "ransac" and run.data.params["iterations"] == "30"
    assert run.data.metrics["mAA"] == pytest.approx(summary["mAA"])
    arts = {a.path for a in mlflow.MlflowClient().list_artifacts(run.info.run_id)}
    assert {"errors.csv", "summary.json"} <= arts


def test_evaluate_is_deterministic_and_reads_params_yaml(workdir):
    synth("d.h5", 8)
    (workdir / "params.yaml").write_text("evaluate:\n  line:\n    iterations: 7\n")
    outs = []
    for name in ("a", "b"):
        r = invoke("evaluate", "--task", "line", "--method", "ransac", "--data", "d.h5", "--out-dir", name,
                   "--no-tracking")
        assert r.exit_code == 0, r.output
        outs.append(json.loads((workdir / name / "summary.json").read_text()))
    assert outs[0]["iterations"] == 7
    assert outs[0]["mAA"] == outs[1]["mAA"] and outs[0]["median_deg"] == outs[1]["median_deg"]


def _wrong_key(path):
    with h5py.File(path, "w") as f:
        f["pts"] = np.zeros((2, 5, 2))


def _text(path):
    path.write_text("not hdf5\n")


def _nan(path):
    with h5py.File(path, "w") as f:
        f["points"] = np.full((2, 5, 2), np.nan, dtype=np.float32)
        f["line"] = np.zeros((2, 3))
        f["inlier_mask"] = np.zeros((2, 5), bool)


@pytest.mark.parametrize("make,fragment", [
    (None, "no such file"), (_text, "not a readable HDF5"), (_wrong_key, "missing key 'points'"), (_nan, "NaN"),
])
def test_evaluate_bad_data(workdir, make, fragment):
    path = workdir / "bad.h5"
    if make:
        make(path)
    r = invoke("evaluate", "--task", "line", "--method", "ransac", "--data", path, "--out-dir", "ev", "--no-tracking")
    assert_user_error(r, fragment)
    assert not (workdir / "ev").exists()


@pytest.mark.parametrize("args,fragment", [
    (["--method", "usac"], "needs an OpenCV estimator, which task 'line' has not "
                           "(tasks with it: fundamental, essential)"),
    (["--task", "fundamental", "--method", "oracle"], "needs the true inlier mask in its data (synthetic data), which "
                                                      "task 'fundamental' has not (tasks with it: line)"),
    (["--method", "rlsac"], "needs --checkpoint"),
    (["--method", "rlsac", "--checkpoint", "nope.pt"], "no such checkpoint"),
    (["--method", "ransac", "--iterations", "0"], "iterations must be positive"),
])
def test_evaluate_bad_options(workdir, args, fragment):
    synth("d.h5", 3)
    r = invoke("evaluate", "--task", "line", "--data", "d.h5", "--out-dir", "ev", "--no-tracking", *args)
    assert_user_error(r, fragment)
    assert not (workdir / "ev").exists()


def test_usage_error_keeps_clicks_exit_code(workdir):
    r = invoke("evaluate", "--task", "circle", "--method", "ransac", "--data", "x.h5")
    assert r.exit_code == 2 and "Traceback" not in r.output


def test_evaluate_rlsac_uses_the_checkpoint_task_options(workdir, monkeypatch):
    """The rlsac method against the checkpoint's and rollout's contracts, with a fake rollout running RANSAC."""
    from rlsac.estimation.baselines import ransac

    seen = {}

    def load_actor(path, device):
        seen["device"] = device
        return "actor", {"task": "line", "task_options": {"threshold": 0.2},
                         "env": {"steps_per_episode": 5, "residual_clip": 3.0, "candidates": 4}}

    def rlsac_estimate(task, batch, actor, iterations, env_conf, sampling, generator, policy_every, sets_per_step,
                       confidence, state_threshold):
        seen.update(threshold=task.threshold, steps=env_conf.steps_per_episode, clip=env_conf.residual_clip,
                    candidates=env_conf.candidates, sampling=sampling, actor=actor, policy_every=policy_every,
                    sets_per_step=sets_per_step, confidence=confidence, state_threshold=state_threshold)
        return ransac(task, batch, iterations, generator)

    from rlsac.rl import checkpoint, rollout

    monkeypatch.setattr(checkpoint, "load_actor", load_actor)
    monkeypatch.setattr(checkpoint, "state_scales", lambda path, device, unit=None: {"residual_threshold": 0.3})
    monkeypatch.setattr(rollout, "rlsac_estimate", rlsac_estimate)
    synth("d.h5", 4)
    (workdir / "ck.pt").write_bytes(b"x")
    s = evaluate({"task": "line", "method": "rlsac", "data": "d.h5", "checkpoint": "ck.pt", "iterations": 10,
                  "device": "cpu", "out_dir": "ev", "sets_per_step": 3, "confidence": 0.9}, track=False)
    # the checkpoint's own env settings (not code defaults) drive the test-time environment, with the options'
    assert seen == {"device": "cpu", "threshold": 0.2, "steps": 5, "clip": 3.0, "candidates": 4, "sampling": "max",
                    "actor": "actor", "policy_every": 1, "sets_per_step": 3, "confidence": 0.9,
                    "state_threshold": 0.3}  # the state's scale is the checkpoint's, not the evaluation threshold
    assert s["steps_per_episode"] == 5 and (workdir / "ev/errors.csv").is_file()


def test_task_from():
    assert task_from("line", {"threshold": 0.3}).threshold == 0.3
    assert task_from("line", {"name": "line"}).name == "line"
    with pytest.raises(RlsacError, match="trained for task"):
        task_from("line", {"name": "fundamental"})
    with pytest.raises(RlsacError, match="bad options"):
        task_from("line", {"no_such_option": 1})


def test_train_builds_options_from_params_flags_and_sets(workdir, monkeypatch):
    import rlsac.evaluation.train as real

    got = {}
    fake = types.ModuleType("rlsac.evaluation.train")
    fake.train = lambda options, track=True: got.update(options=options, track=track) or {"out": "ck.pt"}
    fake.check_params = real.check_params  # params.yaml's train section is checked when the file is read
    fake.OWN_SECTIONS = real.OWN_SECTIONS  # which method reads which section (a --set of the other's is refused)
    monkeypatch.setitem(sys.modules, "rlsac.evaluation.train", fake)
    (workdir / "params.yaml").write_text("train:\n  line:\n    seed: 3\n    sac: {actor_lr: 0.1, batch_size: 8}\n")
    r = invoke("train", "--task", "line", "--data", "t.h5", "--out", "ck.pt", "--set", "sac.actor_lr=1e-4",
               "--set", "env.steps_per_episode=7", "--no-tracking")
    assert r.exit_code == 0, r.output
    assert got["track"] is False
    o = got["options"]
    assert o["task"] == "line" and o["data"] == "t.h5" and o["out"] == "ck.pt" and o["seed"] == 3
    assert o["sac"] == {"actor_lr": 1e-4, "batch_size": 8} and o["env"] == {"steps_per_episode": 7}
    assert "resume" not in o and "device" not in o  # flags not given keep the params/conf defaults
    assert_user_error(invoke("train", "--task", "line", "--set", "novalue"), "key=value")


def test_calibrate_lines_tiny(workdir, monkeypatch):
    from rlsac import numerics

    if numerics.mode() == "native":  # the portable mode set MKL_CBWR=COMPATIBLE at `import rlsac`, and needs it
        monkeypatch.delenv("MKL_CBWR", raising=False)
    before = os.environ.get("MKL_CBWR")
    r = invoke("calibrate-lines", "--n-instances", 10, "--n-seeds", 2, "--iterations", 20, "--out", "rep/cal",
               "--no-tracking")
    assert r.exit_code == 0, r.output
    table = pd.read_csv(workdir / "rep/cal.csv")
    assert (table["mAA_min"] <= table["mAA_ours"] + 1e-4).all() and (table["mAA_ours"] <= table["mAA_max"] + 1e-4).all()
    assert table["seeds_within"].isin([0.0, 0.5, 1.0]).all()
    assert table["outlier_rate"].tolist() == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7])
    assert table["mAA_paper"].iloc[0] == pytest.approx(0.870) and table["median_paper"].iloc[-1] == 0.135
    assert np.allclose(table["mAA_diff"], table["mAA_ours"] - table["mAA_paper"], atol=1e-3)
    md = (workdir / "rep/cal.md").read_text()
    assert "| band |" in md and "0.608" in md
    # the line calibration runs MKL on its vendor-independent branch (the same bytes on Intel and AMD CPUs)
    # MKL on its vendor-independent branch while it ran, and the environment put back (tests/conftest.py made this
    # process's first MKL call, so its branch stays the default one)
    assert "(`MKL_CBWR=COMPATIBLE`" in md and os.environ.get("MKL_CBWR") == before
    # the default noise model is not listed (the committed report predates the knob and keeps its bytes); another is
    assert "| noise |" not in md
    gauss = commands.calibration_markdown(table, {"band": 0.03, "noise": "gaussian"}, 20, [1], "rlsac calibrate-lines")
    assert "| noise | gaussian |" in gauss
    # a user's own MKL_CBWR is named as such, not as the vendor-independent branch
    user = commands.calibration_markdown(table, {"band": 0.03}, 20, [1], "rlsac calibrate-lines", mkl_cbwr="AVX2")
    assert "`MKL_CBWR=AVX2` (set by the user), not on its vendor-independent branch" in user
    assert "MKL runs on its vendor-independent branch" not in user


def test_calibration_table():
    t = commands.calibration_table({0.1: (0.9, 0.04), 0.7: (0.5, 0.2)})
    assert t["mAA_diff"].tolist() == pytest.approx([0.03, -0.108])
    assert t["median_diff"].tolist() == pytest.approx([-0.009, 0.065])
    assert "mAA_oracle" not in t
    t = commands.calibration_table({0.1: (0.9, 0.04)}, oracle={0.1: (0.95, 0.03)})
    assert t["mAA_oracle"].tolist() == [0.95] and t["median_oracle"].tolist() == [0.03]
    t = commands.calibration_table({0.1: (0.905, 0.04)}, per_seed={0.1: [0.86, 0.95]})
    assert t["mAA_sd"].tolist() == pytest.approx([0.0636396]) and t["seeds_within"].tolist() == [0.5]
    assert t["mAA_min"].tolist() == [0.86] and t["mAA_max"].tolist() == [0.95]


def test_portable_blas_sets_compatible_inside_keeps_a_users_value_and_puts_the_environment_back(monkeypatch):
    from rlsac.numerics import portable_blas

    monkeypatch.delenv("MKL_CBWR", raising=False)
    with portable_blas() as pinned:
        assert pinned is True and os.environ["MKL_CBWR"] == "COMPATIBLE"
    assert "MKL_CBWR" not in os.environ
    monkeypatch.setenv("MKL_CBWR", "AVX2")
    with portable_blas() as pinned:
        assert pinned is False and os.environ["MKL_CBWR"] == "AVX2"
    assert os.environ["MKL_CBWR"] == "AVX2"


def test_plot_help_names_every_key_and_its_error_the_docs_names(workdir):
    """`rlsac plot --help` listed no key (issue #63 item 7); an unknown figure's error named the file names, not the
    short ones docs/commands.md uses (`which=line`, `folds`)."""
    from rlsac.reports.figures import DEFAULTS, SHORT

    r = invoke("plot", "--help")
    assert r.exit_code == 0
    text = " ".join(r.output.split())
    missing = [k for k in DEFAULTS if not re.search(rf"(?<!\w){k}(?!\w)", text)]  # a whole word each
    assert not missing, missing
    bad = invoke("plot", "--set", "which=line_stepz", "--no-tracking")
    assert_user_error(bad, "unknown figure 'line_stepz'", *(f"{k} ({v})" for k, v in SHORT.items()))
    assert not os.listdir(workdir)
