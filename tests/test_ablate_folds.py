"""``rlsac ablate --what descriptors|sampling|points|all`` without the retired 87-pair split's data (issue #47): it
prints the fold stages of the study, and those commands name real stages and parse."""

from __future__ import annotations

import fnmatch
import shlex
from pathlib import Path

import pytest
from click.testing import CliRunner
from dvc.cli import parse_args

from rlsac import ablate
from rlsac.cli import cli

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


def test_the_command_prints_runnable_fold_commands_instead_of_failing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no data/fundamental here, as on every clone
    r = CliRunner().invoke(cli, ["ablate", "--what", "sampling", "--no-tracking", "--params", ""])
    assert r.exit_code == 0, r.output
    assert "data/fundamental/train.h5 is made by no stage" in r.output
    lines = [line.strip() for line in r.output.splitlines() if line.startswith("  ")]
    assert lines == ablate.fold_commands("sampling") and len(lines) == 2
    rl, dv = (shlex.split(line) for line in lines)
    cli.commands["pipeline"].make_context("pipeline", rl[2:])  # the options parse
    assert rl[2:-3] == list(ablate.FOLD_STUDIES["sampling"]) and rl[-3] == "tables"
    args = parse_args(dv[1:])
    assert args.glob and args.targets == [*ablate.FOLD_STUDIES["sampling"], "tables"]
    assert not list(tmp_path.iterdir())  # nothing written
