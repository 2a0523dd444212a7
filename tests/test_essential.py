"""The essential-matrix task (not in the paper): five-point solver, calibration, multi-solution
scoring, refinement, baselines, and evaluate / train end to end through the CLI."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from test_fundamental import K, make_batch  # tests/ is on sys.path (pytest prepend mode)

from rlsac.cli import cli
from rlsac.data.fundamental import KIND
from rlsac.data.tutorial import write
from rlsac.estimation.baselines import opencv_estimate, ransac
from rlsac.estimation.lo import score_sets
from rlsac.maths import geometry
from rlsac.tasks import get_task
from rlsac.tasks.essential import EssentialTask
from rlsac.tasks.line import LineTask


def calibrated(batch: dict) -> dict:
    """The essential task's batch of a make_batch batch (pixels -> K^-1 x)."""
    arrays = {k: (v.numpy() if torch.is_tensor(v) else v) for k, v in batch.items()}
    B = len(arrays["K1"])
    arrays.update(pair=np.array([f"p{i}" for i in range(B)], dtype=object), scene=np.array(["s"] * B, dtype=object))
    return {**EssentialTask.to_batch(arrays), "gt_inliers": batch["gt_inliers"]}


def gt_essential(batch: dict) -> torch.Tensor:
    t = lambda k: torch.as_tensor(batch[k], dtype=torch.float64)  # noqa: E731
    E = geometry.essential_from_pose(t("dR"), t("dT"))
    return E / E.flatten(1).norm(dim=-1)[:, None, None]


def sign_free_distance(E: torch.Tensor, E_gt: torch.Tensor) -> torch.Tensor:
    """E (B, S, 3, 3), E_gt (B, 3, 3), both unit norm -> (B, S) min(|E - E_gt|, |E + E_gt|)."""
    return torch.minimum((E - E_gt[:, None]).flatten(2).norm(dim=-1), (E + E_gt[:, None]).flatten(2).norm(dim=-1))


# ------------------------------------------------------------------------------------- geometry
def test_five_point_recovers_the_true_essential_matrix():
    batch = calibrated(make_batch(B=40, N=20, seed=3, dtype=np.float64))
    pts = batch["coords"][:, :5].double()
    E, valid = geometry.five_point(pts)
    assert E.shape == (40, 10, 3, 3) and valid.shape == (40, 10) and E.dtype == torch.float64
    assert valid.any(-1).all() and (E[~valid] == 0).all()
    h1 = torch.cat([pts[..., :2], torch.ones(40, 5, 1, dtype=torch.float64)], -1)
    h2 = torch.cat([pts[..., 2:], torch.ones(40, 5, 1, dtype=torch.float64)], -1)
    algebraic = torch.einsum("bni,bsij,bnj->bsn", h2, E, h1).abs()
    assert algebraic[valid].max() < 1e-9  # every candidate satisfies the five constraints
    sv = torch.linalg.svdvals(E[valid])
    assert torch.allclose(sv[:, 0], sv[:, 1], atol=1e-6) and sv[:, 2].abs().max() < 1e-6  # essential
    d = sign_free_distance(E, gt_essential(batch)).masked_fill(~valid, 9.0)
    # the true E is among the candidates of every sample (float32 calibrated points: ~1e-5)
    assert d.min(-1).values.max() < 1e-4 and d.min(-1).values.median() < 5e-6


def test_five_point_checks_its_input():
    with pytest.raises(ValueError, match=r"\(B, 5, 4\)"):
        geometry.five_point(torch.zeros(3, 4, 4))
    batch = calibrated(make_batch(B=3, N=10, seed=1))
    pts = batch["coords"][:, :5].clone()
    pts[1, 2, 0] = float("nan")
    pts[2] = pts[2, :1]  # five copies of one correspondence: degenerate
    E, valid = geometry.five_point(pts)
    assert valid[0].any() and not valid[1].any() and not valid[2].any()
    assert torch.isfinite(E).all() and (E[1:] == 0).all()


