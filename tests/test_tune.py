"""Issue #26: settings chosen per fold on validation pairs only (rlsac.evaluation.tune), the pixel thresholds and the
SNN pre-filter that evaluate applies, and the guards that keep test pairs out of tuning."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from rlsac.errors import RlsacError
from rlsac.evaluation import tune
from rlsac.evaluation.evaluate import EvalOptions, check_options, mlflow_name, run_name
from rlsac.tasks import get_task, opencv_threshold, prefiltered, task_for


def _conf(**kw):
    return {**tune.DEFAULTS, **kw}


def test_px_thresholds_in_each_task_unit():
    assert get_task("fundamental").px_thresholds(2.0) == (4.0, 2.0)  # squared Sampson error (px^2), OpenCV px
    assert get_task("fundamental", residual="sampson").px_thresholds(1.5) == (1.5, 1.5)
    t, cv = get_task("essential").px_thresholds(0.92)  # f = 920 px: normalised units
    assert t == pytest.approx(0.001) and cv == pytest.approx(0.001)
    o = EvalOptions(task="fundamental", method="ransac", data="", threshold_px=0.5)
    assert task_for(o).threshold == 0.25
    assert opencv_threshold(o, task_for(o)) == 0.5
    plain = o.replace(threshold_px=None)
    assert opencv_threshold(plain, task_for(plain)) == 0.75  # the tutorial's default


def test_prefilter_clears_the_mask_above_the_ratio():
    task = get_task("fundamental")
    feats = torch.zeros(1, 4, 261)
    feats[0, :, 4] = torch.tensor([0.5, 0.8, 0.81, 0.95])
    batch = {"features": feats, "coords": torch.zeros(1, 4, 4), "mask": torch.tensor([[True, True, True, False]])}
    assert prefiltered(task, batch, 0.8)["mask"].tolist() == [[True, True, False, False]]
    assert prefiltered(task, batch, None) is batch


CHECKPOINT = str(Path(__file__).resolve().parents[1] / "checkpoints/folds/hard/fountain/rlsac.pt")


def test_evaluate_options_check_the_new_settings():
    base = {"task": "fundamental", "method": "ransac", "data": __file__}
    o = check_options({**base, "threshold_px": "0.5", "prefilter": 0.8})
    assert (o.threshold_px, o.prefilter, o.iterations, o.out_dir) == (0.5, 0.8, 1000, f"reports/eval/{run_name(o)}")
    # the MLflow run's name tells the sampling ablation's rows apart (issue #63 item 5: a list that reads unopened)
    names = {mlflow_name(check_options({**base, "method": "rlsac", "checkpoint": CHECKPOINT, "sampling": s}))
             for s in ("max", "prob")}
    assert len(names) == 2 and any(" rlsac prob " in n for n in names), names
    with pytest.raises(dataclasses.FrozenInstanceError):  # one object, checked once: nobody changes it after
        o.threshold_px = 1e300
    for bad in ({"threshold_px": 0}, {"prefilter": 1.5}, {"prefilter": 0}):
        with pytest.raises(RlsacError):
            check_options({**base, **bad})
    with pytest.raises(RlsacError, match="pixel threshold"):
        check_options({"task": "line", "method": "ransac", "data": __file__, "threshold_px": 1.0})


def test_search_full_grid_then_knobs_and_edge_extension():
    """A score peaked at threshold 2.0 px, pre-filter 0.8, temperature 0.05: the grid [0.5, 1.0] must be extended
    upward (1.5, 2.25 -> back below) and the knob chosen after the pair."""
    seen = []

    def run(o):
        seen.append(o)
        t, f = o["threshold_px"], o["prefilter"] or 1.0
        v = 1 - abs(t - 2.0) - abs(f - 0.8) - abs(o.get("guide_temperature", 0.1) - 0.05)
        return {"mAA": v, "mAA_R": v, "mAA_t": v}

    c = _conf(threshold_px=[0.5, 1.0], prefilter=[0.8, 1.0], extend=3, guide_temperature=[0.02, 0.05, 0.1])
    best, points = tune.search(run, {"guide_temperature": 0.1}, c, ["guide_temperature"])
    assert best == {"threshold_px": 2.25, "prefilter": 0.8, "guide_temperature": 0.05}
    assert sorted({p["settings"]["threshold_px"] for p in points}) == [0.5, 1.0, 1.5, 2.25, 3.375]
    assert all(o["prefilter"] is None for o in seen if o.get("prefilter") is None)  # 1.0 = no pre-filter
    assert any(o["prefilter"] is None for o in seen)
    assert len(points) == len({json.dumps(p["settings"], sort_keys=True) for p in points})  # each point once


def test_search_breaks_ties_by_grid_order_and_stops_without_extension():
    c = _conf(threshold_px=[0.5, 1.0, 2.0], prefilter=[1.0], extend=0)
    best, points = tune.search(lambda o: {"mAA": 0.5, "mAA_R": 0.5, "mAA_t": 0.5}, {}, c, [])
    assert best == {"threshold_px": 0.5, "prefilter": 1.0} and len(points) == 3


def test_lo_sigma_goes_into_the_lo_conf():
    o = tune.as_options({"threshold_px": 1.0, "prefilter": 1.0, "lo_sigma_scale": 0.25}, {"score": "magsac"})
    assert o == {"threshold_px": 1.0, "prefilter": None, "lo": {"score": "magsac", "sigma_scale": 0.25}}


def test_conf_rejects_unknown_and_bad_values():
    assert tune.conf({})["iterations"] == 1000
    for bad in ({"nope": 1}, {"threshold_px": []}, {"prefilter": [1.2]}, {"iterations": 0}, {"sets_per_step": ["x"]}):
        with pytest.raises(RlsacError):
            tune.conf({"tuning": bad})


TRAIN, TEST = ["castle-P19", "fountain-P11"], ["entry-P10"]


def test_settings_that_saw_a_test_pair_are_refused():
    tune.check_scenes(["castle-P19"], TRAIN, TEST, "val.h5")
    with pytest.raises(RlsacError, match="test scene"):  # the fold's test file given as validation
        tune.check_scenes(["entry-P10"], TRAIN, TEST, "test.h5")
    with pytest.raises(RlsacError, match="test scene"):  # pooled validation pairs of every fold
        tune.check_scenes(["castle-P19", "entry-P10", "fountain-P11"], TRAIN, TEST, "pooled.h5")
    rec = {"regime": "hard", "fold": "entry", "row": "magsac", "chosen": {"threshold_px": 1.0},
           "val_scenes": ["castle-P19"]}
    assert tune.check_record(rec, "r.json", "hard", "entry", "magsac", TRAIN, TEST) == {"threshold_px": 1.0}
    with pytest.raises(RlsacError, match="test scene"):
        tune.check_record({**rec, "val_scenes": ["castle-P19", "entry-P10"]}, "r.json", "hard", "entry", "magsac",
                          TRAIN, TEST)
    with pytest.raises(RlsacError, match="fold"):  # another fold's record
        tune.check_record({**rec, "fold": "castle"}, "r.json", "hard", "entry", "magsac", TRAIN, TEST)
    with pytest.raises(RlsacError, match="row"):
        tune.check_record(rec, "r.json", "hard", "entry", "usac", TRAIN, TEST)


def test_scenes_of_reads_the_pair_scenes():
    assert tune.scenes_of({"scene": np.array(["b", "a", "b"])}) == ["a", "b"]


def test_search_takes_a_second_round_when_the_prefilter_moves():
    """The best threshold depends on the pre-filter (0.5 px with SNN < 0.8, 2 px without it, which scores higher):
    round one finds 0.5 px at the start filter 0.8 and then prefers no filter; round two moves the threshold."""
    def run(o):
        f = o["prefilter"] or 1.0
        base, want = (1.0, 0.5) if f == 0.8 else (3.0, 2.0)
        v = base - abs(o["threshold_px"] - want)
        return {"mAA": v, "mAA_R": v, "mAA_t": v}

    c = _conf(threshold_px=[0.5, 1.0, 2.0, 3.0], prefilter=[0.8, 1.0], extend=0, rounds=2)
    best, points = tune.search(run, {}, c, [])
    assert best == {"threshold_px": 2.0, "prefilter": 1.0}
    one, _ = tune.search(run, {}, {**c, "rounds": 1}, [])  # one round keeps the first pass's threshold
    assert one == {"threshold_px": 0.5, "prefilter": 1.0}
    # 4 thresholds at 0.8, the filter pass (1 new point), 3 new thresholds at 1.0 (0.5 px at 1.0 already scored)
    assert len(points) == 4 + 1 + 3


def test_opencv_hypotheses_bound_follows_the_stopping_rule():
    from rlsac.estimation.baselines import stop_bound

    # w = 0.5, m = 8, p = 0.999: log(0.001) / log(1 - 2^-8) = 1764.9 -> 1765
    assert stop_bound(75, 150, 8, 0.999, 5000) == 1765
    assert stop_bound(75, 150, 8, 0.999, 1000) == 1000  # capped at the budget
    assert stop_bound(150, 150, 8, 0.999, 1000) == 1  # every point an inlier: the first set suffices
    assert stop_bound(0, 150, 8, 0.999, 1000) == 1000  # no inliers: the whole budget
    assert stop_bound(1, 150, 8, 0.999, 1000) == 1000  # w^m underflows (1 - w^m == 1.0): the whole budget
    # w = 0.9, m = 7: log(0.001) / log(1 - 0.9^7) = 10.6 -> 11
    assert stop_bound(135, 150, 7, 0.999, 1000) == 11


def test_refit_output_option_reaches_the_task_and_only_where_it_exists():
    essential = EvalOptions(task="essential", method="ransac", data="")
    assert task_for(essential.replace(refit_output=True)).refit_output is True
    assert task_for(essential).refit_output is False  # the task's default
    with pytest.raises(RlsacError, match="no refit_output"):
        task_for(essential.replace(task="fundamental", refit_output=True))
    assert tune.conf({"tuning": {"refit_output": [True, False]}})["refit_output"] == [True, False]
    for bad in ([], ["true"], True):
        with pytest.raises(RlsacError):
            tune.conf({"tuning": {"refit_output": bad}})


def test_prefilter_optimum_on_the_strict_edge_extends_the_grid():
    """mAA peaks at SNN < 0.65, below the tutorial's grid: the filter grid grows by 0.05 until the peak is inside."""
    def run(o):
        v = 1.0 - abs((o["prefilter"] or 1.0) - 0.65) - abs(o["threshold_px"] - 1.0)
        return {"mAA": v, "mAA_R": v, "mAA_t": v}

    c = _conf(threshold_px=[0.5, 1.0, 2.0], prefilter=[0.75, 0.8, 0.85, 1.0], extend=3, rounds=2)
    best, points = tune.search(run, {}, c, [])
    assert best == {"threshold_px": 1.0, "prefilter": 0.65}
    assert sorted({p["settings"]["prefilter"] for p in points}) == [0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 1.0]
    capped, _ = tune.search(run, {}, {**c, "extend": 1}, [])  # one extension only: stops at 0.7
    assert capped["prefilter"] == 0.7
