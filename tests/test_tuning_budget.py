"""Issue #47 item 7: rows tuned at the test budget (``rlsac folds --tune-iterations``), the re-selection of settings on
bootstrap resamples of the validation pairs (rlsac.evaluation.retune) and the report reports/tuning_budget.md built from
them."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.errors import RlsacError
from rlsac.evaluation import retune, tune
from rlsac.experiments import folds

PARAMS = {
    "folds": {"test": ["castle", "fountain"], "scenes": {"castle": "castle-P19", "fountain": "fountain-P11"},
              "regimes": ["hard"], "pool": {"hard": 1000}, "methods": ["magsac"], "models": [], "train": {},
              "iterations": {"hard": [100, 1000]}, "seed": 0},
    "tuning": {"iterations": 100, "threshold_px": [0.5, 1.0], "prefilter": [1.0], "extend": 0, "rounds": 1},
    "tuning_budget": {"iterations": 1000, "regimes": ["hard"], "methods": ["magsac"], "retune_regime": "hard",
                      "retune_methods": ["magsac"], "retune_draws": 4, "retune_iterations": [1000]},
}


@pytest.fixture
def fold(tmp_path, monkeypatch):
    """A fold castle whose validation pairs are fountain's; evaluate's scoring replaced by a known curve: at 100
    iterations 0.5 px scores best, at 1000 iterations 1.0 px."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(PARAMS))
    d = tmp_path / "data/folds/hard/castle"
    d.mkdir(parents=True)
    for split in ("val", "test"):
        (d / f"{split}.h5").write_bytes(b"")
    from rlsac.tasks import task_class

    data = {"scene": np.array(["fountain-P11"] * 4), "pair": np.array([f"p{i}" for i in range(4)])}
    monkeypatch.setattr(task_class("fundamental"), "read", staticmethod(lambda path: (data, {})))
    calls = []

    def score(o, data, device):
        calls.append(o)
        best = 1.0 if o.iterations == 1000 else 0.5  # o: the checked EvalOptions
        v = 1.0 - abs(o.threshold_px - best)
        return {"mAA": v, "mAA_R": v, "mAA_t": v}, {}

    monkeypatch.setattr("rlsac.evaluation.evaluate.score", score)
    return calls


def _run(**kw):
    return folds.folds({"stage": "tune", "regime": "hard", "fold": "castle", "only": "magsac", "device": "cpu", **kw},
                       track=False)


def test_tune_iterations_tunes_at_that_budget_beside_the_tables_record(fold, tmp_path):
    _run()
    _run(tune_iterations=1000)
    tables = json.loads((tmp_path / "reports/tuning/fundamental/hard/castle/magsac.json").read_text())
    at = json.loads((tmp_path / "reports/tuning_at1000/fundamental/hard/castle/magsac.json").read_text())
    assert (tables["iterations"], tables["chosen"]["threshold_px"]) == (100, 0.5)
    assert (at["iterations"], at["chosen"]["threshold_px"]) == (1000, 1.0)
    assert {o.iterations for o in fold} == {100, 1000} and len(fold) == 4  # two grid points at each budget


def test_evaluate_at_the_tuned_budget_reads_its_record_and_tests_at_it_alone(fold, tmp_path, monkeypatch):
    _run(tune_iterations=1000)
    seen = []
    monkeypatch.setattr("rlsac.evaluation.evaluate.check_all", lambda opts, track: None)
    monkeypatch.setattr("rlsac.evaluation.evaluate.evaluate", lambda o, track: seen.append(o) or {
        "mAA_R": 0.5, "mAA_t": 0.5, "seconds": 0.0})
    folds.folds({"stage": "evaluate", "regime": "hard", "fold": "castle", "only": "magsac", "device": "cpu",
                 "tune_iterations": 1000}, track=False)
    assert [(o["iterations"], o["threshold_px"], o["out_dir"]) for o in seen] == [
        (1000, 1.0, "reports/eval/folds_at1000/hard/castle/magsac/i1000")]


@pytest.mark.parametrize("options, message", [
    ({"tune_iterations": 500}, "not a test budget of regime 'hard'"),
    ({"tune_iterations": 1000, "stage": "data"}, "goes with --stage tune or evaluate"),
])
def test_tune_iterations_refuses_a_budget_the_regime_is_not_tested_at(fold, options, message):
    with pytest.raises(RlsacError, match=message):
        _run(**options)


