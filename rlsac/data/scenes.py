"""Offline scene importer: calibrated image sets (Strecha layout) -> the CVPR 2020 tutorial layout.

Source layout (see data/strecha/README.md): ``<src>/<scene>/images/NNNN.jpg`` and
``<src>/<scene>/cameras/NNNN.jpg.camera`` holding K (3 lines), a distortion line, R camera-to-world
(3 lines), the camera centre C and "W H". World to camera: x_cam = R^T (X - C), so the tutorial's
world-to-camera pose is R_wc = R^T and T = -R^T C.

Per scene: OpenCV SIFT (at most ``max_features`` per image) with RootSIFT descriptors; every image
pair i < j is matched by mutual nearest neighbour under Euclidean descriptor distance, and each
match keeps the SNN ratio d1/d2 of its forward (image 1 -> image 2) match. The output,
``<out>/<split>/<scene>/{matches,match_conf,K1_K2,R,T}.h5`` plus ``images/<id>.jpg`` (copied), is what
``rlsac.data.tutorial.prepare`` reads unchanged. Each scene is built in a hidden staging folder and
renamed into place, so a failure never leaves a half-written scene.
"""

from __future__ import annotations

import os
import platform
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from itertools import combinations
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch

from rlsac.data import descriptor_table, validity
from rlsac.data.fundamental import gt_fundamental, sampson
from rlsac.data.tutorial import PrepareConf
from rlsac.errors import RlsacError
from rlsac.io import atomic_path, check_writable, write_json
from rlsac.progress import tqdm  # no bars unless a person watches (not under CI, not redirected)
from rlsac.tracking import check_store, start_run


@dataclass
class ImportConf:
    src: str = "data/strecha"  # the Strecha copy shipped in the repository (data/strecha/README.md)
    out: str = "data/raw/strecha"  # raw tutorial-layout data, input of `rlsac prepare-cvpr2020`
    split: str = "all"  # one split folder; train/val/test are chosen later by prepare's --scenes
    scenes: str | list[str] = ""  # comma-separated scene names (or a list); "" = every scene folder of src
    max_features: int = 8000  # the CVPR 2020 RANSAC tutorial extracted up to 8000 SIFT keypoints per image
    rootsift: bool = True  # RootSIFT matches better than raw SIFT under Euclidean distance (Arandjelovic 2012)
    store_max_snn: float = 1.0  # keep every mutual NN like the tutorial files; prepare selects the lowest ratios
    # A pair is kept when at least min_matches mutual NN matches have SNN < keep_snn. Measured on Strecha
    # (1034 pairs): 30 / 0.9 drops none; 100 / 0.8 keeps 552 of the 610 pairs whose 150 best matches are
    # >= 30% GT inliers and only 54 of the other 424 (reports in the import summary).
    keep_snn: float = 0.8  # Lowe's ratio-test value: a match below it counts as evidence of overlap
    min_matches: int = 100  # pairs with fewer such matches barely overlap (see the measurement above)
    dedupe: bool = True  # SIFT duplicates keypoints with several orientations: keep one match per coordinate pair
    # "" runs SIFT and matching here; a file (written by --write-matches) gives each pair's matches instead, as the
    # CVPR 2020 tutorial ships its matches: SIFT's low bits depend on the CPU's vendor (reports/platform.md)
    matches: str = ""
    # the keypoint diameter of the scene's descriptor table (rlsac.data.descriptor_table): prepare's default, so
    # that every file prepared from the import looks its descriptors up; 0 writes no table
    descriptor_size: float = PrepareConf.kp_size

    # OpenCV reads max_features=0 as "unlimited": a cap must be given
    ranges = {"max_features": "[1, inf)", "store_max_snn": "(0, inf)", "keep_snn": "(0, inf)",
              "min_matches": "[0, inf)", "descriptor_size": "[0, inf)"}

    def scene_list(self) -> list[str]:
        if isinstance(self.scenes, (list, tuple)):
            return [str(s).strip() for s in self.scenes if str(s).strip()]
        return [s.strip() for s in str(self.scenes).split(",") if s.strip()]


# --- source reading ---------------------------------------------------------------------------------


