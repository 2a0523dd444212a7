"""Progress bars are drawn for a person at a terminal, never into CI logs or redirected output."""

from __future__ import annotations

import io

import pytest

from rlsac import progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def _drawn(stream, **kw) -> str:
    for _ in progress.tqdm(range(5), file=stream, mininterval=0, **kw):
        pass
    return stream.getvalue()


@pytest.fixture(autouse=True)
def _no_env(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.delenv("RLSAC_PROGRESS", raising=False)


def test_terminal_gets_a_bar():
    out = _drawn(_Tty())
    assert "\r" in out and "5/5" in out


def test_redirected_output_gets_none():
    assert _drawn(io.StringIO()) == ""
    assert _drawn(io.StringIO(), disable=None) == ""


@pytest.mark.parametrize("value", ["true", "1", "yes"])
def test_ci_gets_none_even_on_a_terminal(monkeypatch, value):
    monkeypatch.setenv("CI", value)
    assert _drawn(_Tty()) == ""
    assert _drawn(_Tty(), disable=False) == ""  # callers' progress=True does not override CI


def test_ci_false_and_explicit_switches(monkeypatch):
    monkeypatch.setenv("CI", "false")
    assert "5/5" in _drawn(_Tty())
    assert _drawn(_Tty(), disable=True) == ""
    monkeypatch.setenv("RLSAC_PROGRESS", "1")
    assert "5/5" in _drawn(io.StringIO(), disable=None)
    monkeypatch.setenv("RLSAC_PROGRESS", "0")
    assert _drawn(_Tty()) == ""


def test_calibrate_lines_shows_its_progress_on_a_terminal_only(tmp_path, monkeypatch, capsys):
    """The line calibration draws one bar over its rate x seed sets (issue #47: it printed nothing while it ran);
    redirected, as under dvc repro or CI, it draws none."""
    from rlsac.commands import calibrate_lines

    opts = {"n_instances": 8, "n_seeds": 2, "seed": 123, "iterations": 5, "out": str(tmp_path / "cal")}
    monkeypatch.setenv("RLSAC_PROGRESS", "1")
    calibrate_lines(opts, track=False, params_path=None)
    err = capsys.readouterr().err
    assert "calibrate-lines" in err and "14/14" in err and "rate 0.7, data seed 124" in err
    monkeypatch.setenv("RLSAC_PROGRESS", "0")
    calibrate_lines(opts, track=False, params_path=None)
    assert "calibrate-lines" not in capsys.readouterr().err
