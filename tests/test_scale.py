"""The training-scale study (issue #46): its protocol's checks, the runner's refusals, the report on known values."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.errors import RlsacError
from rlsac.layout.scale_layout import arm_final_steps, protocol
from rlsac.reports import scale as report

SCALE = {"fold": "castle", "regime": "hard", "pool": 1000, "arms": ["fixed", "redraw"], "seeds": [0, 1],
         "steps": [30, 10], "iterations": 100, "final_iterations": 1000, "settings_from": "uniform",
         "val_every": 10, "legs": [10, 30], "final_steps": [30], "synthetic_pairs": 20,
         "arm_steps": {}, "pretrain": {"steps": 10, "pairs": 20}}


def test_protocol_checks_every_key():
    from rlsac.layout.scale_layout import ARMS

    assert set(report.ARM_LABEL) == set(ARMS) and set(report.BASE_ARM) < set(ARMS)  # the report names every arm
    s = protocol({"scale": SCALE})
    assert s["steps"] == [10, 30]  # sorted: the largest is the run's length
    with pytest.raises(RlsacError, match="each one of fixed, redraw, pretrain"):
        protocol({"scale": {**SCALE, "arms": ["pretrained"]}})
    with pytest.raises(RlsacError, match="missing \\['val_every'\\]"):
        protocol({"scale": {k: v for k, v in SCALE.items() if k != "val_every"}})
    with pytest.raises(RlsacError, match="scale.arm_steps"):
        protocol({"scale": {**SCALE, "arm_steps": {"fixed": 20}}})  # not a step of the study
    short = protocol({"scale": {**SCALE, "arms": ["fixed", "redraw", "pretrain"], "arm_steps": {"pretrain": 10}}})
    assert arm_final_steps(short, "pretrain") == [10] and arm_final_steps(short, "fixed") == [30]  # each arm's last
    with pytest.raises(RlsacError, match="scale.pretrain must be"):
        protocol({"scale": {**SCALE, "pretrain": {"steps": 0, "pairs": 20}}})
    with pytest.raises(RlsacError, match="scale.seeds must be"):
        protocol({"scale": {**SCALE, "seeds": []}})


def test_the_command_refuses_a_run_it_does_not_know(workdir):
    (workdir / "params.yaml").write_text(json.dumps({"scale": SCALE}))
    res = CliRunner().invoke(cli, ["scale", "--stage", "train", "--arm", "fixed", "--seed", "7", "--no-tracking"])
    assert res.exit_code == 2 and "error:" in res.output


def _write(d, err_r, err_t, scenes):
    d.mkdir(parents=True)
    pd.DataFrame({"instance": range(len(err_r)), "scene": scenes, "pair": [f"p{i}" for i in range(len(err_r))],
                  "err_R": err_r, "err_t": err_t}).to_csv(d / "errors.csv", index=False)
    (d / "summary.json").write_text(json.dumps({"n": len(err_r)}))


def test_the_report_pairs_seeds_and_pairs_on_known_values(workdir):
    """Uniform fails every pair (180 deg); RLSAC is exact on every pair (fixed arm) or on half of them (redraw arm,
    one seed each way): the differences are +1 and +0.5 on mAA, with intervals that say so."""
    m = 8
    scenes = ["castle-P19"] * 4 + ["castle-P30"] * 4
    ev = workdir / "reports" / "eval"
    for c in ("uniform", "guided"):
        for it in (100, 1000):
            _write(ev / "folds/hard/castle" / c / f"i{it}", [180.0] * m, [90.0] * m, scenes)
    for seed in (0, 1):
        for it, steps in ((100, (10, 30)), (1000, (30,))):
            for step in steps:
                _write(ev / f"scale/castle/i{it}/fixed-s{seed}/step{step}", [0.0] * m, [0.0] * m, scenes)
                half = [0.0, 180.0] * (m // 2) if seed == 0 else [180.0, 0.0] * (m // 2)
                _write(ev / f"scale/castle/i{it}/redraw-s{seed}/step{step}", half, half, scenes)
    for seed in (0, 1):  # validation at the test's settings: fixed exact at step 30 only, redraw never
        for arm, step, err in (("fixed", 10, 180.0), ("fixed", 30, 0.0), ("redraw", 10, 180.0), ("redraw", 30, 180.0)):
            _write(ev / f"scale/castle/val-i100/{arm}-s{seed}/step{step}", [err] * 4, [0.0] * 4, ["castle-P19"] * 4)
    got = report.build({"scale": SCALE}, ev, workdir / "reports", workdir)
    df = pd.read_csv(workdir / "reports" / "scale.csv")
    assert len(df) == 2 * 2 + 2  # two steps at 100 hypotheses, the last one at 1000, per arm
    fixed = df[(df.arm == "fixed") & (df.step == 30) & (df.iterations == 1000)].iloc[0]
    assert fixed["mAA_R"] == 1.0 and fixed["vs_uniform_R"] == 1.0 and fixed["vs_uniform_R_lo"] == 1.0
    red = df[(df.arm == "redraw") & (df.step == 30)].iloc[0]
    assert red["vs_guided_t"] == pytest.approx(0.5) and red["vs_guided_t_lo"] < 0.5 < red["vs_guided_t_hi"]
    assert red["sd_R"] == 0.0 and not got["missing"]
    assert red["vs_base_R"] == pytest.approx(-0.5) and red["vs_base_R_hi"] < 0  # redraw - fixed: half the pairs lost
    assert pd.isna(fixed.get("vs_base_R"))  # the fixed arm adds to nothing
    text = (workdir / "reports" / "scale.md").read_text()
    assert "+1.000 [+1.000, +1.000]" in text and (workdir / "reports/scale_curve.png").is_file()
    assert "| fixed | 30 | – | – | 1.000 |" in text and "| redraw | 10 | – | – | 0.000 |" in text
    assert ("(best seed-mean validation mAA, test settings): arm `fixed` at 30 steps (val mAA 1.000; the next best, "
            "arm `fixed` at 10 steps, 0.000; every cell lies within 0.000-1.000)") in text


def test_a_corrupt_result_is_refused_not_read_as_missing(workdir):
    d = workdir / "e"
    _write(d, [1.0, np.nan], [1.0, 2.0], ["a", "a"])
    with pytest.raises(RlsacError, match="not a finite number"):
        report._errors(d, None)
    (d / "summary.json").write_text(json.dumps({"n": 3}))
    _write(workdir / "f", [1.0, 2.0], [1.0, 2.0], ["a", "a"])
    (workdir / "f" / "summary.json").write_text(json.dumps({"n": 3}))
    with pytest.raises(RlsacError, match="truncated"):
        report._errors(workdir / "f", None)


def test_the_positive_control_is_read_into_words():
    """A ratio whose policy reaches the guided sampler's mass says when; one that does not says how far it got."""
    def result(ratio, pis):
        rows = [{"step": 100 * i, "updates": 90 * i, "pi_inliers": p, "mAA_R": 0.5, "mAA_t": 0.4}
                for i, p in enumerate(pis)]
        return {"inlier_ratio": ratio, "controls": {"uniform": {"pi_inliers": ratio, "mAA_R": 0.1, "mAA_t": 0.1},
                                                    "guided (T=0.1)": {"pi_inliers": 0.98, "mAA_R": 1, "mAA_t": 0.9}},
                "curves": [{"seed": 0, "rows": rows}]}

    text = "\n".join(report._positive_control({"results": [result(0.6, [0.6, 0.9, 0.95]), result(0.3, [0.3, 0.4])]}))
    assert "reaches the guided sampler's (0.980) within 0.05 at step 200 (about 180 updates)" in text
    assert "after 100 steps (about 90 updates) the policy's mass on the inliers is 0.400" in text


