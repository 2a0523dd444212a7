"""Reader for the CVPR 2020 RANSAC-tutorial layout and ``prepare``: one h5 of fixed-size pairs per split.

Layout read (exactly the tutorial's): ``<root>/<split>/<scene>/`` holding
    matches.h5     "img1-img2" -> (N,4) x1, y1, x2, y2 in pixels
    match_conf.h5  same keys -> SNN ratio (N,) or (N,1), lower is better
    K1_K2.h5       same keys -> (1,2,3,3): [0][0] = K1, [0][1] = K2
    R.h5           image id -> (3,3) world-to-camera rotation
    T.h5           image id -> (3,1) world-to-camera translation
    images/<id>.jpg
Relative pose of a pair: dR = R2 R1^T, dT = T2 - dR T1.

Descriptors. The tutorial files keep only coordinates, so each endpoint gets a SIFT descriptor
computed by OpenCV at the given location with a fixed keypoint size (``kp_size``, default 12 px
diameter, i.e. a 4x4-cell window of about 72 px on the octave-0 layer, sigma 1.6) and upright
orientation (angle 0: the photos are upright and the original keypoint orientations are not
stored). RootSIFT (L1-normalise, square root) is applied by default. OpenCV's ``compute`` with
provided keypoints keeps their order and number and describes each independently, so we call it
once per image per scene with the keypoints of every pair that image belongs to; the Gaussian
pyramid is then built once per image rather than once per pair.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import time
from collections import defaultdict
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np

from rlsac.data import descriptor_table, sift_record
from rlsac.data.fundamental import KIND, N_FEATURES, gt_inliers
from rlsac.errors import RlsacError
from rlsac.io import atomic_path, open_h5, read_array, write_json
from rlsac.progress import tqdm  # no bars unless a person watches (not under CI, not redirected)
from rlsac.tracking import data_label, start_run

FILES = ("matches.h5", "match_conf.h5", "K1_K2.h5", "R.h5", "T.h5")


@dataclass
class PrepareConf:
    root: str = "data/raw/strecha"  # where `rlsac import-scenes` writes the tutorial layout
    split: str = "all"  # import-scenes puts every scene under one split folder named "all"
    scenes: str = ""  # comma-separated scene names; "" = every scene folder of the split
    n_points: int = 150  # the paper's N for fundamental-matrix estimation (RLSAC Sec. 4.3)
    out: str = "data/fundamental/val.h5"  # one file per split, consumed by the environment and the baselines
    min_correspondences: int = 8  # fewer cannot feed the 8-point algorithm, so the pair is skipped
    # SIFT keypoint diameter (px). Inlier-vs-outlier AUC of the descriptor distance on 21 Strecha pairs:
    # size 4: 0.84, 8: 0.85, 12: 0.87, 16: 0.87, 24: 0.86, 32: 0.84 (the SNN ratio alone: 0.80).
    kp_size: float = 12.0  # the flat optimum of the measurement above
    rootsift: bool = True  # RootSIFT compares better than raw SIFT under Euclidean distance (Arandjelovic 2012)
    max_pairs_per_scene: int = 0  # 0 = every pair; a cap (first pairs in key order) keeps huge scenes quick
    gt_threshold: float = 2.0  # Sampson distance (px) under which a correspondence counts as a GT inlier in the summary

    # checked by rlsac.config.build (n_points, min_correspondences and kp_size by check())
    ranges = {"max_pairs_per_scene": "[0, inf)", "gt_threshold": "(0, inf)"}
    # 0 = the n_points lowest-SNN matches (the paper's and the tutorial's selection). P > n_points = n_points
    # matches drawn, seeded by the pair key, from the P lowest-SNN ones: the hard regime of the fold benchmark,
    # whose inlier ratio falls into the range of the tutorial data (measured in reports/folds.md).
    pool: int = 0
    # "all" pairs, or the "train" / "val" part of a split by a stable hash of "scene/pair": the fold benchmark
    # validates on a held-out part of its training buildings (val_fraction of their pairs).
    holdout: str = "all"
    val_fraction: float = 0.2

    def scene_list(self) -> list[str]:
        if isinstance(self.scenes, (list, tuple)):
            return [str(s).strip() for s in self.scenes if str(s).strip()]
        return [s.strip() for s in str(self.scenes).split(",") if s.strip()]

    def check(self) -> None:
        if int(self.n_points) < 8:
            raise RlsacError(f"n_points must be at least 8, got {self.n_points}")
        if int(self.min_correspondences) < 8:
            raise RlsacError(f"min_correspondences must be at least 8, got {self.min_correspondences}")
        if not float(self.kp_size) > 0:
            raise RlsacError(f"kp_size must be positive, got {self.kp_size}")
        if int(self.pool) != 0 and int(self.pool) < int(self.n_points):
            raise RlsacError(f"pool must be 0 or at least n_points ({self.n_points}), got {self.pool}")
        if self.holdout not in ("all", "train", "val"):
            raise RlsacError(f"holdout must be 'all', 'train' or 'val', got {self.holdout!r}")
        if not 0.0 < float(self.val_fraction) < 1.0:
            raise RlsacError(f"val_fraction must be in (0, 1), got {self.val_fraction}")
        if int(self.max_pairs_per_scene) < 0:
            raise RlsacError(f"max_pairs_per_scene must be >= 0 (0 = every pair), got {self.max_pairs_per_scene}")


def pair_unit(scene: str, key: str, salt: str = "") -> float:
    """A stable number in [0, 1) per pair (sha256 of "salt/scene/key"): hold-out splits and draws that
    do not depend on the order of pairs or scenes, nor on Python's salted hash."""
    digest = hashlib.sha256(f"{salt}/{scene}/{key}".encode()).digest()
    return int.from_bytes(digest[:8], "little") / 2.0**64


