"""``rlsac evaluate --tuning FILE`` / ``--threshold-px`` / ``--prefilter`` (issue #47): a fold cell by hand, and a
record of another row refused before any work."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.errors import RlsacError
from rlsac.tune import record_options

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
