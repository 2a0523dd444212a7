"""reports/claims.md (issue #27): verdicts from intervals, models taken over all their training seeds."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.reports import claims


def _maa(errs) -> float:
    """A summary's mAA for the errors (rlsac.evaluation.results requires one in every summary.json)."""
    import numpy as np

    from rlsac.maths.metrics import mAA

    return mAA(np.asarray(errs, float), 0.5)


def _write(root: Path, fold: str, row: str, err_R, err_t, sub: str = "folds", regime: str = "hard", it: int = 100):
    d = root / sub / regime / fold / row / f"i{it}"
    d.mkdir(parents=True)
    n = len(err_R)
    pd.DataFrame({"instance": range(n), "scene": fold, "pair": [f"p{i}" for i in range(n)], "err_R": err_R,
                  "err_t": err_t}).to_csv(d / "errors.csv", index=False)


@pytest.mark.parametrize("kind, lo, hi, expected", [
    ("better", 0.01, 0.05, "supported"), ("better", -0.01, 0.05, "inconclusive"), ("better", -0.05, -0.01,
                                                                                    "not supported"),
    ("worse", -0.05, -0.01, "supported"), ("worse", 0.01, 0.02, "not supported"),
    ("tie", -0.02, 0.02, "supported"), ("tie", -0.05, 0.02, "inconclusive"), ("tie", 0.01, 0.05, "not supported"),
    ("tie", 0.005, 0.02, "supported"),  # practically equal: inside the margin although it excludes 0
])
def test_verdict_from_the_interval(kind, lo, hi, expected):
    assert claims.verdict(kind, lo, hi) == expected


def test_verdict_rejects_an_unknown_kind():
    with pytest.raises(ValueError, match="claim kind"):
        claims.verdict("bigger", 0.0, 1.0)


def test_a_claim_that_holds_for_one_seed_is_inconclusive_over_seeds(tmp_path):
    """rlsac's first seed solves every pair and uniform half of them: on one seed "RLSAC is better" is supported.
    A second seed that solves none turns the seed mean into a tie with an interval across zero: inconclusive."""
    ev = tmp_path / "eval"
    for fold in ("a", "b"):
        _write(ev, fold, "rlsac", [0.5] * 6, [0.5] * 6)
        _write(ev, fold, "uniform", [0.5, 20.0] * 3, [0.5, 20.0] * 3)
    claim = claims.Claim("RLSAC beats uniform", "test", "folds", "hard", 100, "rlsac", "uniform", "better")
    got = claims.build(ev, tmp_path / "one", (claim,))
    one = pd.read_csv(tmp_path / "one" / "claims.csv").iloc[0]
    assert one["verdict"] == "supported" and one["seeds"] == 1 and one["pairs"] == 12
    assert one["R: model − control [95%]"].startswith("+0.500") and got["missing"] == []
    for fold in ("a", "b"):
        _write(ev, fold, "rlsac-s1", [20.0] * 6, [20.0] * 6)
    claims.build(ev, tmp_path / "two", (claim,))
    two = pd.read_csv(tmp_path / "two" / "claims.csv").iloc[0]
    assert two["seeds"] == 2 and two["R: model − control [95%]"].startswith("+0.000")
    assert two["R: verdict"] == "inconclusive" and two["verdict"] == "inconclusive" and two["R: P(improve)"] == 0.5
    md = (tmp_path / "two" / "claims.md").read_text()
    assert "1 claims: 0 supported, 1 inconclusive, 0 not supported; 0 rest on one training seed." in md


def test_claims_with_missing_rows_are_listed_and_the_command_writes_the_table(tmp_path, monkeypatch):
    ev = tmp_path / "reports" / "eval"
    _write(ev, "a", "rlsac", [0.5] * 4, [0.5] * 4, it=1000)
    _write(ev, "a", "uniform", [0.5] * 3 + [20.0], [0.5] * 4, it=1000)
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(cli, ["table", "--which", "claims", "--no-tracking"])
    assert r.exit_code == 0, r.output
    df = pd.read_csv(tmp_path / "reports" / "claims.csv")
    assert list(df["rows"]) == ["rlsac − uniform"]  # the one claim whose rows exist (hard, 1k)
    assert df.iloc[0]["R: model − control [95%]"].startswith("+0.250") and df.iloc[0]["t: verdict"] == "supported"
    md = (tmp_path / "reports" / "claims.md").read_text()
    assert "Not checked (their rows are not in reports/eval): " in md and "PoseLib is ahead of RLSAC" in md


def test_results_without_any_claims_rows_still_write_the_table(tmp_path):
    """A profile whose rows or budgets no claim uses (the quick one: 10 and 50 iterations) gets a claims table that
    lists every claim as not checked: the tables stage declares the files, so they must exist."""
    ev = tmp_path / "eval"
    _write(ev, "a", "rlsac", [0.5] * 4, [0.5] * 4, it=10)
    got = claims.build(ev, tmp_path)
    assert sorted(Path(f).name for f in got["files"]) == ["claims.csv", "claims.md"]
    assert len(got["missing"]) == len(claims.CLAIMS)
    md = (tmp_path / "claims.md").read_text()
    assert md.count("; ") >= len(claims.CLAIMS) - 1 and "0 claims: 0 supported" in md
    assert pd.read_csv(tmp_path / "claims.csv").empty
    assert claims.build(tmp_path / "nothing", tmp_path / "out")["files"] == []  # no results at all: nothing


