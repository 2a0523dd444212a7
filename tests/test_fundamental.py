"""Fundamental-matrix geometry, task protocol, tutorial pose evaluation and the OpenCV baselines."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rlsac.errors import RlsacError
from rlsac.estimation.baselines import opencv_estimate, ransac
from rlsac.maths import geometry
from rlsac.tasks import get_task
from rlsac.tasks.fundamental import FundamentalTask

W, H = 1000.0, 750.0
K = np.array([[800.0, 0.0, W / 2], [0.0, 820.0, H / 2], [0.0, 0.0, 1.0]])


def rot(axis, deg: float) -> np.ndarray:
    """Rodrigues: rotation by ``deg`` degrees about ``axis``."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    S = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    th = np.radians(deg)
    return np.eye(3) + np.sin(th) * S + (1 - np.cos(th)) * S @ S


def make_batch(B=4, N=150, outlier_rate=0.0, noise=0.0, seed=0, pad=0, dtype=np.float32) -> dict:
    """Two-camera scenes: X2 = R X1 + t, both cameras K; ``pad`` zero rows at the end of each row."""
    rng = np.random.default_rng(seed)
    n = N - pad
    coords = np.zeros((B, N, 4), dtype)
    mask = np.zeros((B, N), bool)
    gt_in = np.zeros((B, N), bool)
    Rs, ts = [], []
    for b in range(B):
        R = rot(rng.normal(size=3), rng.uniform(5, 20))
        t = np.array([1.0, rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)])
        X = np.stack([rng.uniform(-4, 4, 20 * n), rng.uniform(-3, 3, 20 * n), rng.uniform(5, 10, 20 * n)], 1)
        x1, X2 = X @ K.T, X @ R.T + t
        x2 = X2 @ K.T
        x1, x2 = x1[:, :2] / x1[:, 2:], x2[:, :2] / x2[:, 2:]
        ok = (X2[:, 2] > 0) & (x1 >= 0).all(1) & (x1 < [W, H]).all(1) & (x2 >= 0).all(1) & (x2 < [W, H]).all(1)
        pts = np.concatenate([x1, x2], 1)[ok][:n] + rng.normal(scale=noise, size=(n, 4))
        out = rng.choice(n, int(round(n * outlier_rate)), replace=False)
        pts[out, 2:] = rng.uniform([0, 0], [W, H], size=(out.size, 2))
        coords[b, :n], mask[b, :n] = pts, True
        gt_in[b, :n] = True
        gt_in[b, out] = False
        Rs.append(R)
        ts.append(t)
    feats = np.concatenate([coords, rng.uniform(0, 1, (B, N, 257))], -1).astype(np.float32)
    Ks = np.repeat(K[None], B, 0)
    size = np.tile([W, H], (B, 1))
    return {"coords": torch.from_numpy(coords), "mask": torch.from_numpy(mask), "features": torch.from_numpy(feats),
            "K1": Ks, "K2": Ks.copy(), "dR": np.stack(Rs), "dT": np.stack(ts), "size1": size, "size2": size.copy(),
            "gt_inliers": gt_in}


def gt_fundamental(batch) -> torch.Tensor:
    t = lambda k: torch.as_tensor(batch[k], dtype=torch.float64)  # noqa: E731
    return geometry.fundamental_from_pose(t("K1"), t("K2"), t("dR"), t("dT"))


