import numpy as np
import pytest
import torch

from rlsac.baselines import oracle, ransac
from rlsac.config import build
from rlsac.data import lines
from rlsac.data.lines import LineDataConf
from rlsac.errors import RlsacError
from rlsac.metrics import line_angle_deg
from rlsac.tasks import get_task


def conf(**kw):
    return build(LineDataConf, {"n_instances": 50, "seed": 0, **kw})


def test_generator_shapes_and_types():
    c = conf(outlier_rate=0.4, n_points=80)
    d = lines.generate(c)
    assert d["points"].shape == (50, 80, 2) and d["points"].dtype == np.float32
    assert d["line"].shape == (50, 3)
    assert d["inlier_mask"].shape == (50, 80) and d["inlier_mask"].dtype == bool
    assert np.allclose(np.linalg.norm(d["line"][:, :2], axis=1), 1.0)
    outliers = d["points"][~d["inlier_mask"]]
    assert (outliers >= 0).all() and (outliers <= c.picture_size).all()


@pytest.mark.parametrize("rate", [0.1, 0.5, 0.7])
@pytest.mark.parametrize("count", ["fixed", "binomial"])
def test_inlier_fraction(rate, count):
    d = lines.generate(conf(outlier_rate=rate, n_instances=200, inlier_count=count))
    assert d["inlier_mask"].mean() == pytest.approx(1 - rate, abs=0.02)


def test_true_inliers_lie_in_the_band():
    c = conf(outlier_rate=0.5)
    d = lines.generate(c)
    dist = np.abs(np.einsum("ind,id->in", d["points"].astype(np.float64), d["line"][:, :2]) + d["line"][:, 2:3])
    assert (dist[d["inlier_mask"]] <= c.band + 1e-5).all()


def test_determinism_by_seed():
    a, b = lines.generate(conf(seed=3)), lines.generate(conf(seed=3))
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    other = lines.generate(conf(seed=4))
    assert not np.array_equal(a["points"], other["points"])
    assert not np.array_equal(a["line"], other["line"])


def test_write_read_round_trip(tmp_path):
    c = conf(n_instances=5)
    d = lines.generate(c)
    path = lines.write(tmp_path / "x.h5", d, c)
    back, attrs = lines.read(path)
    for k in d:
        np.testing.assert_array_equal(back[k], d[k])
    assert attrs["kind"] == "rlsac-lines" and attrs["outlier_rate"] == c.outlier_rate
    batch = lines.to_batch(back, slice(0, 3))
    assert batch["coords"].shape == (3, 100, 2) and batch["mask"].all()
    assert [p.name for p in tmp_path.iterdir()] == ["x.h5"]  # no temporary file left


@pytest.mark.parametrize("bad", [
    {"outlier_rate": 1.0}, {"outlier_rate": -0.1}, {"n_instances": 0}, {"n_points": 0}, {"band": -1.0},
    {"line": "sideways"}, {"extent": "ray"}, {"inlier_count": "some"}, {"n_points": 2, "outlier_rate": 0.9},
])
def test_bad_conf(bad):
    with pytest.raises(RlsacError):
        lines.generate(conf(**bad))


def test_unknown_conf_key():
    with pytest.raises(RlsacError, match="unknown config key"):
        conf(outliers=0.3)


def _same_line(h, ref, tol=1e-5):
    """Lines (3,) equal up to sign."""
    h, ref = np.asarray(h, dtype=np.float64), np.asarray(ref, dtype=np.float64)
    return np.allclose(h, ref, atol=tol) or np.allclose(h, -ref, atol=tol)


