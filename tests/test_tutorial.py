"""prepare() on a tiny synthetic tutorial-layout scene, its error paths, and the prepared-file reader."""

from __future__ import annotations

import json

import cv2
import h5py
import numpy as np
import pytest
import torch

from rlsac.data import fundamental
from rlsac.data.tutorial import PrepareConf, describe, prepare
from rlsac.errors import RlsacError

W, H = 160, 120
IDS = ["im-0", "im1", "im2"]  # one id with a dash: keys are split against the ids in R.h5
# pair -> (number of matches, match_conf stored as (N,) or (N,1))
PAIRS = {"im-0-im1": (40, "flat"), "im-0-im2": (20, "column"), "im1-im2": (5, "flat")}
N_POINTS = 30


def _rot(rvec) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, np.float64))[0]


def _cameras():
    K = np.array([[150.0, 0, W / 2], [0, 150.0, H / 2], [0, 0, 1]])
    R = {IDS[0]: np.eye(3), IDS[1]: _rot([0.02, -0.1, 0.01]), IDS[2]: _rot([-0.03, 0.12, 0.0])}
    T = {IDS[0]: np.zeros((3, 1)), IDS[1]: np.array([[-1.0], [0.1], [0.05]]), IDS[2]: np.array([[1.0], [0.0], [0.1]])}
    return K, R, T


def _project(K, R, T, X):
    x = (K @ (R @ X.T + T)).T
    return x[:, :2] / x[:, 2:]


def make_scene(root, scene="s1", split="val"):
    """Write a tutorial-layout scene; the first half of each pair's matches are exact projections."""
    rng = np.random.default_rng(0)
    d = root / split / scene
    (d / "images").mkdir(parents=True)
    for i in IDS:
        img = cv2.GaussianBlur(rng.integers(0, 255, (H, W), dtype=np.uint8), (5, 5), 1.5)
        cv2.imwrite(str(d / "images" / f"{i}.jpg"), img)
    K, R, T = _cameras()
    truth = {}
    with h5py.File(d / "matches.h5", "w") as fm, h5py.File(d / "match_conf.h5", "w") as fc, \
            h5py.File(d / "K1_K2.h5", "w") as fk:
        for key, (n, form) in PAIRS.items():
            a, b = ("im-0", key[5:]) if key.startswith("im-0-") else key.split("-")
            X = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(6, 10, n)])
            m = np.concatenate([_project(K, R[a], T[a], X), _project(K, R[b], T[b], X)], axis=1)
            n_in = n // 2
            m[n_in:, 2:] = rng.uniform([0, 0], [W, H], size=(n - n_in, 2))  # outliers
            snn = rng.uniform(0.3, 1.0, n)
            fm[key] = m
            fc[key] = snn if form == "flat" else snn[:, None]
            fk[key] = np.stack([K, K])[None]
            truth[key] = {"m": m, "snn": snn, "inlier": np.arange(n) < n_in, "ids": (a, b)}
    with h5py.File(d / "R.h5", "w") as fr, h5py.File(d / "T.h5", "w") as ft:
        for i in IDS:
            fr[i], ft[i] = R[i], T[i]
    return d, truth


@pytest.fixture
def scene(tmp_path):
    return make_scene(tmp_path / "raw")


def _conf(tmp_path, **kw):
    base = {"root": str(tmp_path / "raw"), "split": "val", "scenes": "s1", "n_points": N_POINTS,
            "out": str(tmp_path / "out" / "val.h5")}
    base.update(kw)
    return PrepareConf(**base)