def test_a_run_is_trained_in_legs_and_resumes_only_its_own_state(workdir, monkeypatch):
    """Legs [10, 30]: the first leg from nothing, the second resuming its state with the conf of a 30-step run; a run
    whose legs are all there trains nothing; a state of another recipe (another seed) is never resumed."""
    import torch

    import rlsac.evaluation.train as train_mod
    import rlsac.experiments.scale as runner
    from rlsac.config import build

    calls = []

    def fake_train(opts, track=True):
        calls.append({k: opts.get(k) for k in ("resume", "snapshot_steps", "ckpt_every")}
                     | {"steps": opts["sac"]["total_steps"]})
        conf = build(train_mod.TrainConf, opts, "train")
        torch.save({"step": conf.sac.total_steps, "conf": train_mod.stored_conf(conf)}, workdir / "final.state.pt")
        torch.save({"step": conf.sac.total_steps}, workdir / "final.pt")
        return {"checkpoint": opts["out"], "steps": conf.sac.total_steps, "best_step": 0, "seconds": 1.0}

    def fake_options(p, params, s, arm, seed, o):
        return {"task": "line", "data": "x.h5", "out": str(workdir / "final.pt"), "seed": seed,
                "sac": {"total_steps": 30}, "snapshot_steps": [10, 20, 30], "ckpt_every": 30}

    monkeypatch.setattr(train_mod, "train", fake_train)
    monkeypatch.setattr(runner, "train_options", fake_options)
    s = protocol({"scale": SCALE})
    runner.train_run({}, {}, s, "fixed", 0, {}, track=False)
    assert calls == [{"resume": False, "snapshot_steps": [10], "ckpt_every": 10, "steps": 10},
                     {"resume": True, "snapshot_steps": [10, 20, 30], "ckpt_every": 30, "steps": 30}]
    calls.clear()
    out = runner.train_run({}, {}, s, "fixed", 0, {}, track=False)
    assert calls == [] and out["steps"] == 30  # every leg there: nothing trained
    runner.train_run({}, {}, s, "fixed", 1, {}, track=False)  # seed 1 finds seed 0's state: starts over
    assert [c["resume"] for c in calls] == [False, True]
    with pytest.raises(RlsacError, match="scale.legs"):
        protocol({"scale": {**SCALE, "legs": [10, 20]}})  # the last leg must end at the largest step
