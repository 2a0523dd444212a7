"""The re-tuning term of the claims' intervals (issue #47 item 7 b, rlsac.reports.retuning): its size from the
re-tuning records, its addition in quadrature, and the verdicts of claims.md and paper.md that read it."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd
import pytest

from rlsac.reports import claims, paper_report, retuning
from rlsac.reports.paper_claims import PaperClaim


def _retune(out: Path, row: str, fold: str, test_acc: list[float], choices: list[int], it: int = 1000):
    """A re-tuning record whose setting i solves a fraction test_acc[i] of its 10 test pairs (error 0 or 90°)."""
    n = 10
    per = {str(i): {"err_R": [0.0] * round(a * n) + [90.0] * (n - round(a * n)),
                    "err_t": [0.0] * n} for i, a in enumerate(test_acc)}
    rec = {"settings": [{"threshold_px": 0.5 * (i + 1)} for i in range(len(test_acc))], "full": 0,
           "choices": choices, "test_scenes": ["s"] * n, "test": {str(it): per}}
    path = out / "retune" / "fundamental" / "hard" / fold / f"{row}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(rec))


def test_widen_adds_the_term_in_quadrature_on_each_side():
    got = retuning.widen({"diff": 0.1, "lo": 0.07, "hi": 0.14, "p_improve": 0.9}, 0.04)
    assert got["diff"] == 0.1 and got["p_improve"] == 0.9
    assert got["lo"] == pytest.approx(0.1 - 0.05) and got["hi"] == pytest.approx(0.1 + math.hypot(0.04, 0.04))


def test_halfwidth_is_the_largest_sd_over_rows_budgets_and_metrics(tmp_path):
    """Row a's draws give test mAA 1.0 or 0.0 (sd 0.577 over 4 draws), row b's always 0.5 (sd 0): the term is a's,
    1.96·√2·0.577; no record: None."""
    assert retuning.halfwidth(tmp_path) is None
    _retune(tmp_path, "a", "castle", [1.0, 0.0], [0, 1, 0, 1])
    _retune(tmp_path, "b", "castle", [0.5, 0.5], [0, 1, 0, 1])
    got = retuning.halfwidth(tmp_path)
    sd = pd.Series([1.0, 0.0, 1.0, 0.0]).std()
    assert got["row"] == "a" and got["metric"] == "R" and got["iterations"] == 1000
    assert got["sd"] == pytest.approx(sd) and got["s"] == pytest.approx(1.96 * math.sqrt(2) * sd)


def _fold(root: Path, fold: str, row: str, err_R, it: int):
    d = root / "eval" / "folds" / "hard" / fold / row / f"i{it}"
    d.mkdir(parents=True)
    n = len(err_R)
    pd.DataFrame({"instance": range(n), "scene": fold, "pair": [f"p{i}" for i in range(n)], "err_R": err_R,
                  "err_t": err_R}).to_csv(d / "errors.csv", index=False)


def test_claims_and_paper_verdicts_read_the_widened_interval(tmp_path):
    """RLSAC solves 8 of 8 pairs per fold, uniform 4: +0.5 with a pairs interval that excludes 0, so "better" is
    supported and the paper's +0.1 reproduced. A re-tuning record whose draws swing a row's test mAA from 0 to 1
    (term ±1.6) turns both into inconclusive / no difference; the pairs-only interval is still printed."""
    for fold in ("a", "b"):
        for it in (100, 1000):
            _fold(tmp_path, fold, "rlsac", [0.5] * 8, it)
            _fold(tmp_path, fold, "uniform", [0.5] * 4 + [90.0] * 4, it)
    claim = claims.Claim("RLSAC beats uniform", "test", "folds", "hard", 100, "rlsac", "uniform", "better")
    pclaim = PaperClaim("c", "Table 2", "§4.3", "RLSAC vs uniform", "mAA R", 0.1, control="uniform",
                        regimes=("hard",))
    ev = tmp_path / "eval"
    claims.build(ev, tmp_path, (claim,))
    paper_report.build(ev, tmp_path, (pclaim,), headline=())
    before = pd.read_csv(tmp_path / "claims.csv", dtype=str).iloc[0]
    pbefore = pd.read_csv(tmp_path / "paper.csv", dtype=str).iloc[0]
    assert before["verdict"] == "supported" and "R: with re-tuning [95%]" not in before
    assert pbefore["verdict"] == "reproduced" and pbefore["ours"].startswith("+0.500 [+")
    _retune(tmp_path, "uniform", "a", [1.0, 0.0], [0, 1, 0, 1])
    claims.build(ev, tmp_path, (claim,))
    paper_report.build(ev, tmp_path, (pclaim,), headline=())
    after = pd.read_csv(tmp_path / "claims.csv", dtype=str).iloc[0]
    pafter = pd.read_csv(tmp_path / "paper.csv", dtype=str).iloc[0]
    assert after["R: model − control [95%]"] == before["R: model − control [95%]"]
    assert after["R: with re-tuning [95%]"].startswith("[-1.") and after["verdict"] == "inconclusive"
    assert pafter["verdict"] == "no difference" and pafter["ours"].startswith("+0.500 [-1.")
    assert pafter["pairs and seeds only"] == pbefore["pairs and seeds only"]
    assert "widened in quadrature by ±1.6" in (tmp_path / "claims.md").read_text()
    assert "The re-tuning term: ±1.6" in (tmp_path / "paper.md").read_text()


def test_one_table_build_computes_the_term_once_for_every_builder(tmp_path, monkeypatch):
    """`rlsac table --which all` reads the re-tuning records once (retuning.halfwidth) and hands the term to the
    claims and the paper's claims, which both print it."""
    from rlsac.reports import tables

    for fold in ("a", "b"):
        for it in (100, 1000):
            _fold(tmp_path, fold, "rlsac", [0.5] * 8, it)
            _fold(tmp_path, fold, "uniform", [0.5] * 4 + [90.0] * 4, it)
    _retune(tmp_path, "uniform", "a", [1.0, 0.0], [0, 1, 0, 1])
    calls = []
    real = retuning.halfwidth

    def counted(out_dir):
        calls.append(out_dir)
        return real(out_dir)

    monkeypatch.setattr(retuning, "halfwidth", counted)
    tables.build({"which": "all", "eval_root": tmp_path / "eval", "out_dir": tmp_path}, track=False)
    assert calls == [tmp_path]
    assert "widened in quadrature by ±1.6" in (tmp_path / "claims.md").read_text()
    assert "The re-tuning term: ±1.6" in (tmp_path / "paper.md").read_text()