def test_project_to_essential_has_two_equal_singular_values():
    E = torch.randn(5, 3, 3, dtype=torch.float64)
    P = geometry.project_to_essential(E)
    sv = torch.linalg.svdvals(P)
    assert torch.allclose(sv, torch.tensor([2**-0.5, 2**-0.5, 0.0], dtype=torch.float64).expand(5, 3), atol=1e-12)
    true = gt_essential(make_batch(B=2, N=10))
    assert torch.allclose(geometry.project_to_essential(true), true, atol=1e-12)  # already essential: unchanged
    with pytest.raises(ValueError):
        geometry.project_to_essential(torch.zeros(3, 3))


def test_batch_is_calibrated_and_true_essential_has_zero_residuals():
    raw = make_batch(B=2, N=30, seed=2, pad=5)
    batch = calibrated(raw)
    x = raw["coords"][0, 0].double().numpy()
    want = np.linalg.inv(K) @ np.array([x[0], x[1], 1.0])
    assert np.allclose(batch["coords"][0, 0, :2].double().numpy(), want[:2] / want[2], atol=1e-6)
    assert torch.equal(batch["pixels"], raw["coords"]) and (batch["coords"][:, 25:] == 0).all()
    task = EssentialTask()
    res = task.residuals(gt_essential(raw).float(), batch["coords"])
    assert res[batch["mask"]].max() < 1e-5 and task.true_inliers(batch).sum() == 50
    # a hypothesis stack (B, S, 3, 3) gives (B, S, N), each slice the single-hypothesis residuals
    stack = torch.stack([gt_essential(raw).float(), torch.randn(2, 3, 3)], 1)
    many = task.residuals(stack, batch["coords"])
    assert many.shape == (2, 2, 30) and torch.allclose(many[:, 1], task.residuals(stack[:, 1], batch["coords"]))


def test_essential_options_are_checked():
    from rlsac.errors import RlsacError

    with pytest.raises(RlsacError, match="sampson"):
        get_task("essential", residual="symmetric")
    t = get_task("essential", use_descriptors=False)
    assert t.feature_dim == 5 and t.sample_size == 5 and t.solutions == 10


@dataclass
class TwoLines(LineTask):
    """A two-solution toy solver: the line through the pair, then that line turned by 90 degrees."""

    solutions: int = 2

    def solve(self, pts):
        line, valid = super().solve(pts)
        turned = torch.stack([-line[:, 1], line[:, 0], -(-line[:, 1] * pts[:, 0, 0] + line[:, 0] * pts[:, 0, 1])], -1)
        return torch.stack([turned, line], 1), torch.stack([valid, valid], 1)

    def residuals(self, hyps, coords):
        if hyps.dim() == 3:
            S = hyps.shape[1]
            return super().residuals(hyps.flatten(0, 1), coords.repeat_interleave(S, 0)).view(len(coords), S, -1)
        return super().residuals(hyps, coords)


def test_score_sets_keeps_the_solution_with_most_inliers():
    x = torch.linspace(0, 9, 10)
    coords = torch.stack([x, torch.full_like(x, 2.0)], -1)[None]  # ten points on y = 2
    mask = torch.ones(1, 10, dtype=torch.bool)
    task = TwoLines()
    hyp, valid, res, count = score_sets(task, coords[:, None, :2], coords, mask)  # one set of one instance
    assert hyp.shape == (1, 1, 3) and res.shape == (1, 1, 10)
    assert valid.all() and count.tolist() == [[10]] and res.abs().max() < 1e-6
    assert torch.allclose(hyp.abs(), torch.tensor([[[0.0, 1.0, 2.0]]]), atol=1e-6)  # y = 2, not x = 0
    # when the better candidate is invalid the other one is kept
    task.solve = lambda pts: (TwoLines.solve(task, pts)[0], torch.tensor([[True, False]]))
    hyp, valid, _, count = score_sets(task, coords[:, None, :2], coords, mask)
    assert valid.all() and count.tolist() == [[1]] and torch.allclose(hyp.abs(), torch.tensor([[[1.0, 0.0, 0.0]]]))