def read_camera(path: Path) -> dict[str, np.ndarray]:
    """Strecha camera file -> K (3,3), R camera-to-world (3,3), C (3,), size (W, H)."""
    if not path.is_file():
        raise RlsacError(f"{path}: no such camera file")
    try:
        vals = np.array(path.read_text().split(), dtype=np.float64)
    except ValueError:
        raise RlsacError(f"{path}: camera file holds a non-number") from None
    if vals.size != 26:
        raise RlsacError(f"{path}: camera file has {vals.size} numbers, expected 26 (K, distortion, R, C, W H)")
    if not np.isfinite(vals).all():
        raise RlsacError(f"{path}: camera file contains NaN or inf")
    K, R, C = vals[:9].reshape(3, 3), vals[12:21].reshape(3, 3), vals[21:24]
    size = vals[24:26].astype(int)
    # what the numbers mean, as the prepared file's reader checks them (rlsac.data.validity)
    checks = validity.image_sizes(size[None], size[None])[:1] + validity.intrinsics(K[None], size[None], "K")
    problem = validity.first_problem(checks + validity.rotations(R[None], "R"), 1)[0]
    if problem:
        raise RlsacError(f"{path}: {problem}")
    return {"K": K, "R": R, "C": C, "size": size}


def read_image(src: Path, image: str, camera: dict) -> np.ndarray:
    """The grey image ``image`` of source scene ``src``, checked against its camera's size -> (H, W) uint8."""
    path = src / "images" / f"{image}.jpg"
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise RlsacError(f"{path}: unreadable image")
    w, h = camera["size"]
    if (img.shape[1], img.shape[0]) != (w, h):
        raise RlsacError(f"{src / 'cameras' / f'{image}.jpg.camera'}: size {w}x{h} but the image is "
                         f"{img.shape[1]}x{img.shape[0]}")
    return img


def check_scene(src: Path) -> None:
    """Every camera file and every image of source scene ``src`` read and checked: ``import_scenes`` calls it for
    every scene before it creates a folder or starts its MLflow run (issue #28, item 2: a corrupt image or camera
    file of a later scene failed inside the run, leaving it FAILED)."""
    for i in source_images(src):
        read_image(src, i, read_camera(src / "cameras" / f"{i}.jpg.camera"))


def source_images(scene: Path) -> list[str]:
    if not (scene / "images").is_dir():
        raise RlsacError(f"{scene / 'images'}: no such folder")
    ids = sorted(p.stem for p in (scene / "images").glob("*.jpg"))
    if len(ids) < 2:
        raise RlsacError(f"{scene / 'images'}: fewer than 2 .jpg images")
    return ids


# --- features and matching ------------------------------------------------------------------------------