def test_prepare_synthetic(tmp_path, scene):
    d, truth = scene
    summary = prepare(_conf(tmp_path), track=False, progress=False)
    assert summary["pairs"] == 2 and summary["skipped"] == 1
    assert summary["mean_correspondences"] == pytest.approx((30 + 20) / 2)

    data, attrs = fundamental.read(tmp_path / "out" / "val.h5")
    assert attrs["kind"] == "rlsac-fundamental" and attrs["n_points"] == N_POINTS
    assert attrs["split"] == "val" and attrs["scenes"] == "s1" and attrs["n_pairs"] == 2 and attrs["n_skipped"] == 1
    assert "SIFT" in attrs["descriptor"]
    skipped = json.loads(attrs["skipped"])
    assert skipped == {"fewer than 8 correspondences": {"count": 1, "pairs": ["s1/im1-im2"]}}
    assert list(data["pair"]) == ["im-0-im1", "im-0-im2"] and list(data["scene"]) == ["s1", "s1"]

    P, N = 2, N_POINTS
    shapes = {"coords": (P, N, 4), "features": (P, N, 261), "mask": (P, N), "K1": (P, 3, 3), "K2": (P, 3, 3),
              "dR": (P, 3, 3), "dT": (P, 3), "size1": (P, 2), "size2": (P, 2)}
    for k, s in shapes.items():
        assert data[k].shape == s, k
    with h5py.File(tmp_path / "out" / "val.h5") as f:
        assert f["coords"].dtype == np.float32 and f["features"].dtype == np.float32
        assert f["mask"].dtype == bool and f["dR"].dtype == np.float64 and f["size1"].dtype == np.int32
    assert data["mask"].sum(1).tolist() == [30, 20]
    assert (data["size1"] == [W, H]).all() and (data["size2"] == [W, H]).all()

    K, R, T = _cameras()
    for p, key in enumerate(data["pair"]):
        t = truth[key]
        n = int(data["mask"][p].sum())
        order = np.argsort(t["snn"], kind="stable")[:n]
        np.testing.assert_allclose(data["coords"][p, :n], t["m"][order], atol=1e-4)
        f = data["features"][p]
        np.testing.assert_array_equal(f[:n, :4], data["coords"][p, :n])
        np.testing.assert_allclose(f[:n, 4], t["snn"][order], rtol=1e-6)
        assert np.all(np.diff(f[:n, 4]) >= 0)
        np.testing.assert_allclose(np.linalg.norm(f[:n, 5:133], axis=1), 1, atol=1e-4)  # RootSIFT: unit L2
        np.testing.assert_allclose(np.linalg.norm(f[:n, 133:], axis=1), 1, atol=1e-4)
        assert (f[n:] == 0).all() and (data["coords"][p, n:] == 0).all()
        a, b = t["ids"]
        np.testing.assert_allclose(data["dR"][p], R[b] @ R[a].T, atol=1e-12)
        np.testing.assert_allclose(data["dT"][p], (T[b] - R[b] @ R[a].T @ T[a]).ravel(), atol=1e-12)
        np.testing.assert_allclose(data["K1"][p], K) and np.testing.assert_allclose(data["K2"][p], K)
        # the ground-truth F of the file agrees with the exact projections, and only with them
        gt = fundamental.gt_inliers({k: v[p : p + 1] for k, v in data.items()}, 1.0)[0]
        np.testing.assert_array_equal(gt[:n], t["inlier"][order])

        # batching descriptors over pairs gives what one call per pair gives
        img = cv2.imread(str(d / "images" / f"{a}.jpg"), cv2.IMREAD_GRAYSCALE)
        direct = describe(cv2.SIFT_create(), img, data["coords"][p, :n, :2], 12.0, True)
        np.testing.assert_allclose(f[:n, 5:133], direct, atol=1e-6)

    batch = fundamental.to_batch(data, [1, 0])
    assert batch["coords"].dtype == torch.float32 and batch["coords"].shape == (2, N, 4)
    assert batch["features"].shape == (2, N, 261) and batch["mask"].dtype == torch.bool
    assert list(batch["pair"]) == ["im-0-im2", "im-0-im1"] and batch["dT"].shape == (2, 3)
    assert isinstance(batch["K1"], np.ndarray)
    one = fundamental.to_batch(data, 0)
    assert one["coords"].shape == (1, N, 4)


def test_prepare_all_scenes_and_padding_only(tmp_path, scene):
    make_scene(tmp_path / "raw", scene="s2")
    summary = prepare(_conf(tmp_path, scenes="", n_points=100), track=False, progress=False)
    assert summary["pairs"] == 4 and summary["scenes"] == "s1,s2" and summary["full_pairs"] == 0
    data, _ = fundamental.read(tmp_path / "out" / "val.h5")
    assert data["mask"].sum(1).tolist() == [40, 20, 40, 20]


def _no_output(tmp_path):
    out = tmp_path / "out"
    return not out.exists() or not any(out.iterdir())


def _drop_key(path, key):
    with h5py.File(path, "a") as f:
        del f[key]


