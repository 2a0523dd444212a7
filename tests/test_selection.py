"""Checkpoint selection measured (issue #27, item 3): the actors validation cannot tell apart, and the report's kept vs
last comparison on known errors (the replay itself runs in tests/test_folds.py's end-to-end test)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from rlsac import selection
from rlsac.errors import RlsacError
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
    from rlsac import checkpoint

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
