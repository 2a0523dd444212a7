"""The plug-in point: a task defined in this file alone (no edit to rlsac/) registers itself and runs
through evaluate, the CLI's --task choices and the method capability checks."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from rlsac.cli import cli
from rlsac.errors import RlsacError
from rlsac.evaluation.evaluate import evaluate
from rlsac.maths import metrics
from rlsac.tasks import TASKS, register_task


@dataclass
class ToyTask:
    """1-D robust location: points on a line, the hypothesis is one value; m = 1, residual |x - h|."""

    experiment: ClassVar[str] = "toy"
    default_iterations: ClassVar[int] = 20
    residual_dof: ClassVar[int] = 2
    true_inlier_data: ClassVar[bool] = False

    threshold: float = 0.5
    name: str = "toy"
    sample_size: int = 1
    coord_dim: int = 1
    feature_dim: int = 1
    solutions: int = 1

    @staticmethod
    def read(path):
        try:
            with np.load(path) as f:
                return {"x": f["x"].astype(np.float32), "truth": f["truth"]}, {}
        except (OSError, ValueError, KeyError) as e:
            raise RlsacError(f"{path}: not a toy file ({e})") from None

    @staticmethod
    def to_batch(arrays, idx=slice(None), device="cpu"):
        x = torch.as_tensor(arrays["x"][idx], device=device)
        return {"coords": x[..., None], "mask": torch.ones_like(x, dtype=torch.bool), "truth": arrays["truth"][idx]}

    def features(self, batch):
        return batch["coords"] / 10

    def solve(self, pts):
        return pts[:, 0], torch.ones(pts.shape[0], dtype=torch.bool)

    def residuals(self, hyps, coords):  # hyps (B, 1) -> (B, N); (B, S, 1) -> (B, S, N)
        return (coords[..., 0] - hyps).abs() if hyps.dim() == 2 else (coords[:, None, :, 0] - hyps).abs()

    def refine(self, coords, inliers):
        w = inliers.to(coords.dtype)
        return ((coords[..., 0] * w).sum(-1) / w.sum(-1).clamp_min(1))[:, None], inliers.sum(-1) > 0

    def true_inliers(self, batch):
        return self.residuals(torch.as_tensor(batch["truth"])[:, None], batch["coords"]) <= self.threshold

    def errors(self, hyps, valid, inliers, batch):
        return {"err": np.where(valid, np.abs(np.asarray(hyps)[:, 0] - batch["truth"]), 10.0)}

    def summarize(self, errors):
        return {"mAA": metrics.mAA(errors["err"], 1.0), "n": int(errors["err"].size)}


@pytest.fixture
def toy(workdir):
    """The toy task registered for one test, and a data file of 6 instances (60% outliers)."""
    register_task(ToyTask)
    rng = np.random.default_rng(0)
    truth = rng.uniform(2, 8, 6)
    x = rng.uniform(0, 10, (6, 40))
    x[:, :16] = truth[:, None] + rng.normal(0, 0.1, (6, 16))
    np.savez(workdir / "toy.npz", x=x, truth=truth)
    yield workdir / "toy.npz"
    del TASKS["toy"]


@pytest.mark.parametrize("method", ["ransac", "uniform", "ransac-lo"])
def test_a_task_defined_outside_the_package_runs_through_evaluate(toy, method):
    s = evaluate({"task": "toy", "method": method, "data": str(toy), "out_dir": "ev", "iterations": 10,
                  **({"lo": {"score": "count"}} if method.endswith("-lo") else {})}, track=False)
    assert s["task"] == "toy" and s["n_instances"] == 6 and s["iterations"] == 10
    assert s["mAA"] > 0.8  # 10 draws at 40% inliers miss the line with probability 0.6^10
    conf = json.loads((toy.parent / "ev" / "config.json").read_text())
    assert conf["task_options"]["threshold"] == 0.5 and conf["method"] == method


def test_the_cli_offers_the_registered_task_and_checks_capabilities(toy):
    run = lambda *a: CliRunner().invoke(cli, [str(x) for x in a])  # noqa: E731
    assert "toy" in run("evaluate", "--help").output
    r = run("evaluate", "--task", "toy", "--method", "ransac", "--data", toy, "--out-dir", "ev", "--no-tracking")
    assert r.exit_code == 0, r.output
    assert json.loads((toy.parent / "ev" / "summary.json").read_text())["iterations"] == 20  # the task's default
    r = run("evaluate", "--task", "toy", "--method", "magsac", "--data", toy, "--out-dir", "ev2", "--no-tracking")
    assert r.exit_code == 2 and "needs an OpenCV estimator, which task 'toy' has not" in r.stderr
    assert not (toy.parent / "ev2").exists()


def test_registering_a_task_checks_its_registry_data():
    @dataclass
    class NoReader:
        name: str = "noreader"
        experiment: ClassVar[str] = "x"
        default_iterations: ClassVar[int] = 1
        residual_dof: ClassVar[int] = 2

    with pytest.raises(TypeError, match="lacks 'read'"):
        register_task(NoReader)
    with pytest.raises(ValueError, match="registered twice"):
        register_task(type("Other", (ToyTask,), {"name": "line"}))
    with pytest.raises(RlsacError, match="unknown task 'nope'"):
        evaluate({"task": "nope", "method": "ransac", "data": "x.h5"}, track=False)