# --- reading the layout ---------------------------------------------------------------------------


def scene_dir(root: str | Path, split: str, scene: str) -> Path:
    root = Path(root)
    if not root.is_dir():
        raise RlsacError(f"{root}: no such dataset root")
    if not (root / split).is_dir():
        raise RlsacError(f"{root / split}: no such split folder")
    d = root / split / scene
    if not d.is_dir():
        raise RlsacError(f"{d}: no such scene folder")
    for name in FILES:
        if not (d / name).is_file():
            raise RlsacError(f"{d / name}: no such file")
    if not (d / "images").is_dir():
        raise RlsacError(f"{d / 'images'}: no such folder")
    return d


def list_scenes(root: str | Path, split: str) -> list[str]:
    d = Path(root) / split
    if not d.is_dir():
        raise RlsacError(f"{d}: no such split folder")
    return sorted(p.name for p in d.iterdir() if p.is_dir() and not p.name.startswith("."))


def split_key(key: str, ids: set[str], where: str) -> tuple[str, str]:
    """'img1-img2' -> ('img1', 'img2'), accepting ids that themselves contain '-'."""
    parts = key.split("-")
    for i in range(1, len(parts)):
        a, b = "-".join(parts[:i]), "-".join(parts[i:])
        if a in ids and b in ids:
            return a, b
    raise RlsacError(f"{where}: key '{key}' does not split into two image ids present in R.h5")


