import math

import numpy as np
import pytest

from rlsac.maths import metrics


def test_thresholds():
    assert np.allclose(metrics.thresholds(0.5), np.arange(1, 11) * 0.05)


def test_maa_hand_computed():
    # thresholds 0.05, 0.10, ..., 0.50: 0.02 passes all 10, 0.12 passes 8 (0.15..0.5), 0.55 none.
    # accuracy per threshold: 1/3, 1/3, then 2/3 eight times -> (2/3 + 16/3) / 10 = 0.6
    assert metrics.mAA([0.02, 0.12, 0.55], 0.5) == pytest.approx(0.6)
    assert metrics.mAA([0.0, 0.0], 0.5) == pytest.approx(1.0)
    assert metrics.mAA([1.0, 2.0], 0.5) == pytest.approx(0.0)
    # a single error of 0.25 passes 6 of 10 thresholds (0.25, 0.30, ..., 0.50)
    assert metrics.mAA([0.25], 0.5) == pytest.approx(0.6)
    # 10 deg limit, 5 thresholds: an error of 4 passes 4, 6, 8, 10 -> 0.8
    assert metrics.mAA([4.0], 10.0, n=5) == pytest.approx(0.8)


def test_maa_failures_and_empty():
    assert metrics.mAA([0.02, np.nan], 0.5) == pytest.approx(0.5)
    assert metrics.mAA([0.02, np.inf], 0.5) == pytest.approx(0.5)
    assert math.isnan(metrics.mAA([], 0.5))


def test_paired_bootstrap_known_difference():
    a = np.full(200, 0.02)  # hit at every threshold
    b = np.concatenate([np.full(100, 0.02), np.full(100, 1.0)])  # half the instances missed
    d, lo, hi = metrics.paired_bootstrap_maa(a, b, 0.5, seed=1)
    assert d == pytest.approx(0.5)
    assert 0.35 < lo < 0.5 < hi < 0.65
    assert metrics.paired_bootstrap_maa(a, a, 0.5) == (0.0, 0.0, 0.0)
    d, lo, hi = metrics.paired_bootstrap_maa(b, a, 0.5)  # antisymmetric
    assert d == pytest.approx(-0.5) and hi < 0
    assert metrics.paired_bootstrap_maa(a, b, 0.5, seed=3) == metrics.paired_bootstrap_maa(a, b, 0.5, seed=3)


def test_paired_bootstrap_rejects_unpaired():
    with pytest.raises(ValueError, match="one length"):
        metrics.paired_bootstrap_maa([0.1, 0.2], [0.1], 0.5)


def test_seed_bootstrap_covers_training_noise():
    """Two seeds of a: one solves every instance, one none; b solves half. The seed mean ties b, but which seeds a
    draw holds moves the difference by +-0.5: the interval must reach both ends (a pairs-only interval would not)."""
    inf = np.inf
    a = np.array([[0.0] * 6, [inf] * 6])
    b = np.array([0.0, inf] * 3)
    got = metrics.seed_bootstrap_maa(a, b, 10.0, n_boot=4000)
    assert got["diff"] == pytest.approx(0.0) and got["mean_a"] == pytest.approx(0.5)
    assert got["lo"] <= -0.5 and got["hi"] >= 0.5  # a's seed draw (+-0.5) plus b's instance draw
    one = metrics.seed_bootstrap_maa(a[:1], b, 10.0, n_boot=4000)  # a single seed: the pairs' noise only
    assert one["diff"] == pytest.approx(0.5) and one["lo"] > 0
    assert got["sd_a"] == pytest.approx(math.sqrt(0.5)) and got["sd_b"] == 0.0
    assert got["p_improve"] == pytest.approx(0.5)  # one seed above b, one below


def test_seed_bootstrap_resamples_within_strata():
    """The difference sits in stratum 0 (a solves both its instances, b neither) and is nil in stratum 1: drawing
    instances within strata keeps two of stratum 0 in every draw, so the interval is the point (+0.5)."""
    a = np.array([[0.0, 0.0, 0.0, np.inf]])
    b = np.array([[np.inf, np.inf, 0.0, np.inf]])
    got = metrics.seed_bootstrap_maa(a, b, 10.0, strata=[0, 0, 1, 1], n_boot=500)
    assert got["diff"] == pytest.approx(0.5) and got["lo"] == pytest.approx(0.5) and got["hi"] == pytest.approx(0.5)
    assert got["p_improve"] == pytest.approx(0.75)  # wins stratum 0, ties stratum 1
    pooled = metrics.seed_bootstrap_maa(a, b, 10.0, n_boot=500)
    assert pooled["lo"] < 0.5 < pooled["hi"]  # without strata the instances' mix varies
    with pytest.raises(ValueError, match="one M"):
        metrics.seed_bootstrap_maa(a, b[:, :3], 10.0)
    with pytest.raises(ValueError, match="strata"):
        metrics.seed_bootstrap_maa(a, b, 10.0, strata=[0, 1])