# ----------------------------------------------------------------------------------- solvers
def test_eight_point_exact():
    batch = make_batch(B=6)
    F, valid = FundamentalTask().solve(batch["coords"][:, :8])
    assert F.shape == (6, 3, 3) and F.dtype == torch.float32 and valid.all()
    d = geometry.sampson_distance(F, batch["coords"])  # px; float32 F: ~1e-4 px, more near the epipoles
    assert d.median() < 1e-3 and d.max() < 0.05
    batch = make_batch(B=6, dtype=np.float64)
    Fd, valid = geometry.eight_point(batch["coords"][:, :8])  # float64 in -> float64 out
    assert Fd.dtype == torch.float64 and valid.all()
    h1 = torch.cat([batch["coords"][..., :2], torch.ones(6, 150, 1)], -1)
    h2 = torch.cat([batch["coords"][..., 2:], torch.ones(6, 150, 1)], -1)
    alg = torch.einsum("bni,bij,bnj->bn", h2, Fd, h1)
    assert alg.abs().max() < 1e-7  # x2^T F x1 ~ 0 on all 150 points, not only the 8 sampled
    assert geometry.sampson_distance(Fd, batch["coords"]).max() < 1e-5  # px (normal equations: ~1e-6)
    s = torch.linalg.svdvals(Fd)
    assert (s[:, 2] / s[:, 0]).max() < 1e-6  # rank 2
    cos = (Fd * gt_fundamental(batch)).flatten(1).sum(-1).abs()  # both unit norm: equal up to sign
    assert (cos > 1 - 1e-6).all()


def test_eight_point_least_squares_weights_and_mask():
    batch = make_batch(B=3, noise=0.3, outlier_rate=0.3, pad=20)
    inl = torch.from_numpy(batch["gt_inliers"])
    F, valid = geometry.eight_point(batch["coords"], inl)
    assert valid.all()
    assert (F.double() * gt_fundamental(batch)).flatten(1).sum(-1).abs().min() > 0.99
    # float weights equal to the bool mask give the same F; < 8 positive weights is invalid
    F2, _ = geometry.eight_point(batch["coords"], inl.float())
    assert torch.allclose(F, F2, atol=1e-5)
    few = inl & (torch.arange(150) < 12)
    few[:, :] = False
    few[:, :7] = True
    _, v = geometry.eight_point(batch["coords"], few)
    assert not v.any()


def test_degenerate_samples_are_invalid_without_nan():
    good = make_batch(B=1)["coords"][:, :8]
    s = torch.linspace(0, 1, 8)
    same = torch.tensor([100.0, 200.0, 300.0, 400.0]).repeat(8, 1)[None]
    collinear = torch.stack([100 + 500 * s, 50 + 300 * s, 200 + 400 * s**1.7, 100 + 100 * s**1.7], -1)[None]
    collinear1 = torch.stack([100 + 500 * s, 50 + 300 * s, torch.rand(8) * 900, torch.rand(8) * 700], -1)[None]
    dup = torch.rand(1, 8, 4) * 500
    dup[0, 7] = dup[0, 6]
    nan = torch.rand(1, 8, 4) * 500
    nan[0, 3, 1] = float("nan")
    inf = torch.rand(1, 8, 4) * 500
    inf[0, 2, 3] = float("inf")
    pts = torch.cat([good, same, collinear, collinear1, dup, nan, inf, torch.zeros(1, 8, 4)])
    F, valid = FundamentalTask().solve(pts)
    assert valid.tolist() == [True] + [False] * 7
    assert torch.isfinite(F).all() and (F[1:] == 0).all()
    res = FundamentalTask().residuals(F, make_batch(B=8)["coords"])
    assert torch.isinf(res[1:]).all() and torch.isfinite(res[0]).all()  # zero F: no inliers


def test_sampson_and_symmetric_known_values():
    F = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]])  # rectified pair: y2 = y1
    pts = torch.tensor([[[5.0, 10.0, 40.0, 13.0], [1.0, 2.0, 3.0, 2.0]]])
    # x2^T F x1 = y1 - y2 = -3, both line normals have unit xy-norm: Sampson^2 = 9 / 2
    assert torch.allclose(geometry.sampson_distance(F, pts), torch.tensor([[3 / 2**0.5, 0.0]]))
    assert torch.allclose(geometry.sampson_distance(F * 7, pts, squared=True), torch.tensor([[4.5, 0.0]]))
    assert torch.allclose(geometry.symmetric_epipolar_distance(F, pts, squared=True), torch.tensor([[18.0, 0.0]]))
    assert torch.allclose(FundamentalTask(residual="symmetric").residuals(F, pts), torch.tensor([[3.0, 0.0]]))
    assert torch.allclose(FundamentalTask(residual="sampson_sq").residuals(F, pts), torch.tensor([[4.5, 0.0]]))
    with pytest.raises(RlsacError):
        FundamentalTask(residual="algebraic")


