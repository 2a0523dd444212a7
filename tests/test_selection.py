"""Checkpoint selection measured (issue #27, item 3): the actors validation cannot tell apart, and the report's kept vs
last comparison on known errors (the replay itself runs in tests/test_folds.py's end-to-end test)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from rlsac.errors import RlsacError
from rlsac.experiments import selection
from rlsac.reports import selection as report


def test_candidates_are_the_steps_within_the_tie_of_the_kept_one():
    hist = [{"step": 100, "charts/val_inlier_ratio": 0.40}, {"step": 200, "charts/val_inlier_ratio": 0.435},
            {"step": 300, "charts/val_inlier_ratio": 0.44}]
    assert selection.candidates(hist, 300, 0.01) == [200, 300]
    assert selection.candidates(hist, 300, 0.0) == [300]
    assert selection.candidates(hist, 300, 0.05) == [100, 200, 300]
    with pytest.raises(RlsacError, match="kept step 400"):
        selection.candidates(hist, 400, 0.01)


def _record(root: Path, fold: str, run: str, kept: int, ratios: dict[int, float], solved: dict[int, bool]) -> None:
    """A fold_select record: two validated steps, 4 test pairs at 100 iterations, each step solving all or none."""
    hist = [{"step": s, "charts/val_inlier_ratio": r, "charts/val_mAA": 0.5} for s, r in ratios.items()]
    steps = sorted(ratios)
    rec = {"regime": "hard", "fold": fold, "model": run, "kept_step": kept, "last_step": steps[-1], "steps": steps,
           "candidates": selection.candidates(hist, kept, 0.01), "history": hist, "iterations": [100], "tie": 0.01}
    d = root / "hard" / fold
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{run}.json").write_text(json.dumps(rec))
    pd.DataFrame([{"step": s, "iterations": 100, "scene": fold, "pair": f"000{i}", "err_R": 0.5 if solved[s] else 20.0,
                   "err_t": 0.5} for s in steps for i in range(4)]).to_csv(d / f"{run}.csv", index=False)


def test_the_report_sets_kept_against_last_over_seeds_and_measures_the_tied_spread(tmp_path):
    """Seed 0 on fold a kept step 1 (solves all 4 pairs) over the tied last step 2 (solves none); every other run kept
    its last actor, which solves all. Kept mAA_R 1.0 for both seeds, last 0.5 and 1.0: kept - last = +0.25 pooled over
    the two folds; one run of four has tied candidates, their spread 1.0, the kept one the better."""
    root = tmp_path / "selection"
    _record(root, "a", "rlsac", 1, {1: 0.50, 2: 0.495}, {1: True, 2: False})
    _record(root, "b", "rlsac", 2, {1: 0.30, 2: 0.50}, {1: False, 2: True})
    _record(root, "a", "rlsac-s1", 2, {1: 0.30, 2: 0.50}, {1: False, 2: True})
    _record(root, "b", "rlsac-s1", 2, {1: 0.30, 2: 0.50}, {1: False, 2: True})
    got = report.build(root, tmp_path)
    assert sorted(got["files"]) == sorted([str(tmp_path / "selection.md"), str(tmp_path / "selection.csv")])
    md = (tmp_path / "selection.md").read_text()
    row = next(line for line in md.splitlines() if "| mAA_R" in line)
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[:6] == ["rlsac", "100", "mAA_R", "2", "4", "3/4"]
    assert cells[6] == "1.000 ± 0.000" and cells[7] == "0.750 ± 0.354" and cells[8].startswith("+0.250 [")
    assert cells[9:] == ["1", "1.000 / 1.000", "1/1"]
    t = next(line for line in md.splitlines() if "| mAA_t" in line)
    assert "+0.000 [+0.000, +0.000]" in t  # t: every actor solves every pair
    per_run = pd.read_csv(tmp_path / "selection.csv")
    assert len(per_run) == 8 and per_run["kept"].sum() == 4 and per_run["candidate"].sum() == 5


def test_the_report_refuses_a_record_that_is_not_one(tmp_path):
    d = tmp_path / "selection" / "hard" / "a"
    d.mkdir(parents=True)
    (d / "rlsac.json").write_text(json.dumps({"fold": "a"}))
    pd.DataFrame({"step": [1]}).to_csv(d / "rlsac.csv", index=False)
    with pytest.raises(RlsacError, match="not a selection record"):
        report.build(tmp_path / "selection", tmp_path)
    assert report.build(tmp_path / "none", tmp_path) == {"files": []}


def test_every_shipped_checkpoint_says_how_it_was_kept(tmp_path):
    from rlsac.rl import checkpoint

    root = tmp_path / "checkpoints"
    checkpoint.write(root / "folds" / "a.pt", {"actor": {}, "selection": "inlier_ratio", "step": 200,
                                                "history": [{"step": 100}, {"step": 200}, {"step": 300}]})
    checkpoint.write(root / "old.pt", {"actor": {}, "step": 1000})
    checkpoint.write(root / "folds" / "a.state.pt", {"not": "a checkpoint"})  # a training state: left out
    got = report.shipped(root)
    assert list(got["checkpoint"]) == [str(root / "folds" / "a.pt"), str(root / "old.pt")]
    assert got.iloc[0]["kept by"].startswith("best validation inlier ratio") and got.iloc[0]["kept step"] == 200
    assert got.iloc[0]["validated steps"] == "100 200 300"
    assert got.iloc[1]["kept by"].startswith("not recorded") and got.iloc[1]["validated steps"] == "–"
    _record(tmp_path / "selection", "a", "rlsac", 2, {1: 0.3, 2: 0.5}, {1: False, 2: True})
    report.build(tmp_path / "selection", tmp_path, root)
    assert "## How every shipped checkpoint was kept" in (tmp_path / "selection.md").read_text()


# ------------------------------------------------------------------ rlsac select: a model of one data file (lines)


def test_first_best_is_the_step_a_training_keeping_that_score_keeps():
    hist = [{"step": 1, "s": 0.2}, {"step": 2, "s": 0.5}, {"step": 3, "s": 0.5}, {"step": 4, "s": 0.1}]
    assert selection.first_best(hist, "s") == 2  # a later actor is kept only when strictly better


@pytest.fixture(scope="module")
def line_run(tmp_path_factory):
    """A tiny line model kept by validation mAA (validated at steps 20 and 40) and its evaluation on a test file."""
    from test_cli import invoke

    d = tmp_path_factory.mktemp("select")
    old = Path.cwd()
    os.chdir(d)
    try:
        for name, n, seed in (("tr", 48, 1), ("va", 16, 2), ("te", 24, 3)):
            assert invoke("synth-lines", "--n-instances", n, "--seed", seed, "--out", f"{name}.h5",
                          "--no-tracking").exit_code == 0
        r = invoke("train", "--task", "line", "--data", "tr.h5", "--val-data", "va.h5", "--out", "m.pt", "--set",
                   "sac.total_steps=40", "--set", "sac.learning_starts=16", "--set", "sac.num_envs=4", "--set",
                   "val_every=20", "--set", "val_instances=16", "--set", "val_iterations=20", "--set",
                   "selection=val_mAA", "--no-tracking")
        assert r.exit_code == 0, r.output
        r = invoke("evaluate", "--task", "line", "--method", "rlsac", "--checkpoint", "m.pt", "--data", "te.h5",
                   "--iterations", 20, "--out-dir", "ev", "--no-tracking")
        assert r.exit_code == 0, r.output
    finally:
        os.chdir(old)
    return d


def _select(*extra):
    from test_cli import invoke

    return invoke("select", "--checkpoint", "m.pt", "--data", "te.h5", "--kept-eval", "ev", "--iterations", 20,
                  "--out", "sel/o0.5-m", "--no-tracking", *extra)


def test_select_replays_the_training_and_tests_every_validated_actor(line_run, monkeypatch):
    monkeypatch.chdir(line_run)
    r = _select()
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (line_run / "sel").iterdir()) == ["o0.5-m.csv", "o0.5-m.json"]  # a stem, not a suffix
    rec = json.loads((line_run / "sel/o0.5-m.json").read_text())
    kept = torch.load(line_run / "m.pt", weights_only=False)
    assert rec["steps"] == [20, 40] and rec["last_step"] == 40 and rec["kept_step"] == kept["step"]
    assert rec["reproduced"] is True and rec["selection"] == "val_mAA" and rec["score"] == "charts/val_mAA"
    # the replay's validation history is the training's own
    assert [h["step"] for h in rec["history"]] == [h["step"] for h in kept["history"]]
    assert [h["charts/val_mAA"] for h in rec["history"]] == [h["charts/val_mAA"] for h in kept["history"]]
    assert rec["inlier_ratio_step"] == selection.first_best(kept["history"], "charts/val_inlier_ratio")
    assert rec["kept_step"] in rec["candidates"]
    # the kept actor's test result is its committed evaluation's, instance for instance
    ev = json.loads((line_run / "ev/summary.json").read_text())
    assert rec["test"][str(rec["kept_step"])]["mAA"] == ev["mAA"]
    errs = pd.read_csv(line_run / "sel/o0.5-m.csv")
    assert list(errs.columns) == ["step", "instance", "err_deg"] and len(errs) == 2 * 24
    own = pd.read_csv(line_run / "ev/errors.csv")["err_deg"].to_numpy()
    assert errs.loc[errs["step"] == rec["kept_step"], "err_deg"].to_numpy() == pytest.approx(own, rel=1e-5)
    other = errs.loc[errs["step"] != rec["kept_step"], "err_deg"].to_numpy()
    assert not np.allclose(other, own)  # another actor, another result


def test_select_refuses_a_checkpoint_its_replay_does_not_give(line_run, monkeypatch, tmp_path):
    from test_cli import assert_user_error

    for name in ("tr.h5", "va.h5", "te.h5", "m.pt", "ev"):
        (shutil.copytree if (line_run / name).is_dir() else shutil.copy)(line_run / name, tmp_path / name)
    monkeypatch.chdir(tmp_path)
    ck = torch.load("m.pt", weights_only=False)
    name = next(iter(ck["actor"]))
    ck["actor"][name] = ck["actor"][name] + 1e-3  # another actor under the same options
    torch.save(ck, "m.pt")
    assert_user_error(_select(), "does not give the kept actor")
    assert not (tmp_path / "sel").exists()


def test_select_refuses_an_evaluation_that_is_not_the_kept_actors(line_run, monkeypatch, tmp_path):
    from test_cli import assert_user_error

    monkeypatch.chdir(line_run)
    shutil.copytree("ev", tmp_path / "ev2")
    summ = json.loads((tmp_path / "ev2/summary.json").read_text())
    (tmp_path / "ev2/summary.json").write_text(json.dumps({**summ, "mAA": summ["mAA"] + 0.01}))
    from test_cli import invoke

    r = invoke("select", "--checkpoint", "m.pt", "--data", "te.h5", "--kept-eval", tmp_path / "ev2", "--iterations",
               20, "--out", tmp_path / "t", "--no-tracking")
    assert_user_error(r, "is not the committed evaluation's")
    assert not list(tmp_path.glob("t.*"))


def test_select_bad_input_fails_before_the_replay(line_run, monkeypatch, tmp_path):
    from test_cli import assert_user_error

    monkeypatch.chdir(line_run)
    assert_user_error(_select("--kept-eval", tmp_path), "no errors.csv")
    assert_user_error(_select("--iterations", 30), "evaluated at 20 iterations, not 30")
    assert_user_error(_select("--tie", -1), "tie")
    from test_cli import invoke

    r = invoke("select", "--checkpoint", "m.pt", "--data", "va.h5", "--kept-eval", "ev", "--iterations", 20, "--out",
               tmp_path / "t", "--no-tracking")
    assert_user_error(r, "not of m.pt on va.h5")
    r = invoke("select", "--checkpoint", "m.pt", "--data", "te.h5", "--kept-eval", "ev", "--iterations", 20, "--out",
               "/proc/nope/t", "--no-tracking")
    assert_user_error(r, "cannot write")
    (tmp_path / "ng.pt").write_bytes(b"")
    ck = torch.load("m.pt", weights_only=False)
    torch.save({**ck, "kind": "ngransac"}, tmp_path / "ng.pt")
    r = invoke("select", "--checkpoint", tmp_path / "ng.pt", "--data", "te.h5", "--kept-eval", "ev", "--iterations",
               20, "--out", tmp_path / "t", "--no-tracking")
    assert_user_error(r, "not an RLSAC checkpoint")
    assert not list(tmp_path.glob("t.*")) and not (line_run / "sel2").exists()


def _line_record(root: Path, seed: int, kept: int, ratios: dict[int, float], vals: dict[int, float],
                 solved: dict[int, int]) -> None:
    """An `rlsac select` record of test_o0.7.h5: 4 test instances, step s solving the first solved[s] of them."""
    hist = [{"step": s, "charts/val_inlier_ratio": ratios[s], "charts/val_mAA": vals[s]} for s in sorted(ratios)]
    steps = sorted(ratios)
    rec = {"data": "data/lines/test_o0.7.h5", "seed": seed, "kept_step": kept, "last_step": steps[-1], "steps": steps,
           "inlier_ratio_step": selection.first_best(hist, "charts/val_inlier_ratio"), "tie": 0.005,
           "candidates": selection.candidates(hist, kept, 0.005, "charts/val_mAA"), "history": hist}
    d = root / "lines"
    d.mkdir(parents=True, exist_ok=True)
    (d / f"o0.7-s{seed}.json").write_text(json.dumps(rec))
    pd.DataFrame([{"step": s, "instance": i, "err_deg": 0.01 if i < solved[s] else 5.0} for s in steps
                  for i in range(4)]).to_csv(d / f"o0.7-s{seed}.csv", index=False)


def test_the_line_section_sets_kept_against_last_and_the_inlier_ratio_pick(tmp_path):
    """Seed 1 kept step 1 (val mAA 0.6, solves 4/4) over its last step 2 (0.5; solves 2/4), whose inlier ratio is the
    higher; seed 2 kept its last step (solves 4/4; step 1 solves 0/4 and ties it on validation mAA). Kept mAA 1.0 in
    both; last 0.5 and 1.0: kept - last = +0.25; the inlier-ratio pick is step 2 in both: pick - kept = -0.25."""
    root = tmp_path / "selection"
    _line_record(root, 1, 1, {1: 0.30, 2: 0.31}, {1: 0.6, 2: 0.5}, {1: 4, 2: 2})
    _line_record(root, 2, 2, {1: 0.30, 2: 0.31}, {1: 0.598, 2: 0.6}, {1: 0, 2: 4})
    got = report.build(root, tmp_path)
    assert sorted(got["files"]) == sorted(str(tmp_path / f) for f in ("selection.md", "selection_lines.csv"))
    md = (tmp_path / "selection.md").read_text()
    assert md.startswith("# Checkpoint selection measured") and "## Line models (Table 1)" in md
    row = next(line for line in md.splitlines() if line.startswith("| test_o0.7"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[:5] == ["test_o0.7", "1 2", "1/2", "1.000 ± 0.000", "0.750 ± 0.354"]
    assert cells[5].startswith("+0.250 [") and cells[6] == "1/2" and cells[7].startswith("-0.250 [")
    assert cells[8:] == ["1", "1.000 / 1.000", "1/1"]
    per_run = pd.read_csv(tmp_path / "selection_lines.csv")
    assert len(per_run) == 4 and per_run["kept"].sum() == 2 and per_run["inlier-ratio pick"].sum() == 2
    assert per_run["test mAA"].tolist() == [1.0, 0.5, 0.0, 1.0]


def test_the_line_section_refuses_a_record_that_is_not_one(tmp_path):
    d = tmp_path / "selection" / "lines"
    d.mkdir(parents=True)
    (d / "x.json").write_text(json.dumps({"data": "t.h5"}))
    (d / "x.csv").write_text("step,instance,err_deg\n1,0,0.1\n")
    with pytest.raises(RlsacError, match="not a line selection record"):
        report.build(tmp_path / "selection", tmp_path)
