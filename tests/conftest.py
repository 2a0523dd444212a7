"""Shared fixtures: every test that writes runs in its own temporary working directory."""

from __future__ import annotations

import pytest


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """chdir into a fresh tmp dir with MLflow pointed at a sqlite db inside it; -> the dir."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.setenv("MLFLOW_LOGGING_LEVEL", "WARNING")
    return tmp_path