def test_refine_on_inliers_and_iterated():
    batch = make_batch(B=4, noise=0.5, outlier_rate=0.3, seed=2)
    inl = torch.from_numpy(batch["gt_inliers"])
    Fgt = gt_fundamental(batch)
    for it in (0, 2):
        F, valid = FundamentalTask(refine_iterations=it).refine(batch["coords"], inl)
        assert valid.all()
        err = geometry.sampson_distance(F.double(), batch["coords"].double())[inl]
        assert err.abs().mean() < 1.0  # noise 0.5 px per coordinate
        assert (F.double() * Fgt).flatten(1).sum(-1).abs().min() > 0.99
    _, valid = FundamentalTask().refine(batch["coords"], inl & (torch.arange(150) < 5))
    assert not valid.any()


# ---------------------------------------------------------------------------- task protocol
def test_features_and_protocol():
    task = get_task("fundamental")
    batch = make_batch(B=2, pad=10)
    f = task.features(batch)
    assert task.feature_dim == 261 and f.shape == (2, 150, 261)
    assert f[:, :140, :4].abs().max() <= 0.5 + 1e-6 and (f[:, 140:] == 0).all()
    x = batch["coords"][0, 0, 0]
    assert torch.isclose(f[0, 0, 0], (x - W / 2) / W)
    assert torch.equal(f[:, :140, 4:], batch["features"][:, :140, 4:])
    small = FundamentalTask(use_descriptors=False)
    assert small.feature_dim == 5 and small.features(batch).shape == (2, 150, 5)
    assert torch.equal(small.features(batch), f[..., :5])
    blind = FundamentalTask(use_snn=False)  # the SNN ratio hidden from the policy, descriptors kept
    fb = blind.features(batch)
    assert blind.feature_dim == 260 and fb.shape == (2, 150, 260)
    assert torch.equal(fb[..., :4], f[..., :4]) and torch.equal(fb[..., 4:], f[..., 5:])
    assert FundamentalTask(use_snn=False, use_descriptors=False).features(batch).shape == (2, 150, 4)
    assert (task.name, task.sample_size, task.coord_dim, task.threshold) == ("fundamental", 8, 4, 4.0)


# ------------------------------------------------------------------------------- evaluation
def test_pose_errors_known_perturbations():
    batch = make_batch(B=3)
    task = FundamentalTask()
    Kt = torch.as_tensor(batch["K1"])
    R, t = batch["dR"].copy(), batch["dT"].copy()
    R[0] = rot([0.3, -1.0, 0.5], 3.0) @ R[0]  # rotation off by 3 deg
    t[1] = rot(np.cross(t[1], [0.2, 1.0, 0.3]), 5.0) @ t[1]  # direction off by 5 deg (axis perpendicular to t)
    F = geometry.fundamental_from_pose(Kt, Kt, torch.as_tensor(R), torch.as_tensor(t)).numpy()
    F[2] *= -3.0  # scale and sign of F do not matter
    e = task.errors(F, np.ones(3, bool), np.ones((3, 150), bool), batch)
    assert e["err_R"][0] == pytest.approx(3.0, abs=1e-3) and e["err_t"][0] < 3.0
    assert e["err_R"][1] == pytest.approx(0.0, abs=1e-3) and e["err_t"][1] == pytest.approx(5.0, abs=1e-2)
    assert e["err_R"][2] < 1e-3 and e["err_t"][2] < 1e-3