def _set_key(path, key, value):
    with h5py.File(path, "a") as f:
        del f[key]
        f[key] = value


def _nan_matches(d):
    with h5py.File(d / "matches.h5", "a") as f:
        m = f["im-0-im1"][()]
        m[3, 1] = np.nan
        del f["im-0-im1"]
        f["im-0-im1"] = m


BREAKS = {
    "missing T.h5": (lambda d: (d / "T.h5").unlink(), r"T\.h5: no such file"),
    "missing image": (lambda d: (d / "images" / "im2.jpg").unlink(), r"im2\.jpg: no such image"),
    "unreadable image": (lambda d: (d / "images" / "im1.jpg").write_bytes(b"not a jpeg"), r"im1\.jpg: unreadable"),
    "key missing in K1_K2": (lambda d: _drop_key(d / "K1_K2.h5", "im-0-im2"), r"K1_K2\.h5: missing key 'im-0-im2'"),
    "image missing in R": (lambda d: _drop_key(d / "R.h5", "im2"), r"matches\.h5: key 'im-0-im2'"),
    "image missing in T": (lambda d: _drop_key(d / "T.h5", "im1"), r"T\.h5: missing key 'im1'"),
    "matches wrong shape": (lambda d: _set_key(d / "matches.h5", "im-0-im1", np.zeros((40, 3))),
                            r"matches\.h5: key 'im-0-im1' has shape \(40, 3\)"),
    "conf wrong length": (lambda d: _set_key(d / "match_conf.h5", "im-0-im1", np.zeros(39)),
                          r"match_conf\.h5: key 'im-0-im1' has shape \(39,\)"),
    "K wrong shape": (lambda d: _set_key(d / "K1_K2.h5", "im-0-im1", np.zeros((2, 3, 3))),
                      r"K1_K2\.h5: key 'im-0-im1' has shape"),
    "R wrong shape": (lambda d: _set_key(d / "R.h5", "im1", np.eye(4)), r"R\.h5: key 'im1' has shape"),
    "T wrong shape": (lambda d: _set_key(d / "T.h5", "im1", np.zeros((1, 3, 2))), r"T\.h5: key 'im1' has shape"),
    "NaN in matches": (_nan_matches, r"matches\.h5: key 'im-0-im1' contains NaN"),
    "NaN in R": (lambda d: _set_key(d / "R.h5", "im1", np.full((3, 3), np.nan)), r"R\.h5: key 'im1' contains NaN"),
}


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_prepare_errors_leave_no_output(tmp_path, scene, name):
    d, _ = scene
    breaker, message = BREAKS[name]
    breaker(d)
    with pytest.raises(RlsacError, match=message):
        prepare(_conf(tmp_path), track=False, progress=False)
    assert _no_output(tmp_path)


@pytest.mark.parametrize("kw, message", [
    ({"root": "nowhere"}, "nowhere: no such dataset root"),
    ({"split": "test"}, r"test: no such split folder"),
    ({"scenes": "s1,s9"}, r"s9: no such scene folder"),
    ({"n_points": 4}, "n_points must be at least 8"),
])
def test_prepare_bad_options(tmp_path, scene, kw, message):
    with pytest.raises(RlsacError, match=message):
        prepare(_conf(tmp_path, **kw), track=False, progress=False)
    assert _no_output(tmp_path)


def test_prepare_nothing_to_write(tmp_path, scene):
    with pytest.raises(RlsacError, match="nothing to write"):
        prepare(_conf(tmp_path, min_correspondences=50), track=False, progress=False)
    assert _no_output(tmp_path)


def test_prepare_tracks_a_run(tmp_path, scene, monkeypatch):
    mlflow = pytest.importorskip("mlflow")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    prepare(_conf(tmp_path), track=True, progress=False)
    mlflow.set_tracking_uri(uri)
    runs = mlflow.search_runs(experiment_names=["fundamental"])
    assert len(runs) == 1 and runs.loc[0, "status"] == "FINISHED"
    assert runs.loc[0, "metrics.pairs"] == 2 and runs.loc[0, "metrics.skipped"] == 1
    assert runs.loc[0, "params.n_points"] == str(N_POINTS)


@pytest.fixture
def prepared(tmp_path, scene):
    prepare(_conf(tmp_path), track=False, progress=False)
    return tmp_path / "out" / "val.h5"


