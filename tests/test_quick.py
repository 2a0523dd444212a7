"""`rlsac quick`, the README's main job (issue #63 item 6): the committed RLSAC model against uniform sets, OpenCV's
RANSAC and MAGSAC++ on one fold's test pairs, from the clone alone (rlsac.experiments.quick)."""

from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner

from rlsac.cli import cli

ROOT = Path(__file__).resolve().parents[1]


def test_rlsac_against_its_controls_remakes_the_records_errors_and_prints_the_table(tmp_path, monkeypatch):
    """At 10 iterations (the command's default is Table 2's 1000): each row's errors are the record's, byte for byte
    (committed checkpoint and tuned settings, the test pairs prepared from the shipped matches when data/ lacks
    them), and the printed table has each control with RLSAC's lead and its interval."""
    monkeypatch.chdir(ROOT)
    out = tmp_path / "quick"
    r = CliRunner().invoke(cli, ["quick", "--iterations", "10", "--out", str(out), "--no-tracking"],
                           catch_exceptions=False)
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.output.splitlines() if not ln.startswith("note: ")]  # stderr notes (issue #64)
    assert lines[0].startswith("RLSAC against its controls on fold fountain (42 test pairs"), r.output
    assert "The record: reports/table2_folds.md" in lines[0]
    rows = {ln.split("|")[1].strip(): [c.strip() for c in ln.strip("|").split("|")] for ln in lines
            if ln.startswith("| ") and not ln.startswith("| row")}
    assert list(rows) == ["rlsac", "uniform", "opencv_ransac", "magsac"], r.output
    assert rows["rlsac"][-2:] == ["–", "–"] and all(" [" in rows[m][-1] for m in ("uniform", "magsac"))
    for m in ("uniform", "opencv_ransac", "magsac"):  # RLSAC's lead: its mAA minus the row's (rounded to 0.001)
        for col, diff in ((3, -2), (4, -1)):
            lead = float(rows["rlsac"][col]) - float(rows[m][col])
            assert abs(float(rows[m][diff].split()[0]) - lead) < 0.0015, (m, rows[m])
    for row in rows:
        made = out / "eval" / row / "i10" / "errors.csv"
        record = ROOT / "reports" / "eval" / "folds" / "hard" / "fountain" / row / "i10" / "errors.csv"
        assert made.read_bytes() == record.read_bytes(), row
    assert lines[-1] == f"table: {out / 'table.md'}" and "| opencv_ransac " in (out / "table.md").read_text()


def test_a_bad_option_is_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    r = CliRunner().invoke(cli, ["quick", "--fold", "nowhere", "--out", str(tmp_path / "q"), "--no-tracking"])
    assert r.exit_code == 2 and r.output.startswith("error: fold must be one of castle, "), r.output
    r = CliRunner().invoke(cli, ["quick", "--iterations", "0", "--out", str(tmp_path / "q"), "--no-tracking"])
    assert r.exit_code == 2 and r.output.startswith("error: ") and "iterations" in r.output, r.output
    assert not (tmp_path / "q").exists()