def test_errors_exact_data_and_failures():
    batch = make_batch(B=4)
    task = FundamentalTask()
    F, valid = task.refine(batch["coords"], batch["mask"])
    inl = (task.residuals(F, batch["coords"]) <= task.threshold) & batch["mask"]
    e = task.errors(F, valid, inl, batch)
    assert np.all(e["err_R"] < 1e-2) and np.all(e["err_t"] < 1e-2)
    # failures: invalid flag, < 5 inliers, non-finite F -> maximal errors
    Fn = F.numpy().copy()
    Fn[3] = np.nan
    v = valid.numpy().copy()
    v[1] = False
    few = inl.numpy().copy()
    few[2, 4:] = False
    e = task.errors(Fn, v, few, batch)
    assert e["err_R"].tolist()[1:] == [180.0] * 3 and e["err_t"].tolist()[1:] == [90.0] * 3
    assert e["err_R"][0] < 1e-2
    s = task.summarize(e)
    assert s["n"] == 4 and s["mAA"] == pytest.approx(0.25) and s["mAA_R"] == pytest.approx(0.25)
    assert set(s) == {"mAA_R", "mAA_t", "mAA", "median_R", "median_t", "n"}
    s = task.summarize({"err_R": np.array([0.5, 3.5]), "err_t": np.array([9.5, 1.0])})
    assert s["mAA_R"] == pytest.approx((1.0 + 0.7) / 2) and s["mAA"] == pytest.approx((0.1 + 0.7) / 2)


# -------------------------------------------------------------------------------- baselines
@pytest.fixture(scope="module")
def noisy_batch():
    return make_batch(B=6, noise=0.5, outlier_rate=0.3, seed=5, pad=15)


@pytest.mark.parametrize("method", ["ransac", "usac", "usac_accurate", "magsac"])
def test_opencv_fundamental_recovers_pose(noisy_batch, method):
    out = opencv_estimate(FundamentalTask(), noisy_batch, method, 1000, threshold=1.5)
    assert out["hyp"].shape == (6, 3, 3) and out["valid"].all() and out["inliers"].shape == (6, 150)
    assert not out["inliers"][:, 135:].any()  # padding never an inlier
    gt = noisy_batch["gt_inliers"]
    assert (out["inliers"] & gt).sum() / gt.sum() > 0.8 and (out["inliers"] & ~gt).sum() / (~gt).sum() < 0.1
    e = FundamentalTask().errors(out["hyp"], out["valid"], out["inliers"], noisy_batch)
    assert e["err_R"].max() < 2.0 and np.median(e["err_t"]) < 5.0 and e["err_t"].max() < 15.0
    again = opencv_estimate(FundamentalTask(), noisy_batch, method, 1000, threshold=1.5)
    assert np.array_equal(again["inliers"], out["inliers"])  # same seed, same result


def test_opencv_fundamental_failures():
    batch = make_batch(B=3, seed=1)
    batch["mask"][0, 7:] = False  # 7 correspondences: cannot estimate
    batch["coords"][1] = torch.tensor([100.0, 200.0, 300.0, 400.0])  # all identical
    out = opencv_estimate(FundamentalTask(), batch, "usac", 100)
    assert out["valid"].tolist() == [False, False, True]
    assert not out["inliers"][:2].any() and np.isfinite(out["hyp"]).all()
    with pytest.raises(RlsacError):
        opencv_estimate(FundamentalTask(), batch, "lmeds", 100)


def test_generic_ransac_recovers_pose(noisy_batch):
    # eps = 4 px (paper) also admits the ~3% of outliers lying within 4 px of their epipolar line, which the
    # least-squares refinement feels in t; a 1 px threshold is checked more tightly.
    for task, med_t in ((FundamentalTask(), 10.0), (FundamentalTask(threshold=1.0), 5.0)):
        out = ransac(task, noisy_batch, 200, torch.Generator().manual_seed(0))
        assert out["hyp"].shape == (6, 3, 3) and out["valid"].all()
        assert not out["inliers"][:, 135:].any()
        gt = noisy_batch["gt_inliers"]
        assert (out["inliers"].numpy() & gt).sum() / gt.sum() > 0.8
        e = task.errors(out["hyp"], out["valid"], out["inliers"], noisy_batch)
        assert e["err_R"].max() < 2.0 and np.median(e["err_t"]) < med_t and e["err_t"].max() < 25.0
