"""``rlsac ablate --what descriptors|sampling|points|all`` without the retired 87-pair split's data (issue #47): it
prints the fold stages of the study, and those commands name real stages and parse."""

from __future__ import annotations

import fnmatch
import shlex
from pathlib import Path

import pytest
from click.testing import CliRunner
from dvc.cli import parse_args

from rlsac.cli import cli
from rlsac.experiments import ablate

ROOT = Path(__file__).resolve().parents[1]


def _stages() -> list[str]:
    from dvc import repo as dvc_repo

    with dvc_repo.Repo(str(ROOT)) as repo:
        return [s.addressing for s in repo.index.stages]


@pytest.fixture(scope="module")
def stages() -> list[str]:
    return _stages()


def _hits(stages: list[str], what: str) -> set[str]:
    return {s for p in ablate.FOLD_STUDIES[what] for s in stages if fnmatch.fnmatchcase(s, p)}


def test_each_study_names_its_fold_stages_and_no_other(stages):
    desc, samp, pts = (_hits(stages, w) for w in ("descriptors", "sampling", "points"))
    assert {"fold_eval_ablation@hard-castle-rlsac-nodesc", "fold_train_ablation_seed@castle-rlsac-nodesc-4"} <= desc
    assert {"fold_eval_prob@hard-castle-rlsac-trainmax", "fold_eval_ablation@hard-entry-rlsac-trainmax"} <= samp
    assert "fold_data_points@hard-castle-300" in pts and "fold_eval_points_method@hard-castle-100-uniform" in pts
    assert not desc & samp and not samp & pts and not desc & pts
    assert all("nodesc" in s for s in desc) and all("trainmax" in s or "prob" in s for s in samp)
    assert len(desc) == 4 * 5 * 3 and len(pts) == 12 * 6  # (a): 4 folds x 5 seeds x train / tune / eval


def test_the_points_study_prints_runnable_fold_commands_instead_of_failing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no data/fundamental here, as on every clone
    r = CliRunner().invoke(cli, ["ablate", "--what", "points", "--no-tracking", "--params", ""])
    assert r.exit_code == 0, r.output
    assert "data/fundamental/train_n100.h5 is made by no stage" in r.output
    assert "`rlsac ablate --what points --full` runs its fold stages" in r.output
    lines = [line.strip() for line in r.output.splitlines() if line.startswith("  ")]
    assert lines == ablate.fold_commands("points") and len(lines) == 3
    rl, dv = (shlex.split(line) for line in lines[:2])
    cli.commands["pipeline"].make_context("pipeline", rl[2:])  # the options parse
    assert rl[2:-2] == list(ablate.FOLD_STUDIES["points"])  # the study's stages, not `tables` (it needs them all)
    args = parse_args(dv[1:])
    assert args.glob and args.targets == list(ablate.FOLD_STUDIES["points"])
    assert not list(tmp_path.iterdir())  # nothing written


def _committed(row: str, it: int) -> Path:
    return ROOT / "reports" / "eval" / "folds" / "hard" / "fountain" / row / f"i{it}" / "errors.csv"


def test_the_sampling_study_runs_quickly_on_one_fold_and_prints_its_table(tmp_path, monkeypatch):
    """The default: the committed checkpoints and tuning records on fountain's test pairs (prepared from the committed
    matches when data/ lacks them), at 10 iterations here (the default is Table 2's 1000): the record's errors byte
    for byte, the table printed and written under --out, nothing committed touched."""
    monkeypatch.chdir(ROOT)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["ablate", "--what", "sampling", "--iterations", "10", "--out", str(out),
                                 "--no-tracking"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.output.splitlines() if not ln.startswith("note: ")]  # stderr notes (issue #64)
    assert lines[0].startswith("Table 3 (sampling), quick: fold fountain (42 test pairs), hard regime, 10 iterations")
    rows = [ln.split("|")[1].strip() for ln in lines if ln.startswith("| rlsac")]
    assert rows == ["rlsac", "rlsac-trainmax", "rlsac-trainmax-prob", "rlsac-prob"], r.output
    assert lines[-1] == f"table: {out / 'sampling' / 'table.md'}"
    assert "| rlsac-prob " in (out / "sampling" / "table.md").read_text()
    for row in rows:  # the record's evaluation, re-made from the clone
        assert (out / "sampling" / "eval" / row / "i10" / "errors.csv").read_bytes() == _committed(row, 10).read_bytes()


def test_a_bad_fold_is_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    r = CliRunner().invoke(cli, ["ablate", "--what", "sampling", "--fold", "nowhere", "--out", str(tmp_path / "o"),
                                 "--no-tracking"])
    assert r.exit_code == 2 and r.output.startswith("error: fold must be one of castle, "), r.output
    assert not (tmp_path / "o").exists()


def test_full_runs_exactly_the_studys_stages_then_its_table(tmp_path, monkeypatch):
    """--full: `rlsac pipeline` on the study's fold stages only (not `tables`, which needs every stage of the record),
    then Table 3 (folds) from reports/eval under --out: on the committed results, the committed table's bytes."""
    import rlsac.runners.pipeline

    asked = []

    def pipeline(options, track=True):  # the stages are the record's: up to date, nothing to run here
        asked.append(options)
        return {"results": {}, "counts": {"skipped": 0}}

    monkeypatch.setattr(rlsac.runners.pipeline, "pipeline", pipeline)
    monkeypatch.chdir(ROOT)
    r = CliRunner().invoke(cli, ["ablate", "--what", "sampling", "--full", "--workers", "2", "--out", str(tmp_path),
                                 "--no-tracking"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert asked == [{"stages": ",".join(ablate.FOLD_STUDIES["sampling"]), "workers": 2}]
    made = tmp_path / "sampling-full" / "table3_folds.md"
    assert made.read_bytes() == (ROOT / "reports" / "table3_folds.md").read_bytes()
    assert r.output.splitlines()[-1] == f"table: {made}, {tmp_path / 'sampling-full' / 'table3_folds.csv'}"