def test_line_claims_take_both_rows_over_their_seeds(tmp_path):
    """A Table 1 claim reads <eval_root>/lines/<row>/o<rate>/errors.csv, each row over its training seeds: Ours-0.5
    (3 seeds) against Ours (2 seeds) at 0.3, with the lines' tie margin; a rate without results is not checked."""
    ev = tmp_path / "eval"

    def put(d: str, errs, iterations: int = 150) -> None:
        out = ev / "lines" / d / "o0.3"
        out.mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"instance": range(len(errs)), "err_deg": errs}).to_csv(out / "errors.csv", index=False)
        (out / "summary.json").write_text(json.dumps({"iterations": iterations, "mAA": _maa(errs)}))

    good, bad = [0.02] * 20, [0.02] * 19 + [1.0]  # mAA 1.0 and 0.95
    for d, errs in (("ours-0.5", good), ("ours-0.5-s1", good), ("ours-0.5-s2", bad), ("ours", good),
                    ("ours-s1", good)):
        put(d, errs)
    tie = claims.Claim("Ours-0.5 ties Ours", "test", "lines", "0.3", 150, "ours-0.5", "ours", "tie", ("angle",),
                       claims.LINE_TIE_MARGIN)
    elsewhere = claims.Claim("at 0.7", "test", "lines", "0.7", 150, "ours-0.5", "ours", "tie", ("angle",), 0.01)
    got = claims.build(ev, tmp_path / "out", (tie, elsewhere))
    assert got["missing"] == ["at 0.7"]
    row = pd.read_csv(tmp_path / "out" / "claims.csv").iloc[0]
    assert row["seeds"] == "3 vs 2" and row["pairs"] == 20
    assert row["angle: model − control [95%]"].startswith("-0.017 [")  # seed means 0.983 - 1.0
    assert row["angle: verdict"] == "inconclusive"  # the interval reaches -0.05, beyond the 0.01 margin
    md = (tmp_path / "out" / "claims.md").read_text()
    assert "## Lines (Table 1)" in md and "## Fold benchmarks" not in md and "0 rest on one training seed" in md
    wide = claims.Claim("Ours-0.5 ties Ours", "test", "lines", "0.3", 150, "ours-0.5", "ours", "tie", ("angle",), 0.1)
    claims.build(ev, tmp_path / "wide", (wide,))  # the claim's own margin decides: inside ±0.1
    assert pd.read_csv(tmp_path / "wide" / "claims.csv").iloc[0]["verdict"] == "supported"
    put("ours-s1", good, iterations=30)  # a seed evaluated at another budget: the claim (150) is not checked
    assert claims.build(ev, tmp_path / "other", (wide,))["missing"] == ["Ours-0.5 ties Ours"]


def test_a_line_claim_at_a_rate_without_other_seeds_uses_the_first_seed(tmp_path):
    """The other line seeds train only at lines.seed_rates: at any other rate Ours is its first seed alone, not a
    claim left unchecked."""
    ev = tmp_path / "eval"
    for d, rate, errs in (("ours", 0.1, [0.02] * 10), ("ransac", 0.1, [0.02] * 5 + [1.0] * 5),
                          ("ours-s1", 0.3, [0.02] * 10)):
        out = ev / "lines" / d / f"o{rate:g}"
        out.mkdir(parents=True)
        pd.DataFrame({"instance": range(10), "err_deg": errs}).to_csv(out / "errors.csv", index=False)
        (out / "summary.json").write_text(json.dumps({"iterations": 150, "mAA": _maa(errs)}))
    claim = claims.Claim("Ours beats RANSAC at 0.1", "test", "lines", "0.1", 150, "ours", "ransac", "better",
                         ("angle",), 0.01)
    assert claims.build(ev, tmp_path / "out", (claim,))["missing"] == []
    row = pd.read_csv(tmp_path / "out" / "claims.csv").iloc[0]
    assert row["seeds"] == 1 and row["angle: model − control [95%]"].startswith("+0.500")


def test_a_fold_claim_against_a_learned_control_takes_the_controls_seeds_too(tmp_path):
    """rlsac-nosnn (one seed, solves every pair) against rlsac: rlsac's first seed solves every pair as well, its second
    none. Over rlsac's first seed alone the tie would be exact; with both of its seeds the control's mean is 0.5, the
    difference +0.5, and the seeds column says 1 vs 2."""
    ev = tmp_path / "eval"
    for fold in ("a", "b"):
        _write(ev, fold, "rlsac-nosnn", [0.5] * 6, [0.5] * 6)
        _write(ev, fold, "rlsac", [0.5] * 6, [0.5] * 6)
        _write(ev, fold, "rlsac-s1", [20.0] * 6, [20.0] * 6)
    claim = claims.Claim("no-SNN ties RLSAC", "test", "folds", "hard", 100, "rlsac-nosnn", "rlsac", "tie")
    claims.build(ev, tmp_path / "out", (claim,))
    row = pd.read_csv(tmp_path / "out" / "claims.csv").iloc[0]
    assert row["seeds"] == "1 vs 2" and row["R: model − control [95%]"].startswith("+0.500")
    assert row["verdict"] != "supported"