def test_refine_returns_an_essential_matrix_close_to_the_truth():
    raw = make_batch(B=3, N=80, noise=0.3, seed=4)
    batch = calibrated(raw)
    E, valid = EssentialTask().refine(batch["coords"], batch["mask"])
    assert valid.all()
    sv = torch.linalg.svdvals(E.double())
    assert torch.allclose(sv[:, 0], sv[:, 1], atol=1e-5) and sv[:, 2].abs().max() < 1e-5
    assert sign_free_distance(E.double()[:, None], gt_essential(raw))[:, 0].max() < 0.02


# ------------------------------------------------------------------------------------- estimators
@pytest.fixture(scope="module")
def noisy():
    return calibrated(make_batch(B=5, noise=0.5, outlier_rate=0.3, seed=5, pad=15))


def _pose_errors(task, out, batch):
    np_batch = {k: (v.numpy() if torch.is_tensor(v) else v) for k, v in batch.items()}
    hyp = out["hyp"].numpy() if torch.is_tensor(out["hyp"]) else out["hyp"]
    return task.errors(hyp, np.asarray(out["valid"]), np.asarray(out["inliers"]), np_batch)


def test_our_ransac_recovers_the_pose(noisy):
    task = EssentialTask(threshold=2.0 / 800)  # 2 px in this synthetic camera (f = 800), noise 0.5 px
    out = ransac(task, noisy, 300, torch.Generator().manual_seed(0))
    e = _pose_errors(task, out, noisy)
    assert out["hyp"].shape == (5, 3, 3) and out["valid"].all() and not out["inliers"][:, 135:].any()
    assert e["err_R"].max() < 2.0 and e["err_t"].max() < 5.0  # the best minimal model (no refit)
    gt = noisy["gt_inliers"]
    assert (out["inliers"].numpy() & gt).sum() / gt.sum() > 0.9


@pytest.mark.parametrize("method", ["ransac", "usac", "magsac"])
def test_opencv_essential_recovers_the_pose(noisy, method):
    task = EssentialTask()
    out = opencv_estimate(task, noisy, method, 1000, seed=1)  # 0.75 px at f = 920: 0.65 px here, noise 0.5 px
    e = _pose_errors(task, out, noisy)
    assert out["hyp"].shape == (5, 3, 3) and out["valid"].all() and not out["inliers"][:, 135:].any()
    assert e["err_R"].max() < 2.0 and e["err_t"].max() < 5.0
    assert np.array_equal(opencv_estimate(task, noisy, method, 1000, seed=1)["inliers"], out["inliers"])


# ------------------------------------------------------------------------------------- end to end
def write_pairs(path, raw: dict) -> str:
    """A prepared two-view file (the fundamental task's format) of make_batch pairs."""
    B = raw["coords"].shape[0]
    data = {k: (raw[k].numpy() if torch.is_tensor(raw[k]) else raw[k]) for k in ("coords", "features", "mask")}
    data.update({k: np.asarray(raw[k], np.float64) for k in ("K1", "K2", "dR", "dT")})
    data.update(size1=np.asarray(raw["size1"], np.int32), size2=np.asarray(raw["size2"], np.int32),
                pair=np.array([f"p{i}" for i in range(B)], dtype=object), scene=np.array(["s"] * B, dtype=object))
    write(path, data, {"kind": KIND, "n_points": data["coords"].shape[1], "split": "test", "scenes": "s"})
    return str(path)


