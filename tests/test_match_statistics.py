"""The synthetic generator's fitted statistics (rlsac.data.match_statistics) on known values, and the generator's
"fitted" mode drawing what they say."""

import numpy as np
import pytest

from rlsac.data import match_statistics as ms
from rlsac.data.synthetic_pairs import SyntheticPairsConf, generate
from rlsac.errors import RlsacError


def _batch():
    """Two pairs of 4 points in 100 x 50 images: pair 0 has inliers 0, 1; pair 1 inlier 0; point 3 of pair 1 is
    padding. Inliers' SNN 0.1, 0.2, 0.3; outliers' 0.8, 0.9, 1.0 (and 0.5 on the padding, which must not count)."""
    coords = np.zeros((2, 4, 4))
    coords[..., 0], coords[..., 1] = 10.0, 10.0  # image 1: every point in cell (0, 1) of the 8 x 6 grid
    coords[..., 2], coords[..., 3] = 90.0, 40.0  # image 2: cell (7, 4)
    feats = np.zeros((2, 4, 5))
    feats[0, :, 4] = [0.1, 0.2, 0.8, 0.9]
    feats[1, :, 4] = [0.3, 1.0, 1.0, 0.5]
    mask = np.array([[1, 1, 1, 1], [1, 1, 1, 0]], bool)
    inliers = np.array([[1, 1, 0, 0], [1, 0, 0, 1]], bool)  # the padding's label is ignored
    size = np.array([[100, 50], [100, 50]])
    return {"coords": coords, "features": feats, "mask": mask, "size1": size, "size2": size}, inliers


def test_fit_counts_what_the_pairs_hold():
    batch, inliers = _batch()
    st = ms.fit(batch, inliers)
    assert st["pairs"] == 2 and st["points"] == 7
    assert st["inlier_ratio"] == pytest.approx([0.5, 1 / 3], abs=1e-6)
    assert st["snn_inliers"][0] == pytest.approx(0.1) and st["snn_inliers"][-1] == pytest.approx(0.3)
    assert st["snn_inliers"][10] == pytest.approx(0.2)  # the median
    assert st["snn_outliers"][0] == pytest.approx(0.8) and st["snn_outliers"][-1] == pytest.approx(1.0)
    h1, h2 = np.asarray(st["position1_outliers"]), np.asarray(st["position2_outliers"])
    assert h1.shape == ms.GRID and h1[0, 1] == 1.0 and h2[7, 4] == 1.0
    with pytest.raises(ValueError, match="inliers"):
        ms.fit(batch, inliers[:, :3])


def test_the_samplers_draw_the_fitted_distributions():
    rng = np.random.default_rng(0)
    q = list(np.linspace(0.5, 1.0, len(ms.QUANTILES)))  # U(0.5, 1)
    x = ms.sample_snn(rng, q, 20000)
    assert x.min() >= 0.5 and x.max() <= 1.0 and np.mean(x) == pytest.approx(0.75, abs=0.01)
    hist = np.zeros(ms.GRID)
    hist[2, 3] = 1.0
    pos = ms.sample_positions(rng, hist.tolist(), 500)
    assert ((pos[:, 0] >= 2 / 8) & (pos[:, 0] < 3 / 8) & (pos[:, 1] >= 3 / 6) & (pos[:, 1] < 4 / 6)).all()


def test_the_fitted_generator_reproduces_the_statistics():
    hist = np.zeros(ms.GRID)
    hist[0, 0] = hist[7, 5] = 0.5
    st = {"inlier_ratio": [0.2, 0.6], "snn_inliers": list(np.linspace(0.0, 0.4, 21)),
          "snn_outliers": list(np.linspace(0.6, 1.0, 21)), "position1_outliers": hist.tolist(),
          "position2_outliers": hist.tolist()}
    d = generate(SyntheticPairsConf(n_pairs=40, n_points=50, snn="fitted", statistics=st, seed=3))
    ratios = d["inliers"].mean(1)
    assert set(np.round(ratios, 2)) == {0.2, 0.6}  # each pair's ratio is one of the real pairs'
    snn = d["features"][..., 4]
    assert snn[d["inliers"]].max() <= 0.4 and snn[~d["inliers"]].min() >= 0.6
    out = d["coords"][~d["inliers"]] / [1000.0, 750.0, 1000.0, 750.0]
    corner = ((out[:, 0] < 1 / 8) & (out[:, 1] < 1 / 6)) | ((out[:, 0] >= 7 / 8) & (out[:, 1] >= 5 / 6))
    assert corner.all()  # outliers only where the histogram has mass
    with pytest.raises(RlsacError, match="fitted"):
        SyntheticPairsConf(snn="fitted").check()
