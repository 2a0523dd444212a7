"""Reports follow the recorded provenance (dvc.lock, summary.json), not whether data/ exists in this checkout,
and a failing ``rlsac plot`` leaves the figures it would have replaced untouched."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.commands import lines_protocol_data
from rlsac.errors import RlsacError
from rlsac.reports import figures, provenance, tables

LINES_PARAMS = {"lines.n_test": 8, "lines.n_train": 4, "lines.n_val": 4, "lines.seed_test": 3000,
                "lines.seed_train": 1000, "lines.seed_val": 2000, "lines_data": {}}
PREPARE = ("rlsac prepare-cvpr2020 --root data/raw/strecha --split all --scenes fountain-P11,entry-P10\n"
           "  --n-points 150 --max-pairs-per-scene 0 --out data/fundamental/test.h5")
FIGURES = ["fundamental_iterations", "line_steps", "fundamental_pair", "fundamental_steps"]


def _md5_of_regenerated() -> str:
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "p.yaml").write_text(yaml.safe_dump({"lines": {"n_test": 8, "seed_test": 3000}}))
        s = lines_protocol_data({"rate": 0.7, "splits": "test", "out_dir": tmp}, track=False,
                                params_path=Path(tmp) / "p.yaml")
        return provenance.md5(s["files"][0])


@pytest.fixture
def fresh_clone(workdir):
    """What a fresh clone holds: dvc.lock, committed summaries and figures; no data/."""
    md5 = _md5_of_regenerated()
    lock = {"schema": "2.0", "stages": {
        "lines_data@0.7": {"cmd": "rlsac lines-data --rate 0.7", "params": {"params.yaml": LINES_PARAMS},
                           "outs": [{"path": "data/lines/test_o0.7.h5", "hash": "md5", "md5": md5, "size": 1}]},
        "prepare_fundamental@test": {"cmd": PREPARE, "outs": [{"path": "data/fundamental/test.h5", "md5": "x"}]},
        "fold_data@hard-fountain": {"cmd": "rlsac folds --stage data --regime hard --fold fountain",
                                    "outs": [{"path": "data/folds/hard/fountain", "md5": "y.dir"}]},
    }}
    (workdir / "dvc.lock").write_text(yaml.safe_dump(lock))
    d = workdir / "reports" / "eval" / "fundamental" / "rlsac" / "i1000"
    d.mkdir(parents=True)
    summary = {"mAA_R": 0.9, "mAA_t": 0.6, "mAA": 0.6, "median_R": 0.3, "median_t": 1.9, "n_instances": 87,
               "data": "data/fundamental/test.h5"}
    (d / "summary.json").write_text(json.dumps(summary))
    figs = workdir / "reports" / "figures"
    figs.mkdir()
    for name in FIGURES:
        for ext in ("png", "pdf"):
            (figs / f"{name}.{ext}").write_bytes(b"committed " + name.encode())
    return workdir


def _committed(root: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((root / "reports" / "figures").iterdir())}


def _no_leftovers(root: Path) -> None:
    assert sorted(p.name for p in (root / "reports").iterdir()) == ["eval", "figures"]
    assert not (root / "data").exists()


def test_table_caption_from_dvc_lock_without_data(fresh_clone):
    df = tables.table2("reports/eval", "out")
    caption = df.attrs["caption"]
    assert "Strecha substitute (fountain-P11, entry-P10), 87 pairs, N=150 correspondences" in caption
    assert "not readable" not in caption
    assert provenance.prepared_attrs("data/fundamental/test.h5")["stage"] == "prepare_fundamental@test"
    (fresh_clone / "dvc.lock").unlink()
    assert "not readable" in tables.table2("reports/eval", "out").attrs["caption"]


def test_failed_plot_touches_nothing(fresh_clone):
    before = _committed(fresh_clone)
    r = CliRunner().invoke(cli, ["plot", "--no-tracking"])
    assert r.exit_code == 2
    assert r.output.startswith("error: rlsac plot needs: ") and r.output.count("\n") == 1
    # every problem, in one line; the pair figures read a fold's test file, made by its (directory) data stage
    assert "data/folds/hard/fountain/test.h5: no prepared two-view file" in r.output
    assert "dvc repro fold_data@hard-fountain" in r.output and "line_o0.7.pt: no such checkpoint" in r.output
    assert _committed(fresh_clone) == before
    _no_leftovers(fresh_clone)


def test_failure_while_drawing_touches_nothing(fresh_clone):
    """The iterations figure is drawn, then the line figure fails: neither replaces a committed file."""
    before = _committed(fresh_clone)
    with pytest.raises(RlsacError, match="line_index 999 out of range"):
        figures.plot({"which": "iterations,line", "line_checkpoint": "", "line_index": 999}, track=False)
    assert _committed(fresh_clone) == before
    _no_leftovers(fresh_clone)


def test_line_figure_uses_the_recorded_file(fresh_clone):
    before = _committed(fresh_clone)
    s = figures.plot({"which": "line", "line_checkpoint": "", "line_index": 1}, track=False)
    assert "data/lines/test_o0.7.h5 regenerated as recorded in dvc.lock" in s["notes"]
    after = _committed(fresh_clone)
    assert {k for k in after if after[k] != before[k]} == {"line_steps.png", "line_steps.pdf"}
    _no_leftovers(fresh_clone)
    lock = yaml.safe_load((fresh_clone / "dvc.lock").read_text())
    lock["stages"]["lines_data@0.7"]["params"]["params.yaml"]["lines.seed_test"] = 4000  # not what was recorded
    (fresh_clone / "dvc.lock").write_text(yaml.safe_dump(lock))
    with pytest.raises(RlsacError, match="other bytes: run `dvc repro lines_data@0.7`"):
        figures.plot({"which": "line", "line_checkpoint": "", "line_index": 1}, track=False)
    assert _committed(fresh_clone) == after


def test_missing_checkpoint_is_an_error_not_a_fallback(fresh_clone):
    before = _committed(fresh_clone)
    with pytest.raises(RlsacError, match="nope.pt: no such checkpoint"):
        figures.plot({"which": "line", "line_checkpoint": "nope.pt"}, track=False)
    assert _committed(fresh_clone) == before