def test_median():
    assert metrics.median([3.0, 1.0, 2.0]) == 2.0
    assert metrics.median([1.0, 2.0, 3.0, 4.0]) == 2.5
    assert metrics.median([1.0, np.nan, 3.0]) == 3.0  # NaN counts as an infinite error
    assert math.isnan(metrics.median([]))


def _unit(deg):
    r = np.radians(deg)
    return np.array([np.cos(r), np.sin(r)])


def test_line_angle_known_values_and_symmetry():
    a = np.array([1.0, 0.0])
    assert metrics.line_angle_deg(a, np.array([0.0, 1.0])) == pytest.approx(90.0)
    assert metrics.line_angle_deg(a, a) == pytest.approx(0.0, abs=1e-6)
    assert metrics.line_angle_deg(a, _unit(30)) == pytest.approx(30.0)
    assert metrics.line_angle_deg(_unit(30), a) == pytest.approx(30.0)
    # undirected: a flipped normal is the same line, 150 deg between normals is 30 deg between lines
    assert metrics.line_angle_deg(a, -a) == pytest.approx(0.0, abs=1e-6)
    assert metrics.line_angle_deg(a, _unit(150)) == pytest.approx(30.0)
    # scale does not matter, and it broadcasts over rows
    out = metrics.line_angle_deg(np.stack([3 * a, -2 * _unit(45)]), np.stack([_unit(10), a]))
    assert out == pytest.approx([10.0, 45.0])


def _rot_z(deg):
    r = np.radians(deg)
    c, s = np.cos(r), np.sin(r)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_rotation_error():
    assert metrics.rotation_error_deg(np.eye(3), np.eye(3)) == pytest.approx(0.0, abs=1e-6)
    assert metrics.rotation_error_deg(_rot_z(10), np.eye(3)) == pytest.approx(10.0)
    assert metrics.rotation_error_deg(np.eye(3), _rot_z(-25)) == pytest.approx(25.0)
    assert metrics.rotation_error_deg(_rot_z(40), _rot_z(10)) == pytest.approx(30.0)
    assert metrics.rotation_error_deg(_rot_z(180), np.eye(3)) == pytest.approx(180.0)
    batch = metrics.rotation_error_deg(np.stack([_rot_z(5), _rot_z(90)]), np.stack([np.eye(3), np.eye(3)]))
    assert batch == pytest.approx([5.0, 90.0])


def test_translation_error_ignores_sign_and_scale():
    x = np.array([1.0, 0.0, 0.0])
    assert metrics.translation_error_deg(x, -2 * x) == pytest.approx(0.0, abs=1e-6)
    assert metrics.translation_error_deg(x, np.array([1.0, 1.0, 0.0])) == pytest.approx(45.0)
    assert metrics.translation_error_deg(x, np.array([-1.0, 1.0, 0.0])) == pytest.approx(45.0)
    assert metrics.translation_error_deg(x, np.array([0.0, 0.0, 3.0])) == pytest.approx(90.0)
    # column vectors (3, 1) are accepted
    assert metrics.translation_error_deg(x[:, None], np.array([[1.0], [1.0], [0.0]])) == pytest.approx(45.0)


def test_seed_bootstrap_with_paired_seeds_draws_the_same_seeds_for_both():
    """Two checkpoints of two runs: run 0's last actor loses one of six instances its kept actor solves, run 1's actors
    solve none. Paired, no draw's difference is below 0 (the instance draw alone moves it up to a few sixths); unpaired,
    the seeds' own spread (+-0.5) swamps it."""
    inf = np.inf
    kept = np.array([[0.0] * 6, [inf] * 6])
    last = np.array([[0.0] * 5 + [inf], [inf] * 6])
    paired = metrics.seed_bootstrap_maa(kept, last, 10.0, n_boot=2000, paired_seeds=True)
    assert paired["diff"] == pytest.approx(1 / 12) and paired["lo"] == 0.0 and paired["hi"] < 0.4
    unpaired = metrics.seed_bootstrap_maa(kept, last, 10.0, n_boot=2000)
    assert unpaired["lo"] <= -0.4 and unpaired["hi"] >= 0.4
    with pytest.raises(ValueError, match="as many seeds"):
        metrics.seed_bootstrap_maa(kept, last[:1], 10.0, paired_seeds=True)