def test_read_rejects_bad_files(tmp_path, prepared):
    with pytest.raises(RlsacError, match="no such file"):
        fundamental.read(tmp_path / "missing.h5")
    with h5py.File(prepared, "a") as f:
        f.attrs["kind"] = "rlsac-lines"
    with pytest.raises(RlsacError, match="attribute 'kind'"):
        fundamental.read(prepared)
    with h5py.File(prepared, "a") as f:
        f.attrs["kind"] = "rlsac-fundamental"
        f["features"][0, 0, 7] = np.nan
    with pytest.raises(RlsacError, match="key 'features' contains NaN"):
        fundamental.read(prepared)
    with h5py.File(prepared, "a") as f:
        f["features"][0, 0, 7] = 0
        del f["dT"]
        f["dT"] = np.zeros((2, 3, 1))
    with pytest.raises(RlsacError, match=r"key 'dT' has shape \(2, 3, 1\), expected \(2,3\)"):
        fundamental.read(prepared)
    with h5py.File(prepared, "a") as f:
        del f["dT"]
    with pytest.raises(RlsacError, match="missing key 'dT'"):
        fundamental.read(prepared)


def test_gt_helpers():
    rng = np.random.default_rng(1)
    K, R, T = _cameras()
    X = np.column_stack([rng.uniform(-2, 2, 50), rng.uniform(-1, 1, 50), rng.uniform(5, 9, 50)])
    x1, x2 = _project(K, R["im1"], T["im1"], X), _project(K, R["im2"], T["im2"], X)
    dR = R["im2"] @ R["im1"].T
    dT = (T["im2"] - dR @ T["im1"]).ravel()
    F = fundamental.gt_fundamental(K, K, dR, dT)
    assert np.abs(fundamental.sampson(F, x1, x2)).max() < 1e-6
    assert np.linalg.norm(F) == pytest.approx(1.0)
    # moving x2 by 3 px off its epipolar line: Sampson shares the error between both points,
    # 3 px / sqrt(2) when both epipolar lines have similar gradients, never more than 3 px
    line = F @ np.append(x1[0], 1.0)
    n = line[:2] / np.linalg.norm(line[:2])
    e = fundamental.sampson(F, x1[:1], x2[:1] + 3 * n)[0]
    assert 3 / np.sqrt(2) * 0.8 < e <= 3.0
    Fb = fundamental.gt_fundamental(np.stack([K, K]), np.stack([K, K]), np.stack([dR, dR]), np.stack([dT, dT]))
    np.testing.assert_allclose(Fb[1], F)


def test_fundamental_end_to_end_cli(tmp_path, prepared, monkeypatch):
    """prepared tutorial-layout file -> tiny RLSAC training -> evaluate every method through the CLI."""
    import json

    from click.testing import CliRunner

    from rlsac.cli import cli

    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    sets = ["threads=1", "val_instances=2", "val_iterations=20", "val_every=5", "sac.total_steps=6",
            "sac.num_envs=2", "sac.batch_size=4", "sac.learning_starts=4", "policy.graph_dims=4"]
    args = ["train", "--task", "fundamental", "--data", str(prepared), "--val-data", str(prepared),
            "--out", "ck/f.pt", "--device", "cpu", "--params", "", "--no-tracking"]
    res = runner.invoke(cli, args + [a for s in sets for a in ("--set", s)])
    assert res.exit_code == 0, res.output
    for method in ("ransac", "magsac", "usac", "opencv_ransac", "rlsac"):
        extra = ["--checkpoint", "ck/f.pt", "--batch-size", "2"] if method == "rlsac" else []
        res = runner.invoke(cli, ["evaluate", "--task", "fundamental", "--method", method, "--data", str(prepared),
                                  "--iterations", "30", "--out-dir", f"ev/{method}", "--device", "cpu",
                                  "--no-tracking", *extra])
        assert res.exit_code == 0, (method, res.output)
        s = json.loads((tmp_path / "ev" / method / "summary.json").read_text())
        assert s["n_instances"] >= 2 and 0.0 <= s["mAA_R"] <= 1.0 and 0.0 <= s["mAA_t"] <= 1.0
        assert (tmp_path / "ev" / method / "errors.csv").read_text().count("\n") == s["n_instances"] + 1