def detect(img: np.ndarray, max_features: int, rootsift: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints (M,2) float64 pixels and descriptors (M,128) float32 with unit L2 norm."""
    sift = cv2.SIFT_create(nfeatures=int(max_features))
    kps, desc = sift.detectAndCompute(img, None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    xy = np.array([k.pt for k in kps], dtype=np.float64)
    desc = desc.astype(np.float32)
    if rootsift:
        desc = np.sqrt(desc / np.maximum(desc.sum(1, keepdims=True), 1e-12))
    else:
        desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    return xy, desc


def mutual_nn(d1: torch.Tensor, d2: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbours of unit descriptors -> (idx1, idx2, forward SNN ratio d1/d2)."""
    if len(d1) < 1 or len(d2) < 2:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    sim = d1 @ d2.T
    top, arg = sim.topk(2, dim=1)
    dist = (2.0 - 2.0 * top).clamp_min(0).sqrt()
    back = sim.argmax(dim=0)
    i1 = torch.arange(len(d1))
    mutual = back[arg[:, 0]] == i1
    snn = dist[:, 0] / dist[:, 1].clamp_min(1e-12)
    return i1[mutual].numpy(), arg[mutual, 0].numpy(), snn[mutual].double().numpy()


def match_pair(xy1, d1, xy2, d2, store_max_snn: float = 1.0, dedupe: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """-> matches (M,4) x1,y1,x2,y2 and SNN ratios (M,), sorted by ratio."""
    i1, i2, snn = mutual_nn(d1, d2)
    keep = snn <= store_max_snn
    m = np.concatenate([xy1[i1[keep]], xy2[i2[keep]]], axis=1)
    snn = snn[keep]
    order = np.argsort(snn, kind="stable")
    m, snn = m[order], snn[order]
    if dedupe and len(m):
        _, first = np.unique(np.round(m, 2), axis=0, return_index=True)  # first = lowest ratio
        first = np.sort(first)
        m, snn = m[first], snn[first]
    return m, snn


# --- import ------------------------------------------------------------------------------------------


def _write_h5(path: Path, items: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for k, v in items.items():
                f.create_dataset(k, data=v)


# --- shipped matches ------------------------------------------------------------------------------------
# One HDF5 file: /<scene>/matches/<pair> (M,4) and /<scene>/match_conf/<pair> (M,1), the kept pairs exactly as the
# import writes them; /<scene> attrs images (the image ids, comma-separated) and mean_features; root attrs the
# ImportConf fields that decide the matches (SHIPPED_FIELDS) and the numeric platform that made them.
SHIPPED_FIELDS = ("max_features", "rootsift", "store_max_snn", "keep_snn", "min_matches", "dedupe")


def read_shipped(path: str | Path, scenes: dict[str, list[str]], conf: ImportConf) -> dict[str, dict]:
    """The shipped matches of ``scenes`` (name -> its image ids), checked against them and ``conf`` before any
    work: {scene: {"matches": {pair: (M,4)}, "match_conf": {pair: (M,1)}, "mean_features": float}}."""
    path = Path(path)
    if not path.is_file():
        raise RlsacError(f"--matches {path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise RlsacError(f"--matches {path}: not an HDF5 file ({e})") from None
    out = {}
    with f:
        for k in SHIPPED_FIELDS:
            made = f.attrs.get(k)
            want = getattr(conf, k)
            # a pair dropped for fewer matches is not in the file: a larger minimum can still be served from it
            if made is None or (type(want)(made) > want if k == "min_matches" else type(want)(made) != want):
                raise RlsacError(f"--matches {path}: made with {k}={made}, not {want}; give "
                                 f"--set {k}={made} or extract anew with --matches ''")
        for scene, ids in scenes.items():
            if scene not in f:
                raise RlsacError(f"--matches {path}: no scene {scene} (it has {', '.join(sorted(f)) or 'none'})")
            g = f[scene]
            if str(g.attrs.get("images", "")) != ",".join(ids):
                raise RlsacError(f"--matches {path}: scene {scene} was matched on other images than {len(ids)} here")
            pairs = {f"{a}-{b}" for a, b in combinations(ids, 2)}
            if "matches" not in g or "match_conf" not in g or set(g["matches"]) != set(g["match_conf"]) or not \
                    set(g["matches"]) <= pairs:
                raise RlsacError(f"--matches {path}: scene {scene}: matches and match_conf must hold the same pairs "
                                 f"of its images")
            m = {k: g["matches"][k][()].astype(np.float64) for k in g["matches"]}
            c = {k: g["match_conf"][k][()].astype(np.float64) for k in g["match_conf"]}
            for k in m:
                if m[k].ndim != 2 or m[k].shape[1] != 4 or c[k].shape != (len(m[k]), 1) or not \
                        (np.isfinite(m[k]).all() and np.isfinite(c[k]).all()):
                    raise RlsacError(f"--matches {path}: {scene}/{k}: needs finite (M,4) matches and (M,1) ratios")
            out[scene] = {"matches": m, "match_conf": c, "mean_features": float(g.attrs.get("mean_features", 0.0))}
    return out


def write_shipped(path: str | Path, dst: Path, scenes: list[str], per_scene: dict, conf: ImportConf,
                  made_on: str) -> None:
    """Pack the import under ``dst`` into the shipped-matches file ``path`` (atomic; gzip, so about half the size)."""
    with atomic_path(Path(path)) as tmp:
        with h5py.File(tmp, "w") as f:
            for k in SHIPPED_FIELDS:
                f.attrs[k] = getattr(conf, k)
            f.attrs["made_on"] = made_on
            for scene in scenes:
                g = f.create_group(scene)
                g.attrs["images"] = ",".join(source_images(Path(conf.src) / scene))
                g.attrs["mean_features"] = per_scene[scene]["mean_features"]
                for name in ("matches", "match_conf"):
                    sub = g.create_group(name)
                    with h5py.File(dst / scene / f"{name}.h5", "r") as src:
                        for k in src:
                            v = src[k][()]
                            # SIFT's coordinates and the ratios are float32 values stored as float64: lossless
                            if np.array_equal(v.astype(np.float32).astype(v.dtype), v):
                                v = v.astype(np.float32)
                            sub.create_dataset(k, data=v, compression="gzip", compression_opts=9, shuffle=True)


def _features_and_matches(src: Path, ids: list[str], cams: dict, conf: ImportConf, progress: bool):
    """SIFT on every image and mutual-NN matching of every pair -> ({pair: (M,4)}, {pair: (M,)}, mean features)."""
    feats = {}
    for i in tqdm(ids, desc=f"{src.name}: SIFT", unit="img", disable=not progress, leave=False):
        xy, d = detect(read_image(src, i, cams[i]), conf.max_features, conf.rootsift)
        feats[i] = (xy, torch.from_numpy(d))
    matches, ratios = {}, {}
    for a, b in tqdm(list(combinations(ids, 2)), desc=f"{src.name}: match", unit="pair", disable=not progress,
                     leave=False):
        matches[f"{a}-{b}"], ratios[f"{a}-{b}"] = match_pair(feats[a][0], feats[a][1], feats[b][0], feats[b][1],
                                                             conf.store_max_snn, conf.dedupe)
    return matches, ratios, float(np.mean([len(f[0]) for f in feats.values()]))


def _import_scene(src: Path, dst_parent: Path, conf: ImportConf, progress: bool, shipped: dict | None) -> dict:
    ids = source_images(src)
    cams = {i: read_camera(src / "cameras" / f"{i}.jpg.camera") for i in ids}
    stage = Path(tempfile.mkdtemp(prefix=f".{src.name}.", suffix=".tmp", dir=dst_parent))
    try:
        (stage / "images").mkdir()
        for i in ids:
            shutil.copyfile(src / "images" / f"{i}.jpg", stage / "images" / f"{i}.jpg")
        if shipped is None:
            found, ratios, mean_features = _features_and_matches(src, ids, cams, conf, progress)
        else:  # the kept pairs as shipped: a pair not in the file was dropped when it was made
            found, ratios = shipped["matches"], {k: v[:, 0] for k, v in shipped["match_conf"].items()}
            mean_features = shipped["mean_features"]
        matches, confs, kk = {}, {}, {}
        dropped = []
        n_kept = []
        for a, b in combinations(ids, 2):
            key = f"{a}-{b}"
            if key not in found or int((ratios[key] < conf.keep_snn).sum()) < conf.min_matches:
                dropped.append(key)
                continue
            m, snn = found[key], ratios[key]
            matches[key] = m.astype(np.float64)
            confs[key] = snn.reshape(-1, 1).astype(np.float64)
            kk[key] = np.stack([cams[a]["K"], cams[b]["K"]])[None]
            n_kept.append(len(m))
        _write_h5(stage / "matches.h5", matches)
        _write_h5(stage / "match_conf.h5", confs)
        _write_h5(stage / "K1_K2.h5", kk)
        _write_h5(stage / "R.h5", {i: cams[i]["R"].T for i in ids})
        _write_h5(stage / "T.h5", {i: (-cams[i]["R"].T @ cams[i]["C"]).reshape(3, 1) for i in ids})
        if conf.descriptor_size > 0:  # described once here, not again by each file prepared from the scene
            descriptor_table.write(stage / descriptor_table.FILE, stage / "images", matches, conf.descriptor_size)
        final = dst_parent / src.name
        if final.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{src.name}.", suffix=".old", dir=dst_parent))
            os.replace(final, old / src.name)
            os.replace(stage, final)
            shutil.rmtree(old)
        else:
            os.replace(stage, final)
    finally:
        if stage.exists():
            shutil.rmtree(stage)
    n_pairs = len(ids) * (len(ids) - 1) // 2
    return {
        "images": len(ids), "pairs": n_pairs, "kept": n_pairs - len(dropped), "dropped": len(dropped),
        "mean_features": mean_features,
        "mean_matches_kept": float(np.mean(n_kept)) if n_kept else 0.0,
    }


def import_scenes(conf: ImportConf, track: bool = True, progress: bool = True,
                  write_matches: str | None = None) -> dict:
    """Import every scene of ``conf.src`` into ``<out>/<split>/<scene>``; return a summary. ``conf.matches``: the
    pairs' matches from that shipped file instead of SIFT; ``write_matches``: pack the result into such a file."""
    t0 = time.time()
    split = Path(str(conf.split))
    if str(conf.split) in ("", ".") or split.is_absolute() or len(split.parts) != 1 or split.name == "..":
        raise RlsacError(f"split {conf.split!r}: one folder name under --out (e.g. all, train), not a path")
    src = Path(conf.src)
    if not src.is_dir():
        raise RlsacError(f"{src}: no such source folder")
    scenes = conf.scene_list() or sorted(p.name for p in src.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not scenes:
        raise RlsacError(f"{src}: no scene folders")
    for s in scenes:
        if not (src / s).is_dir():
            raise RlsacError(f"{src / s}: no such scene folder")
    for s in scenes:
        check_scene(src / s)
    shipped = read_shipped(conf.matches, {s: source_images(src / s) for s in scenes}, conf) if conf.matches else None
    dst = Path(conf.out) / conf.split
    check_writable(dst / "import_summary.json")
    if write_matches:
        if conf.matches:
            raise RlsacError("--write-matches packs matches this import extracts; it takes --matches ''")
        check_writable(Path(write_matches))
    check_store(track, "fundamental")
    created = [p for p in (dst, *dst.parents) if not p.exists()]  # removed again if the import fails
    dst.mkdir(parents=True, exist_ok=True)
    try:
        summary = _import_all(src, dst, scenes, conf, track, progress, t0, shipped)
    except BaseException:
        for p in created:  # deepest first; only folders the import created and left empty
            try:
                p.rmdir()
            except OSError:
                break
        raise
    if write_matches:
        from rlsac import numerics

        write_shipped(write_matches, dst, scenes, summary["per_scene"], conf,
                      f"{numerics.cpu_vendor()} {platform.machine()}, numerics {numerics.mode()}")
        summary["wrote_matches"] = str(write_matches)
    return summary


def _import_all(src: Path, dst: Path, scenes: list[str], conf: ImportConf, track: bool, progress: bool,
                t0: float, shipped: dict | None) -> dict:
    with torch.no_grad(), start_run("fundamental", f"import-scenes {dst}", {**asdict(conf), "scenes": ",".join(scenes)},
                                    tags={"command": "import-scenes"}, enabled=track) as run:
        per_scene = {}
        for s in tqdm(scenes, desc="scenes", unit="scene", disable=not progress):
            per_scene[s] = _import_scene(src / s, dst, conf, progress, shipped[s] if shipped else None)
        tot = {k: sum(v[k] for v in per_scene.values()) for k in ("images", "pairs", "kept", "dropped")}
        summary = {"out": str(dst), **tot, "per_scene": per_scene,
                   "drop_rule": f"fewer than {conf.min_matches} mutual NN matches with SNN < {conf.keep_snn}"}
        # the import's outputs are a function of its inputs: its duration goes to MLflow, not into the summary file
        write_json(dst / "import_summary.json", summary)
        seconds = round(time.time() - t0, 2)
        run.metrics({**{k: float(v) for k, v in tot.items()}, "seconds": seconds})
        run.artifact(dst / "import_summary.json")
    return {**summary, "seconds": seconds}


# --- ground-truth check ----------------------------------------------------------------------------------


def gt_check(root: str | Path, split: str, scene: str, pair: str, max_snn: float = 0.8,
             threshold: float = 1.0, seed: int = 0) -> dict:
    """Sampson distances of a tutorial-layout pair's matches to the ground-truth F, on MAGSAC++ inliers.

    Matches with SNN ratio below ``max_snn`` go through cv2.findFundamentalMat(USAC_MAGSAC,
    ``threshold`` px); returns counts and the median GT Sampson distance (px) of its inliers.
    """
    from rlsac.data.tutorial import Scene

    with Scene(root, split, scene) as sc:
        p = sc.pair(pair)
    sel = p["snn"] < max_snn
    x1, x2 = p["matches"][sel, :2], p["matches"][sel, 2:]
    if len(x1) < 8:
        raise RlsacError(f"{scene}/{pair}: only {len(x1)} matches with SNN < {max_snn}")
    cv2.setRNGSeed(seed)
    F_est, inl = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, threshold, 0.9999, 10000)
    if F_est is None:
        raise RlsacError(f"{scene}/{pair}: MAGSAC++ found no fundamental matrix")
    inl = inl.ravel().astype(bool)
    F = gt_fundamental(p["K1"], p["K2"], p["dR"], p["dT"])
    err = sampson(F, x1, x2)
    return {
        "matches": int(len(x1)), "magsac_inliers": int(inl.sum()),
        "median_sampson_inliers": float(np.median(err[inl])), "median_sampson_all": float(np.median(err)),
        "gt_inlier_ratio_2px": float((err < 2.0).mean()),
    }