def test_bad_input_is_one_line_at_exit_2(fold, tmp_path):
    run = CliRunner()
    base = ["folds", "--stage", "tune", "--regime", "hard", "--fold", "castle", "--no-tracking"]
    r = run.invoke(cli, base + ["--tune-iterations", "500"])
    assert r.exit_code == 2 and r.output.startswith("error: ") and r.output.count("\n") == 1
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({**PARAMS, "tuning_budget": {"draws": 3}}))
    (tmp_path / "reports/eval").mkdir(parents=True)
    r = run.invoke(cli, ["table", "--which", "tuning-budget", "--no-tracking"])
    assert r.exit_code == 2 and "unknown params key(s) tuning_budget.['draws']" in r.output


TWO_REGIMES = {**PARAMS, "folds": {**PARAMS["folds"], "regimes": ["easy", "hard"], "pool": {"easy": 0, "hard": 1000},
                                   "iterations": {"easy": [1000], "hard": [100, 1000]}}}


@pytest.mark.parametrize("also, message", [
    ({"regime": "easy", "methods": ["magsac"]}, None),
    ({"regime": "hard", "methods": ["magsac"]}, "other than retune_regime 'hard'"),
    ({"regime": "easy", "methods": ["ransac"]}, r"retune_also.methods \['ransac'\]: not methods"),
    ({"regime": "easy"}, "must be {regime: <a regime>, methods: \\[<rows>\\]}"),
    ({"regime": "easy", "methods": ["magsac"], "iterations": [1000]}, "must be {regime"),
])
def test_retune_also_is_a_second_regimes_rows_at_its_budgets(also, message):
    """issue #62: the easy regime's claims get their selection term from a second set of re-tuning records."""
    params = {**TWO_REGIMES, "tuning_budget": {**TWO_REGIMES["tuning_budget"], "retune_also": also}}
    if message is None:
        assert retune.conf(params)["retune_also"] == also
        return
    with pytest.raises(RlsacError, match=message):
        retune.conf(params)


def test_retune_also_budgets_are_that_regimes_test_budgets():
    budgets = {**TWO_REGIMES["tuning_budget"], "retune_iterations": [100],
               "retune_also": {"regime": "easy", "methods": ["magsac"]}}
    with pytest.raises(RlsacError, match=r"retune_iterations \[100\]: not test budgets of regime 'easy'"):
        retune.conf({**TWO_REGIMES, "tuning_budget": budgets})
    assert retune.conf({**TWO_REGIMES, "tuning_budget": {**budgets, "retune_also": {"regime": "easy",
                                                                                    "methods": []}}})


# --------------------------------------------------------------------------------------------- re-selection


def test_reselect_replays_the_tuning_rule_on_each_resample():
    """Two settings that differ on two pairs only: 1.0 px fits pair 0 (0.5 px misses it), 0.5 px fits pair 5. A draw
    chooses 1.0 px exactly when it holds pair 0 more often than pair 5 (a tie keeps the grid's first point, 0.5 px)."""
    strata = ["a"] * 4 + ["b"] * 4
    err = {0.5: np.full(8, 0.1), 1.0: np.full(8, 0.1)}
    err[0.5][0], err[1.0][5] = 90.0, 90.0
    c = {**tune.DEFAULTS, "threshold_px": [0.5, 1.0], "prefilter": [1.0], "extend": 0, "rounds": 1}
    full, chosen = retune.reselect(lambda s: (err[s["threshold_px"]], err[s["threshold_px"]]), strata, c, [], 50, 3,
                                   10.0)
    assert full == {"threshold_px": 0.5, "prefilter": 1.0}  # one pair each: a tie
    want = [1.0 if (idx == 0).sum() > (idx == 5).sum() else 0.5 for idx in retune.draws(strata, 50, 3)]
    assert [s["threshold_px"] for s in chosen] == want and 0 < want.count(1.0) < 50
    assert all(set(i[:4]) <= {0, 1, 2, 3} and set(i[4:]) <= {4, 5, 6, 7} for i in retune.draws(strata, 50, 3))


# -------------------------------------------------------------------------------------------------- report