class Scene:
    """Open h5 files of one tutorial scene; ``pair(key)`` reads and checks one pair."""

    def __init__(self, root: str | Path, split: str, name: str):
        self.name = name
        self.dir = scene_dir(root, split, name)
        self.files = {}
        try:
            for n in FILES:
                self.files[n] = open_h5(self.dir / n)
        except Exception:
            self.close()
            raise
        self.ids = set(self.files["R.h5"].keys())
        self._pose: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def close(self) -> None:
        for f in self.files.values():
            f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def keys(self) -> list[str]:
        return sorted(self.files["matches.h5"].keys())

    def pose(self, image: str) -> tuple[np.ndarray, np.ndarray]:
        if image not in self._pose:
            R = read_array(self.files["R.h5"], image, (3, 3)).astype(np.float64)
            T = read_array(self.files["T.h5"], image).astype(np.float64)
            if T.size != 3 or T.ndim not in (1, 2) or (T.ndim == 2 and T.shape != (3, 1)):
                raise RlsacError(f"{self.files['T.h5'].filename}: key '{image}' has shape {T.shape}, expected (3,1)")
            self._pose[image] = (R, T.reshape(3))
        return self._pose[image]

    def pair(self, key: str) -> dict:
        f = self.files
        id1, id2 = split_key(key, self.ids, f["matches.h5"].filename)
        m = read_array(f["matches.h5"], key, (None, 4)).astype(np.float64)
        conf = read_array(f["match_conf.h5"], key)
        if not (conf.shape == (m.shape[0],) or conf.shape == (m.shape[0], 1)):
            raise RlsacError(
                f"{f['match_conf.h5'].filename}: key '{key}' has shape {conf.shape}, expected ({m.shape[0]},) "
                f"or ({m.shape[0]},1) to match matches.h5"
            )
        K = read_array(f["K1_K2.h5"], key, (1, 2, 3, 3)).astype(np.float64)
        R1, T1 = self.pose(id1)
        R2, T2 = self.pose(id2)
        dR = R2 @ R1.T
        return {
            "key": key, "id1": id1, "id2": id2, "matches": m, "snn": conf.reshape(-1).astype(np.float64),
            "K1": K[0, 0], "K2": K[0, 1], "dR": dR, "dT": T2 - dR @ T1,
        }


def load_gray(path: Path) -> np.ndarray:
    if not path.is_file():
        raise RlsacError(f"{path}: no such image")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None or img.size == 0:
        raise RlsacError(f"{path}: unreadable image")
    return img


def describe(sift, img: np.ndarray, xy: np.ndarray, size: float, rootsift: bool,
             recorded: dict | None = None) -> np.ndarray:
    """SIFT descriptors (M,128) float32 at the given pixel locations, upright, fixed size. ``recorded``: the
    record's raw descriptors of this image (rlsac.data.sift_record), put back before the normalisation."""
    return finish(descriptor_table.sift_bins(sift, img, xy, size), xy, rootsift, recorded)


def finish(bins: np.ndarray, xy: np.ndarray, rootsift: bool, recorded: dict | None = None) -> np.ndarray:
    """Raw SIFT bins (M,128) at ``xy`` -> the descriptors: the record's bins put back (rlsac.data.sift_record), then
    RootSIFT or L2 normalisation."""
    if len(xy) == 0:
        return np.zeros((0, 128), np.float32)
    desc = sift_record.apply(bins.astype(np.float32), xy, recorded or {})
    if rootsift:
        desc = np.sqrt(desc / np.maximum(desc.sum(1, keepdims=True), 1e-12))
    else:
        desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
    return desc


# --- prepare -----------------------------------------------------------------------------------------


def _prepare_scene(scene: Scene, conf: PrepareConf, skipped: dict, progress: bool) -> list[dict]:
    N = int(conf.n_points)
    keys = scene.keys()
    if conf.max_pairs_per_scene and conf.max_pairs_per_scene > 0:
        keys = keys[: int(conf.max_pairs_per_scene)]
    if conf.holdout != "all":
        keys = [k for k in keys if (pair_unit(scene.name, k, "holdout") < conf.val_fraction) == (conf.holdout == "val")]
    pairs = []
    for key in tqdm(keys, desc=f"{scene.name}: pairs", unit="pair", disable=not progress, leave=False):
        p = scene.pair(key)
        n = len(p["matches"])
        if n < conf.min_correspondences:
            skipped[f"fewer than {conf.min_correspondences} correspondences"].append(f"{scene.name}/{key}")
            continue
        order = np.argsort(p["snn"], kind="stable")
        if conf.pool and min(n, conf.pool) > N:  # N of the `pool` lowest-SNN matches, drawn with the pair's own seed
            rng = np.random.default_rng(int(pair_unit(scene.name, key, "pool") * 2**63))
            order = order[np.sort(rng.choice(min(n, int(conf.pool)), N, replace=False))]  # still in SNN order
        order = order[:N]
        p["matches"], p["snn"], p["n"] = p["matches"][order], p["snn"][order], len(order)
        pairs.append(p)

    # one SIFT compute call per image over every pair it belongs to
    sift = cv2.SIFT_create()
    uses: dict[str, list[tuple[int, int]]] = defaultdict(list)  # image id -> (pair index, side)
    for i, p in enumerate(pairs):
        uses[p["id1"]].append((i, 0))
        uses[p["id2"]].append((i, 1))
    for p in pairs:
        p["desc"] = [None, None]
    table = descriptor_table.Table.open(scene.dir, float(conf.kp_size))  # the import's, where it has one
    try:
        for image in tqdm(sorted(uses), desc=f"{scene.name}: descriptors", unit="img", disable=not progress,
                          leave=False):
            xy = np.concatenate([pairs[i]["matches"][:, 2 * s : 2 * s + 2] for i, s in uses[image]])
            found = table.lookup(image, xy) if table is not None else None
            if found is not None:
                bins, (w, h) = found
            else:
                img = load_gray(scene.dir / "images" / f"{image}.jpg")
                h, w = img.shape[:2]
                bins = descriptor_table.sift_bins(sift, img, xy, float(conf.kp_size))
            _place(pairs, uses[image], finish(bins, xy, bool(conf.rootsift),
                                              sift_record.recorded(scene.name, image, conf.kp_size)), (w, h))
    finally:
        if table is not None:
            table.close()
    for p in pairs:
        p["scene"] = scene.name
    return pairs