def test_essential_through_train_and_evaluate(workdir):
    data = write_pairs(workdir / "pairs.h5", make_batch(B=4, noise=0.5, outlier_rate=0.4, seed=8))
    run = lambda *a: CliRunner().invoke(cli, [str(x) for x in a])  # noqa: E731
    ev = "reports/eval/essential/hard/s"  # Table E's layout: <regime>/<fold>/<method>/i<iterations>
    r = run("evaluate", "--task", "essential", "--method", "ransac", "--data", data, "--iterations", 200,
            "--out-dir", f"{ev}/ransac/i200", "--no-tracking")
    assert r.exit_code == 0, r.output
    s = json.loads((workdir / ev / "ransac/i200/summary.json").read_text())
    assert s["task"] == "essential" and s["n_instances"] == 4 and s["mAA"] > 0.5
    conf = json.loads((workdir / ev / "ransac/i200/config.json").read_text())
    assert conf["iterations"] == 200 and conf["task_options"]["residual"] == "sampson"
    r = run("train", "--task", "essential", "--data", data, "--val-data", data, "--out", "ess.pt", "--no-tracking",
            "--set", "sac.total_steps=3", "--set", "sac.num_envs=2", "--set", "sac.batch_size=4",
            "--set", "sac.learning_starts=2", "--set", "val_every=2", "--set", "val_iterations=20",
            "--set", "val_instances=2", "--set", "policy.graph_dims=4")
    assert r.exit_code == 0, r.output
    r = run("evaluate", "--task", "essential", "--method", "rlsac", "--checkpoint", "ess.pt", "--data", data,
            "--iterations", 200, "--out-dir", f"{ev}/rlsac/i200", "--no-tracking")
    assert r.exit_code == 0, r.output
    s = json.loads((workdir / ev / "rlsac/i200/summary.json").read_text())
    assert s["method"] == "rlsac" and 0.0 <= s["mAA"] <= 1.0 and s["n_instances"] == 4
    r = run("table", "--which", "essential", "--no-tracking")
    assert r.exit_code == 0, r.output
    md = (workdir / "reports/tableE_essential.md").read_text()
    assert md.startswith("# Table E (not in the paper)") and "4 test pairs pooled over 1 folds" in md
    assert "RANSAC (our batched torch)" in md and "R − rlsac" in md
    # each cell's config.json must match its folder: a result moved under another budget is refused
    cfg = workdir / ev / "ransac/i200/config.json"
    cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "iterations": 100}))
    before = md
    r = run("table", "--which", "essential", "--no-tracking")
    assert r.exit_code == 2 and "holds method 'ransac' (no checkpoint) at 100 iterations" in r.stderr
    assert (workdir / "reports/tableE_essential.md").read_text() == before
    cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "iterations": 200}))
    r = run("plot", "--set", "which=essential", "--no-tracking")
    assert r.exit_code == 0, r.output
    assert (workdir / "reports/figures/essential_iterations.png").is_file()
    r = run("evaluate", "--task", "fundamental", "--method", "rlsac", "--checkpoint", "ess.pt", "--data", data,
            "--iterations", 10, "--out-dir", "ev/wrong", "--no-tracking")
    assert r.exit_code == 2 and "trained for task 'essential'" in r.stderr


def test_the_output_is_the_best_minimal_model_without_refit(noisy):
    from rlsac.estimation.baselines import finalize

    E = gt_essential({k: noisy[k] for k in ("dR", "dT")}).float()
    E = E + 1e-3 * torch.randn(E.shape, generator=torch.Generator().manual_seed(0))  # off the manifold
    valid = torch.ones(5, dtype=torch.bool)
    out = finalize(EssentialTask(), noisy["coords"], noisy["mask"], E, valid)
    assert torch.equal(out["hyp"], E) and out["inliers"].any(-1).all()
    refit = finalize(EssentialTask(refit_output=True), noisy["coords"], noisy["mask"], E, valid)
    assert not torch.equal(refit["hyp"], E)  # the option refits (8-point on the inliers, projected)