def _cell(root, sub, fold, row, errors, it=1000):
    d = root / "eval" / sub / "hard" / fold / row / f"i{it}"
    d.mkdir(parents=True)
    pd.DataFrame({"instance": range(len(errors)), "scene": "s", "pair": [f"p{i}" for i in range(len(errors))],
                  "err_R": errors, "err_t": errors}).to_csv(d / "errors.csv", index=False)
    (d / "summary.json").write_text(json.dumps({"mAA": 0.5, "n_instances": len(errors)}))


def _record(root, name, fold, chosen):
    p = root / name / "fundamental/hard" / fold / "magsac.json"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps({"chosen": chosen, "val_scenes": ["x"], "val": {"mAA": 0.5}}))


def test_report_on_known_values(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(PARAMS))
    r = tmp_path / "reports"
    for fold, tables, at in (("castle", [0.5] * 4, [0.5] * 2 + [90.0] * 2), ("fountain", [0.5] * 4, [0.5] * 4)):
        _cell(r, "folds", fold, "magsac", tables)
        _cell(r, "folds_at1000", fold, "magsac", at)
        _record(r, "tuning", fold, {"threshold_px": 0.5})
        _record(r, "tuning_at1000", fold, {"threshold_px": 1.0 if fold == "castle" else 0.5})
    # re-tuning: one fold, setting 0 meets every threshold on its 2 test pairs, setting 1 none; draws 0, 1, 0, 1
    rec = {"settings": [{"threshold_px": 0.5}, {"threshold_px": 1.0}], "full": 0, "choices": [0, 1, 0, 1],
           "test_scenes": ["s", "s"], "test": {"1000": {"0": {"err_R": [0.1, 0.1], "err_t": [0.1, 0.1]},
                                                        "1": {"err_R": [90, 90], "err_t": [90, 90]}}}}
    path = r / "retune/fundamental/hard/castle/magsac.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(rec))
    out = CliRunner().invoke(cli, ["table", "--which", "tuning-budget", "--no-tracking"])
    assert out.exit_code == 0, out.output
    df = pd.read_csv(r / "tuning_budget.csv")
    a, b = df[df["part"] == "a"].iloc[0], df[df["part"] == "b"].iloc[0]
    assert a["folds re-chosen"] == "1/2" and a["mAA_R tuned@100"] == 1.0 and a["mAA_R tuned@1000"] == 0.75
    assert a["R: @1000 − @100 [95%]"].startswith("-0.250 [")
    assert b["mAA_t: tables"] == 1.0 and b["mAA_t: re-tuned sd [95% range]"] == "0.577 [0.000, 1.000]"
    assert b["draws ≠ tables' choice"] == 0.5 and b["settings chosen"] == 2  # one fold: 2 settings chosen
    md = (r / "tuning_budget.md").read_text()
    assert "the largest move: hard/magsac, R -0.250" in md and "**Decision.**" in md
    rec["choices"] = [0, 7]  # a choice that names no setting
    path.write_text(json.dumps(rec))
    out = CliRunner().invoke(cli, ["table", "--which", "tuning-budget", "--no-tracking"])
    assert out.exit_code == 2 and out.output.startswith("error: ") and "not a re-tuning record" in out.output


def test_a_learned_row_at_the_test_budget_re_chooses_its_threshold_alone():
    """threshold_only: the tables' pre-filter (0.8) stays although 0.75 would score higher, no pre-filter grid point is
    run, and the threshold is re-chosen (1.0 over the tables' 0.5)."""
    c = {**tune.DEFAULTS, "iterations": 1000, "threshold_px": [0.5, 1.0], "prefilter": [0.75, 0.8, 1.0], "extend": 2}
    grid = folds.threshold_only(c, {"chosen": {"threshold_px": 0.5, "prefilter": 0.8}})

    def run(o):
        v = 1.0 - abs(o["threshold_px"] - 1.0) - abs(o["prefilter"] - 0.75)
        return {"mAA": v, "mAA_R": v, "mAA_t": v}

    best, points = tune.search(run, {}, grid, [], on_settings=True)
    assert best == {"threshold_px": 1.0, "prefilter": 0.8}
    assert {pt["settings"]["prefilter"] for pt in points} == {0.8}
    full, _ = tune.search(run, {}, c, [], on_settings=True)  # the tables' rule on this curve moves the pre-filter
    assert full["prefilter"] == 0.75