def _place(pairs: list[dict], uses: list[tuple[int, int]], desc: np.ndarray, size: tuple[int, int]) -> None:
    """One image's descriptors, in the order of its ``uses`` (pair index, side), into those pairs."""
    w, h = size
    start = 0
    for i, s in uses:
        n = pairs[i]["n"]
        pairs[i]["desc"][s] = desc[start : start + n]
        pairs[i][f"size{s + 1}"] = (w, h)
        start += n


def _assemble(pairs: list[dict], N: int) -> dict[str, np.ndarray]:
    P = len(pairs)
    coords = np.zeros((P, N, 4), np.float32)
    feats = np.zeros((P, N, N_FEATURES), np.float32)
    mask = np.zeros((P, N), bool)
    for i, p in enumerate(pairs):
        n = p["n"]
        coords[i, :n] = p["matches"]
        feats[i, :n, :4] = p["matches"]
        feats[i, :n, 4] = p["snn"]
        feats[i, :n, 5:133] = p["desc"][0]
        feats[i, :n, 133:261] = p["desc"][1]
        mask[i, :n] = True
    return {
        "coords": coords, "features": feats, "mask": mask,
        "K1": np.stack([p["K1"] for p in pairs]).astype(np.float64),
        "K2": np.stack([p["K2"] for p in pairs]).astype(np.float64),
        "dR": np.stack([p["dR"] for p in pairs]).astype(np.float64),
        "dT": np.stack([p["dT"] for p in pairs]).astype(np.float64),
        "size1": np.array([p["size1"] for p in pairs], np.int32).reshape(P, 2),
        "size2": np.array([p["size2"] for p in pairs], np.int32).reshape(P, 2),
        "pair": np.array([p["key"] for p in pairs], dtype=object),
        "scene": np.array([p["scene"] for p in pairs], dtype=object),
    }


def write(path: str | Path, data: dict[str, np.ndarray], attrs: dict) -> Path:
    """Write the prepared arrays atomically (no partial file on error)."""
    str_t = h5py.string_dtype("utf-8")
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for k, v in data.items():
                if v.dtype == object:
                    f.create_dataset(k, data=[str(s) for s in v], dtype=str_t)
                else:
                    f.create_dataset(k, data=v, compression="gzip" if v.size > 100000 else None)
            for k, v in attrs.items():
                f.attrs[k] = v
    return Path(path)


@dataclass
class Collected:
    """What ``collect`` read and computed for one output file, before anything is written or tracked."""

    scenes: list[str]
    data: dict[str, np.ndarray]  # ``_assemble``'s arrays
    per_scene: dict[str, int]
    skipped: dict[str, list[str]]
    seconds: float  # the reading and SIFT time, counted into the run's "seconds" metric


def descriptor_text(conf: PrepareConf) -> str:
    return (f"OpenCV SIFT compute at the given location, size {conf.kp_size} px, angle 0 (upright), "
            f"octave 0; {'RootSIFT (L1-normalise, sqrt)' if conf.rootsift else 'L2-normalised SIFT'}")