def test_line_task_solve_residuals_refine():
    task = get_task("line")
    s = 1 / np.sqrt(2)
    pts = torch.tensor([[[0.0, 0.0], [1.0, 1.0]], [[2.0, 3.0], [2.0, 3.0]]])
    hyps, valid = task.solve(pts)
    assert valid.tolist() == [True, False]  # coincident points are degenerate
    assert _same_line(hyps[0], [-s, s, 0.0])  # y = x
    coords = torch.tensor([[[1.0, 0.0], [3.0, 3.0], [0.0, 2.0]]])
    res = task.residuals(hyps[:1], coords)
    assert res[0].tolist() == pytest.approx([s, 0.0, 2 * s], abs=1e-6)
    # refine on exact points of y = 2x + 1 -> normal (2, -1)/sqrt5, c = 1/sqrt5 (up to sign)
    x = torch.linspace(0, 4, 9)
    on = torch.stack([x, 2 * x + 1], -1)[None]
    mask = torch.ones(1, 9, dtype=torch.bool)
    ref, ok = task.refine(on, mask)
    r5 = np.sqrt(5)
    assert ok.item() and _same_line(ref[0], [2 / r5, -1 / r5, 1 / r5])
    one = torch.zeros(1, 9, dtype=torch.bool)
    one[0, 0] = True
    assert not task.refine(on, one)[1].item()  # < 2 inliers


def test_line_task_errors_and_summary():
    task = get_task("line")
    gt = {"line": np.array([[1.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}
    hyps = np.array([[-1.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    e = task.errors(hyps, np.array([True, False]), None, gt)["err_deg"]
    assert e.tolist() == pytest.approx([0.0, 90.0], abs=1e-6)  # flipped sign ok; invalid = 90 deg
    s = task.summarize({"err_deg": e})
    assert s["mAA"] == pytest.approx(0.5) and s["n"] == 2


def test_ransac_recovers_an_easy_line():
    task = get_task("line")
    d = lines.generate(conf(outlier_rate=0.3, n_instances=20))
    g = torch.Generator().manual_seed(0)
    out = ransac(task, lines.to_batch(d), 100, g)
    assert out["valid"].all()
    err = line_angle_deg(out["hyp"][:, :2].numpy(), d["line"][:, :2])
    assert np.median(err) < 0.5 and err.max() < 2.0
    # found inliers are mostly true inliers
    inl = out["inliers"].numpy()
    assert (inl & d["inlier_mask"]).sum() / inl.sum() > 0.9


def test_oracle_fits_the_true_inliers_only():
    task = get_task("line")
    x = torch.linspace(0, 8, 6)
    inl = torch.stack([x, 0.5 * x + 1], -1)  # y = x/2 + 1 -> normal (1, -2)/sqrt5, c = 2/sqrt5
    out = torch.tensor([[1.0, 9.0], [7.0, 0.5], [3.0, 6.0], [9.0, 9.0]])  # far from it
    coords = torch.cat([inl, out])[None]
    truth = np.array([[True] * 6 + [False] * 4])
    batch = {"coords": coords, "mask": torch.ones(1, 10, dtype=torch.bool), "inlier_mask": truth}
    res = oracle(task, batch)
    r5 = np.sqrt(5)
    assert res["valid"].item() and _same_line(res["hyp"][0], [1 / r5, -2 / r5, 2 / r5])
    assert res["inliers"][0].tolist() == truth[0].tolist()
    one = {**batch, "inlier_mask": np.array([[True] + [False] * 9])}
    assert not oracle(task, one)["valid"].item()  # a single true inlier defines no line
    with pytest.raises(RlsacError, match="true inlier mask"):
        oracle(task, {"coords": coords, "mask": batch["mask"]})


def test_oracle_is_at_least_as_good_as_ransac_on_average():
    task = get_task("line")
    d = lines.generate(conf(outlier_rate=0.6, n_instances=200, seed=7))
    b = lines.to_batch(d)
    g = torch.Generator().manual_seed(0)
    e_ransac = task.errors(ransac(task, b, 150, g)["hyp"].numpy(), np.ones(200, bool), None, d)["err_deg"]
    e_oracle = task.errors(oracle(task, b)["hyp"].numpy(), np.ones(200, bool), None, d)["err_deg"]
    assert np.median(e_oracle) < np.median(e_ransac)
    assert e_oracle.max() < 5.0  # never a wrong line
