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