def collect(conf: PrepareConf, progress: bool = True) -> Collected:
    """Every input of ``conf`` read and every pair built in memory: each h5 file opened, each pair and image
    read. A corrupt file fails here, before ``prepare`` writes anything or starts its MLflow run (issue #28,
    item 2: it used to fail inside the run, leaving a FAILED run)."""
    conf.check()
    t0 = time.time()
    scenes = conf.scene_list() or list_scenes(conf.root, conf.split)
    if not scenes:
        raise RlsacError(f"{Path(conf.root) / conf.split}: no scene folders")
    for s in scenes:  # fail on a missing scene before any work
        scene_dir(conf.root, conf.split, s)
    skipped: dict[str, list[str]] = defaultdict(list)
    pairs: list[dict] = []
    per_scene = {}
    for s in scenes:
        with Scene(conf.root, conf.split, s) as scene:
            got = _prepare_scene(scene, conf, skipped, progress)
        per_scene[s] = len(got)
        pairs.extend(got)
    if not pairs:
        raise RlsacError(f"{Path(conf.root) / conf.split}: no pair of scenes {scenes} has "
                         f"{conf.min_correspondences} correspondences; nothing to write")
    return Collected(scenes, _assemble(pairs, int(conf.n_points)), per_scene, skipped, time.time() - t0)


def prepare(conf: PrepareConf, track: bool = True, progress: bool = True, collected: Collected | None = None) -> dict:
    """Read ``conf.scenes`` of ``conf.split`` and write one fixed-size h5 to ``conf.out``; return a summary.
    ``collected``: what ``collect(conf)`` returned, when the caller checked its inputs first (rlsac folds)."""
    c = collected if collected is not None else collect(conf, progress)
    t0 = time.time() - c.seconds
    scenes, data, per_scene, skipped = c.scenes, c.data, c.per_scene, c.skipped
    descriptor = descriptor_text(conf)
    # the OpenCV version goes to MLflow only: in the h5 it would change the file's hash with every OpenCV build
    params = {**asdict(conf), "scenes": ",".join(scenes), "descriptor": descriptor, "opencv_version": cv2.__version__}
    with start_run("fundamental", f"prepare {data_label(conf.out)}", params, enabled=track) as run:
        n_pairs = len(data["pair"])
        n_skipped = sum(len(v) for v in skipped.values())
        skip_json = json.dumps({k: {"count": len(v), "pairs": v[:200]} for k, v in skipped.items()})
        attrs = {
            "kind": KIND, "n_points": int(conf.n_points), "split": conf.split, "scenes": ",".join(scenes),
            "root": str(conf.root), "descriptor": descriptor, "n_pairs": n_pairs, "n_skipped": n_skipped,
            "skipped": skip_json,
        }
        write(conf.out, data, attrs)
        counts = data["mask"].sum(1)
        inl = gt_inliers(data, float(conf.gt_threshold)).sum(1) / counts
        summary = {
            "out": str(conf.out), "split": conf.split, "scenes": ",".join(scenes), "pairs": n_pairs,
            "pairs_per_scene": per_scene, "skipped": n_skipped,
            "skip_reasons": {k: len(v) for k, v in skipped.items()},
            "mean_correspondences": float(counts.mean()), "full_pairs": int((counts == conf.n_points).sum()),
            f"mean_gt_inlier_ratio_sampson_{conf.gt_threshold:g}px": float(inl.mean()),
            "gt_inlier_ratio_quantiles": {f"q{int(q * 100)}": float(np.quantile(inl, q))
                                          for q in (0.1, 0.25, 0.5, 0.75, 0.9)},
        }
        seconds = round(time.time() - t0, 2)  # MLflow and the returned summary only, not the written files
        run.metrics({"pairs": n_pairs, "skipped": n_skipped, "mean_correspondences": summary["mean_correspondences"],
                     "mean_gt_inlier_ratio": float(inl.mean()), "seconds": seconds})
        if track:
            with tempfile.TemporaryDirectory() as d:
                run.artifact(write_json(Path(d) / f"prepare_{Path(conf.out).stem}_summary.json", summary))
    return {**summary, "seconds": seconds}
