"""``rlsac evaluate --tuning FILE`` / ``--threshold-px`` / ``--prefilter`` (issue #47): a fold cell by hand, and a
record of another row refused before any work."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.errors import RlsacError
from rlsac.evaluation.tune import record_options

RECORD = {"task": "fundamental", "method": "magsac", "row": "magsac", "regime": "hard", "fold": "castle",
          "checkpoint": None, "chosen": {"prefilter": 0.8, "threshold_px": 0.25}, "val_scenes": ["entry-P10"]}


def _record(tmp_path: Path, **changes) -> Path:
    f = tmp_path / "rec.json"
    f.write_text(json.dumps({**RECORD, **changes}))
    return f


def test_a_record_gives_its_chosen_settings(tmp_path):
    assert record_options(_record(tmp_path), "fundamental", "magsac", None, None) == {"prefilter": 0.8,
                                                                                      "threshold_px": 0.25}
    # pre-filter 1.0 is "none", and an LO sigma goes into the row's LO conf (as the fold stage does)
    got = record_options(_record(tmp_path, method="rlsac-lo", checkpoint="m.pt",
                                 chosen={"prefilter": 1.0, "threshold_px": 1.0, "lo_sigma_scale": 0.25}),
                         "fundamental", "rlsac-lo", "m.pt", {"iterations": 4, "sigma_scale": 0.5})
    assert got == {"prefilter": None, "threshold_px": 1.0, "lo": {"iterations": 4, "sigma_scale": 0.25}}


@pytest.mark.parametrize("changes, args, match", [
    ({"method": "usac"}, (), "method 'usac', not task 'fundamental', method 'magsac'"),
    ({"task": "essential"}, (), "task 'essential'"),
    ({"checkpoint": "checkpoints/folds/hard/castle/rlsac.pt", "method": "magsac"}, (), "tuned for checkpoint"),
    ({"chosen": None}, (), "not a tuning record"),
    # issue #49: accepted, and the cell evaluated untuned at exit 0 (the fold stages' reader refused them)
    ({"chosen": {}}, (), "'chosen' is {}"),
    ({"val_scenes": []}, (), "not the validation scenes"),
    ({"chosen": {"threshold_px": "x"}}, (), "chosen setting 'threshold_px' is 'x'"),
])
def test_a_record_of_another_row_is_refused(tmp_path, changes, args, match):
    with pytest.raises(RlsacError, match=match):
        record_options(_record(tmp_path, **changes), "fundamental", "magsac", *args or (None,), None)


def _evaluate(tmp_path: Path, *extra: str):
    data = tmp_path / "test.h5"
    data.write_bytes(b"")  # never read: the record is refused first
    return CliRunner().invoke(cli, ["evaluate", "--no-tracking", "--task", "fundamental", "--method", "magsac",
                                    "--data", str(data), "--out-dir", str(tmp_path / "out"), *extra])


@pytest.mark.parametrize("record, extra, match", [
    ({"method": "usac"}, (), "error: --tuning"),
    ({}, ("--threshold-px", "0.5"), "sets threshold_px; give --threshold-px or --tuning, not both"),
    (None, (), "error: --tuning"),  # not JSON
    ("[]", (), "not a tuning record (holds a list"),  # valid JSON, not a record
    ("null", (), "not a tuning record (holds a NoneType"),
    ({"chosen": {}}, (), "'chosen' is {}"),
])
def test_the_command_refuses_a_bad_record_on_one_line_before_any_work(tmp_path, record, extra, match):
    if record is None or isinstance(record, str):
        f = tmp_path / "rec.json"
        f.write_text(record or "{not json")
    else:
        f = _record(tmp_path, **record)
    r = _evaluate(tmp_path, "--tuning", str(f), *extra)
    assert r.exit_code == 2 and match in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_threshold_and_prefilter_are_range_checked(tmp_path):
    r = _evaluate(tmp_path, "--prefilter", "1.5")
    assert r.exit_code == 2 and "prefilter" in r.output and not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    """A small prepared fundamental file of one scene, "s1" (test_tutorial's synthetic scene)."""
    from test_reliability import _fundamental  # tests/ is on sys.path (pytest prepend mode)

    return _fundamental(tmp_path_factory.mktemp("pairs"))


def _evaluate_on(tmp_path: Path, data: Path, *extra: str):
    import shutil

    shutil.copy(Path(__file__).resolve().parents[1] / "params.yaml", tmp_path / "params.yaml")
    return CliRunner().invoke(cli, ["evaluate", "--no-tracking", "--task", "fundamental", "--method", "magsac",
                                    "--iterations", "5", "--data", str(data), "--out-dir", str(tmp_path / "out"),
                                    "--params", str(tmp_path / "params.yaml"), *extra])


@pytest.mark.parametrize("record, extra, match", [
    # issue #64: each evaluated at exit 0, mAA 0 and median errors 180 / 90 degrees, or with the settings of another
    # fold, chosen on the pairs being evaluated
    (None, ("--threshold-px", "1e300"), "threshold_px must be in [0.001, 1000], got 1e+300"),
    (None, ("--threshold-px", "1e-300"), "threshold_px must be in [0.001, 1000], got 1e-300"),
    (None, ("--prefilter", "1e-9"), "prefilter 1e-09 leaves fewer than a minimal set (8 points) in every instance"),
    ({"chosen": {"prefilter": 0.8, "threshold_px": 1e6}}, (),
     "rec.json: chosen threshold_px must be in [0.001, 1000], got 1000000.0"),
    ({"val_scenes": ["s1", "entry-P10"]}, (), "tuned on pairs of scene(s) ['s1']"),
    ({}, (), "a record of fold 'castle'; {data} holds pairs of scene(s) ['s1'] outside that fold's test building"),
    ({"iterations": 5000}, (), "tuned at 5000 iterations, neither the tables' tuning budget nor --iterations (5, 100)"),
], ids=["threshold-huge", "threshold-tiny", "prefilter-empty", "record-huge-threshold", "record-leak",
        "record-other-fold", "record-other-budget"])
def test_settings_and_records_are_checked_against_the_data(tmp_path, pairs, record, extra, match):
    args = extra if record is None else ("--tuning", str(_record(tmp_path, **record)), *extra)
    r = _evaluate_on(tmp_path, pairs, *args)
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert err.startswith("error: ") and "\n" not in err and match.format(data=pairs) in err, err
    assert not (tmp_path / "out").exists()


def test_a_record_of_another_folds_data_path_is_refused(tmp_path, pairs):
    import shutil

    data = tmp_path / "data/folds/hard/entry/test.h5"
    data.parent.mkdir(parents=True)
    shutil.copy(pairs, data)
    r = _evaluate_on(tmp_path, data, "--tuning", str(_record(tmp_path)))
    assert r.exit_code == 2 and "a record of regime 'hard', fold 'castle'; " in r.stderr, r.output
    assert "is regime 'hard', fold 'entry'" in r.stderr and not (tmp_path / "out").exists()


def test_a_record_of_the_fold_on_its_own_test_building_runs(tmp_path, pairs):
    """The checks refuse only what is wrong: a castle record (castle's pairs renamed) evaluates."""
    import h5py

    data = tmp_path / "castle.h5"
    import shutil

    shutil.copy(pairs, data)
    with h5py.File(data, "a") as f:
        n = len(f["scene"])
        del f["scene"]
        f["scene"] = np.array(["castle-P19"] * n, dtype=h5py.string_dtype())
    r = _evaluate_on(tmp_path, data, "--tuning", str(_record(tmp_path, iterations=100)))
    assert r.exit_code == 0, r.output
