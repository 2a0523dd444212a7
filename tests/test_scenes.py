"""import_scenes on the real Strecha data (one scene), the ground-truth check, and the importer's errors."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from rlsac.data import fundamental
from rlsac.data.scenes import ImportConf, gt_check, import_scenes, mutual_nn, read_camera
from rlsac.data.tutorial import PrepareConf, prepare
from rlsac.errors import RlsacError

# The Strecha copy ships inside the repository (data/strecha); RLSAC_STRECHA points at another copy.
STRECHA = Path(os.environ.get("RLSAC_STRECHA", Path(__file__).resolve().parents[1] / "data" / "strecha"))


def _strecha() -> Path:
    assert (STRECHA / "fountain-P11" / "images" / "0001.jpg").is_file(), (
        f"Strecha data missing at {STRECHA}: data/strecha is tracked in the repository"
    )
    return STRECHA


@pytest.fixture(scope="module")
def fountain(tmp_path_factory):
    """fountain-P11 imported once for the module (about 5 s on 2 cores)."""
    out = tmp_path_factory.mktemp("imported")
    summary = import_scenes(ImportConf(src=str(_strecha()), out=str(out), scenes="fountain-P11"),
                            track=False, progress=False)
    return out, summary


def test_import_layout(fountain):
    out, summary = fountain
    assert summary["images"] == 11 and summary["pairs"] == 55 and summary["kept"] + summary["dropped"] == 55
    assert summary["kept"] >= 30  # the fountain views overlap widely
    d = out / "all" / "fountain-P11"
    assert sorted(p.name for p in (d / "images").iterdir()) == [f"{i:04d}.jpg" for i in range(11)]
    assert (d / "images" / "0003.jpg").read_bytes() == (STRECHA / "fountain-P11" / "images" / "0003.jpg").read_bytes()
    assert not [p for p in (out / "all").iterdir() if p.name.startswith(".")]  # no staging folder left
    cam = read_camera(STRECHA / "fountain-P11" / "cameras" / "0004.jpg.camera")
    with h5py.File(d / "R.h5") as fr, h5py.File(d / "T.h5") as ft:
        np.testing.assert_allclose(fr["0004"][()], cam["R"].T)
        assert ft["0004"].shape == (3, 1)
        np.testing.assert_allclose(ft["0004"][()].ravel(), -cam["R"].T @ cam["C"])
    with h5py.File(d / "matches.h5") as fm, h5py.File(d / "match_conf.h5") as fc, h5py.File(d / "K1_K2.h5") as fk:
        keys = sorted(fm.keys())
        assert "0001-0005" in keys and sorted(fc.keys()) == keys == sorted(fk.keys())
        m, c = fm["0001-0005"][()], fc["0001-0005"][()]
        assert m.shape[1] == 4 and c.shape == (len(m), 1) and (c >= 0).all() and (c <= 1).all()
        assert fk["0001-0005"].shape == (1, 2, 3, 3)
        np.testing.assert_allclose(fk["0001-0005"][0, 0], read_camera(STRECHA / "fountain-P11" / "cameras" /
                                                                      "0001.jpg.camera")["K"])
        assert len(np.unique(m, axis=0)) == len(m)  # duplicate-orientation keypoints deduplicated


def test_ground_truth_agrees_with_magsac(fountain):
    out, _ = fountain
    r = gt_check(out, "all", "fountain-P11", "0001-0005")
    assert r["magsac_inliers"] >= 100
    assert r["median_sampson_inliers"] < 1.0, r


def test_import_then_prepare(fountain, tmp_path):
    out, summary = fountain
    dst = tmp_path / "test.h5"
    s = prepare(PrepareConf(root=str(out), split="all", scenes="fountain-P11", n_points=150, out=str(dst)),
                track=False, progress=False)
    assert s["pairs"] == summary["kept"] and s["skipped"] == 0
    data, attrs = fundamental.read(dst)
    assert data["features"].shape == (s["pairs"], 150, 261) and attrs["root"] == str(out)
    assert (data["size1"] == [1024, 683]).all()
    i = list(data["pair"]).index("0001-0005")
    inl = fundamental.gt_inliers(data, 2.0)
    assert inl[i].mean() > 0.8  # the 150 best ratios of a wide-overlap pair are mostly correct
    assert s["mean_gt_inlier_ratio_sampson_2px"] > 0.3


def test_mutual_nn():
    rng = np.random.default_rng(0)
    d1 = rng.normal(size=(50, 128))
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    perm = rng.permutation(50)
    d2 = d1[perm] + 0.01 * rng.normal(size=(50, 128))
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    i1, i2, snn = mutual_nn(torch.tensor(d1, dtype=torch.float32), torch.tensor(d2, dtype=torch.float32))
    assert len(i1) == 50 and (perm[i2] == i1).all() and (snn < 0.2).all()


def _mini_source(tmp_path, n=2) -> Path:
    src = tmp_path / "src" / "mini"
    (src / "images").mkdir(parents=True)
    (src / "cameras").mkdir()
    for i in range(n):
        name = f"{i + 1:04d}"
        shutil.copyfile(STRECHA / "fountain-P11" / "images" / f"{name}.jpg", src / "images" / f"{name}.jpg")
        shutil.copyfile(STRECHA / "fountain-P11" / "cameras" / f"{name}.jpg.camera",
                        src / "cameras" / f"{name}.jpg.camera")
    return src


def _corrupt_camera(src):
    p = src / "cameras" / "0002.jpg.camera"
    p.write_text("\n".join(p.read_text().splitlines()[:-1]))


def _nan_camera(src):
    p = src / "cameras" / "0002.jpg.camera"
    p.write_text(p.read_text().replace("0 0 0", "nan 0 0", 1))


@pytest.mark.parametrize("breaker, message", [
    (lambda s: (s / "cameras" / "0002.jpg.camera").unlink(), r"0002\.jpg\.camera: no such camera file"),
    (_corrupt_camera, r"0002\.jpg\.camera: camera file has 24 numbers"),
    (_nan_camera, r"0002\.jpg\.camera: camera file contains NaN"),
    (lambda s: (s / "images" / "0002.jpg").write_bytes(b"junk"), r"0002\.jpg: unreadable image"),
    (lambda s: (s / "images" / "0002.jpg").unlink(), r"images: fewer than 2 \.jpg images"),
])
def test_import_errors_leave_nothing(tmp_path, breaker, message):
    _strecha()
    src = _mini_source(tmp_path)
    breaker(src)
    out = tmp_path / "out"
    with pytest.raises(RlsacError, match=message):
        import_scenes(ImportConf(src=str(src.parent), out=str(out)), track=False, progress=False)
    assert not (out / "all").exists() or not any((out / "all").iterdir())


def test_import_missing_source(tmp_path):
    with pytest.raises(RlsacError, match="no such source folder"):
        import_scenes(ImportConf(src=str(tmp_path / "none"), out=str(tmp_path / "out")), track=False)
    src = _mini_source(tmp_path)
    with pytest.raises(RlsacError, match=r"nope: no such scene folder"):
        import_scenes(ImportConf(src=str(src.parent), out=str(tmp_path / "out"), scenes="mini,nope"), track=False)


def test_import_replaces_existing_scene(tmp_path):
    _strecha()
    src = _mini_source(tmp_path)
    out = tmp_path / "out"
    (out / "all" / "mini").mkdir(parents=True)
    (out / "all" / "mini" / "stale.txt").write_text("old")
    s = import_scenes(ImportConf(src=str(src.parent), out=str(out), min_matches=0), track=False, progress=False)
    assert s["kept"] == 1 and not (out / "all" / "mini" / "stale.txt").exists()
    assert sorted(p.name for p in (out / "all").iterdir()) == ["import_summary.json", "mini"]


def test_import_is_byte_identical_on_a_re_run(tmp_path):
    # the import's outputs are a function of its inputs: no duration or version string in any file
    _strecha()
    src = _mini_source(tmp_path)
    files, out = [], tmp_path / "out"
    for _ in range(2):  # the same command twice (the summary names its output folder)
        s = import_scenes(ImportConf(src=str(src.parent), out=str(out), min_matches=0), track=False, progress=False)
        assert s["seconds"] >= 0  # returned for the command's summary line, not written
        files.append({p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()})
    assert files[0] == files[1] and len(files[0]) > 3
    assert b"seconds" not in files[0][Path("all/import_summary.json")]


# ------------------------------------------------------------------ shipped matches (--matches, --write-matches)


def _ship(tmp_path, n=3):
    """A 3-image source imported once with --write-matches: (source parent, the import's files, the shipped file)."""
    _strecha()
    src = _mini_source(tmp_path, n)
    out, shipped = tmp_path / "extracted", tmp_path / "matches.h5"
    s = import_scenes(ImportConf(src=str(src.parent), out=str(out), min_matches=0), track=False, progress=False,
                      write_matches=str(shipped))
    assert s["wrote_matches"] == str(shipped) and s["kept"] == n * (n - 1) // 2
    return src.parent, {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*.h5"))}, shipped


def test_shipped_matches_give_the_same_import_without_sift(tmp_path, monkeypatch):
    src, extracted, shipped = _ship(tmp_path)
    from rlsac.data import scenes

    def no_sift(*a, **k):
        raise AssertionError("SIFT ran although the matches were shipped")

    monkeypatch.setattr(scenes, "detect", no_sift)
    out = tmp_path / "from_shipped"
    s = import_scenes(ImportConf(src=str(src), out=str(out), min_matches=0, matches=str(shipped)), track=False,
                      progress=False)
    assert s["kept"] == 3 and s["per_scene"]["mini"]["mean_features"] > 1000
    assert {p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*.h5"))} == extracted
    with h5py.File(shipped) as f:  # stored as float32 where that is lossless (SIFT's coordinates, the ratios)
        assert f["mini/matches/0001-0002"].dtype == np.float32 and f.attrs["max_features"] == 8000


def test_shipped_matches_are_what_the_import_writes(tmp_path):
    # the file is read, not just checked: a changed match in it is the changed match of the import
    src, _, shipped = _ship(tmp_path)
    with h5py.File(shipped, "r+") as f:
        f["mini/matches/0001-0003"][0, 0] = 12.5
    out = tmp_path / "out"
    import_scenes(ImportConf(src=str(src), out=str(out), min_matches=0, matches=str(shipped)), track=False,
                  progress=False)
    with h5py.File(out / "all" / "mini" / "matches.h5") as f:
        assert f["0001-0003"][0, 0] == 12.5
    # a larger minimum is served from the file (its dropped pairs are absent), a smaller one is not
    s = import_scenes(ImportConf(src=str(src), out=str(out), min_matches=10**6, matches=str(shipped)), track=False,
                      progress=False)
    assert s["kept"] == 0 and s["dropped"] == 3


def _drop_scene(f):
    del f["mini"]


def _other_images(f):
    f["mini"].attrs["images"] = "0001,0002"


def _nan_match(f):
    f["mini/matches/0001-0002"][0, 0] = np.nan


def _unpaired(f):
    del f["mini/match_conf/0001-0002"]


@pytest.mark.parametrize("breaker, conf, message", [
    (None, {"matches": "nope.h5"}, r"--matches .*nope\.h5: no such file"),
    (None, {"max_features": 100}, r"made with max_features=8000, not 100; give --set max_features=8000"),
    (None, {"min_matches": -1}, r"made with min_matches=0, not -1"),
    (_drop_scene, {}, r"no scene mini \(it has none\)"),
    (_other_images, {}, r"scene mini was matched on other images than 3 here"),
    (_nan_match, {}, r"mini/0001-0002: needs finite \(M,4\) matches"),
    (_unpaired, {}, r"matches and match_conf must hold the same pairs"),
])
def test_shipped_matches_errors_write_nothing(tmp_path, breaker, conf, message):
    src, _, shipped = _ship(tmp_path)
    if breaker:
        with h5py.File(shipped, "r+") as f:
            breaker(f)
    out = tmp_path / "out"
    kw = {"src": str(src), "out": str(out), "min_matches": 0, "matches": str(shipped), **conf}
    if conf.get("matches"):
        kw["matches"] = str(tmp_path / conf["matches"])
    with pytest.raises(RlsacError, match=message):
        import_scenes(ImportConf(**kw), track=False, progress=False)
    assert not out.exists()


def test_shipped_matches_not_hdf5_and_write_with_shipped(tmp_path):
    src, _, shipped = _ship(tmp_path, 2)
    junk = tmp_path / "junk.h5"
    junk.write_text("not hdf5")
    out = tmp_path / "out"
    with pytest.raises(RlsacError, match="junk.h5: not an HDF5 file"):
        import_scenes(ImportConf(src=str(src), out=str(out), min_matches=0, matches=str(junk)), track=False)
    with pytest.raises(RlsacError, match="--write-matches packs matches this import extracts"):
        import_scenes(ImportConf(src=str(src), out=str(out), min_matches=0, matches=str(shipped)), track=False,
                      write_matches=str(tmp_path / "again.h5"))
    assert not out.exists() and not (tmp_path / "again.h5").exists()


def test_the_descriptor_table_holds_siftss_bins_at_every_kept_keypoint(fountain):
    """The import describes each image once (rlsac.data.descriptor_table): a lookup gives the bins OpenCV's SIFT
    computes at those keypoints whatever else shares the call; a keypoint it lacks, or another size, gives None."""
    import cv2

    from rlsac.data import descriptor_table

    out, _ = fountain
    d = out / "all" / "fountain-P11"
    with h5py.File(d / "matches.h5") as fm:
        m = fm["0001-0005"][()]
    table = descriptor_table.Table.open(d, 12.0)
    assert table is not None and descriptor_table.Table.open(d, 8.0) is None
    try:
        xy = np.concatenate([m[::-3, 2:4], m[:5, 2:4]])  # image 0005's side, reversed, a few twice
        bins, size = table.lookup("0005", xy)
        img = cv2.imread(str(d / "images" / "0005.jpg"), cv2.IMREAD_GRAYSCALE)
        assert size == (img.shape[1], img.shape[0]) == (1024, 683)
        np.testing.assert_array_equal(bins, descriptor_table.sift_bins(cv2.SIFT_create(), img, xy, 12.0))
        assert bins.shape == (len(xy), 128) and bins.max() > 100
        assert table.lookup("0005", np.array([[0.25, 0.5]])) is None and table.lookup("9999", xy) is None
    finally:
        table.close()


def test_prepare_writes_the_same_bytes_with_and_without_the_table(fountain, tmp_path):
    out, _ = fountain
    conf = dict(root=str(out), split="all", scenes="fountain-P11", n_points=100, pool=400)
    prepare(PrepareConf(**conf, out=str(tmp_path / "with.h5")), track=False, progress=False)
    shutil.copytree(out, tmp_path / "bare")
    (tmp_path / "bare" / "all" / "fountain-P11" / "descriptors.h5").unlink()
    prepare(PrepareConf(**{**conf, "root": str(tmp_path / "bare")}, out=str(tmp_path / "without.h5")), track=False,
            progress=False)
    a, _ = fundamental.read(tmp_path / "with.h5")
    b, _ = fundamental.read(tmp_path / "without.h5")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
