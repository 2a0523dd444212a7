"""Shared fixtures: every test that writes runs in its own temporary working directory."""

from __future__ import annotations

# isort: off
# rlsac before torch, numpy and OpenCV: in the portable numeric mode its pins must be set before they load
import rlsac  # noqa: F401
# isort: on
import pytest
import torch

# MKL fixes its code branch at its first call. Make that call here, on the mode's branch: `rlsac calibrate-lines`
# (run in-process by some tests) sets MKL_CBWR=COMPATIBLE while it runs, and had it come first, this process
# would round differently from the subprocesses that tests compare it with (rlsac.numerics.portable_blas)
torch.ones(2, 2) @ torch.ones(2, 2)


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """chdir into a fresh tmp dir with MLflow pointed at a sqlite db inside it; -> the dir."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.setenv("MLFLOW_LOGGING_LEVEL", "WARNING")
    return tmp_path
