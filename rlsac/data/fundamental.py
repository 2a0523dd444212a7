"""The prepared fundamental-matrix file (one h5 per split) and the ground-truth epipolar helpers.

Format (written by ``rlsac.data.tutorial.prepare``), P pairs of N correspondences each:
    coords (P,N,4) float32      x1, y1, x2, y2 in pixels, zero-padded
    features (P,N,261) float32  [x1, y1, x2, y2, snn, desc1 (128), desc2 (128)], zero-padded
    mask (P,N) bool             valid correspondences
    K1, K2, dR (P,3,3) float64; dT (P,3) float64; size1, size2 (P,2) int32 (width, height)
    pair, scene (P,) utf-8 strings
    attrs: kind="rlsac-fundamental", n_points, split, scenes, root, descriptor, n_pairs, n_skipped, skipped
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from rlsac.data import validity
from rlsac.errors import RlsacError
from rlsac.io import open_h5, read_array

KIND = "rlsac-fundamental"
N_FEATURES = 261  # 4 coordinates + SNN ratio + two 128-D descriptors


def read(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """Read and validate a prepared fundamental file -> (arrays, attrs).

    Pairs whose geometry is meaningless (``pair_problems``) are left out of the arrays and reported in
    ``attrs["unusable"]`` (rlsac.data.validity.keep_usable: count, file rows, reasons); a file without a usable
    pair is an RlsacError. The arrays of the usable pairs are the file's, unchanged."""
    with open_h5(path) as f:
        kind = f.attrs.get("kind")
        if kind != KIND:
            raise RlsacError(f"{path}: attribute 'kind' is {kind!r}, expected {KIND!r}: not a prepared file")
        coords = read_array(f, "coords", (None, None, 4))
        P, N = coords.shape[:2]
        out = {
            "coords": coords.astype(np.float32, copy=False),
            "features": read_array(f, "features", (P, N, N_FEATURES)).astype(np.float32, copy=False),
            "mask": read_array(f, "mask", (P, N)).astype(bool),
            "K1": read_array(f, "K1", (P, 3, 3)).astype(np.float64),
            "K2": read_array(f, "K2", (P, 3, 3)).astype(np.float64),
            "dR": read_array(f, "dR", (P, 3, 3)).astype(np.float64),
            "dT": read_array(f, "dT", (P, 3)).astype(np.float64),
            "size1": read_array(f, "size1", (P, 2)).astype(np.int32),
            "size2": read_array(f, "size2", (P, 2)).astype(np.int32),
            "pair": _strings(read_array(f, "pair", (P,))),
            "scene": _strings(read_array(f, "scene", (P,))),
        }
        attrs = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in f.attrs.items()}
    if P == 0:
        raise RlsacError(f"{path}: key 'coords' holds no pairs")
    out, report = validity.keep_usable(out, pair_problems(out), out["pair"], path, "pair")
    if report:
        attrs[validity.REPORT] = report
    return out, attrs


def pair_problems(data: dict[str, np.ndarray]) -> np.ndarray:
    """What makes each pair unusable (rlsac.data.validity): too few or identical correspondences, K1 / K2 that
    are no camera for their image, a ground-truth dR that is no rotation or a zero dT, correspondences outside
    their images. data: ``read``'s arrays, P pairs -> (P,) reasons, "" for a usable pair."""
    checks = validity.correspondences(data["coords"], data["mask"]) + validity.image_sizes(data["size1"], data["size2"])
    for j in (1, 2):
        checks += validity.intrinsics(data[f"K{j}"], data[f"size{j}"], f"K{j}")
    checks += validity.rotations(data["dR"]) + validity.translations(data["dT"])
    checks += validity.in_images(data["coords"], data["mask"], data["size1"], data["size2"])
    return validity.first_problem(checks, len(data["coords"]))


def _strings(arr: np.ndarray) -> np.ndarray:
    return np.array([s.decode("utf-8") if isinstance(s, bytes) else str(s) for s in arr], dtype=object)


def to_batch(data: dict[str, np.ndarray], idx=slice(None), device: str | torch.device = "cpu") -> dict:
    """Slice arrays into the batch dict the environment and the baselines consume."""
    if isinstance(idx, (int, np.integer)):
        idx = [int(idx)]
    batch = {
        "coords": torch.as_tensor(np.ascontiguousarray(data["coords"][idx]), dtype=torch.float32, device=device),
        "features": torch.as_tensor(np.ascontiguousarray(data["features"][idx]), dtype=torch.float32, device=device),
        "mask": torch.as_tensor(np.ascontiguousarray(data["mask"][idx]), dtype=torch.bool, device=device),
    }
    for k in ("K1", "K2", "dR", "dT", "size1", "size2", "pair", "scene"):
        batch[k] = data[k][idx]
    return batch


# --- ground-truth epipolar geometry -------------------------------------------------------------


def skew(t: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices [t]x."""
    t = np.asarray(t, dtype=np.float64)
    z = np.zeros(t.shape[:-1])
    return np.stack([
        np.stack([z, -t[..., 2], t[..., 1]], -1),
        np.stack([t[..., 2], z, -t[..., 0]], -1),
        np.stack([-t[..., 1], t[..., 0], z], -1),
    ], -2)


def gt_fundamental(K1: np.ndarray, K2: np.ndarray, dR: np.ndarray, dT: np.ndarray) -> np.ndarray:
    """F = K2^-T [dT]x dR K1^-1, batched over leading axes, scaled to unit Frobenius norm."""
    dT = np.asarray(dT, dtype=np.float64).reshape(*np.shape(dR)[:-2], 3)
    E = skew(dT) @ np.asarray(dR, dtype=np.float64)
    F = np.linalg.inv(K2).swapaxes(-1, -2) @ E @ np.linalg.inv(K1)
    return F / np.linalg.norm(F, axis=(-2, -1), keepdims=True)


def sampson(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Sampson distance in pixels (square root of the first-order squared error), batched.

    F (..., 3, 3); x1, x2 (..., N, 2) pixels -> (..., N).
    """
    F = np.asarray(F, dtype=np.float64)
    h1 = np.concatenate([x1, np.ones(x1.shape[:-1] + (1,))], -1).astype(np.float64)
    h2 = np.concatenate([x2, np.ones(x2.shape[:-1] + (1,))], -1).astype(np.float64)
    Fx1 = h1 @ F.swapaxes(-1, -2)  # (..., N, 3) rows F x1
    Ftx2 = h2 @ F  # rows F^T x2
    num = (h2 * Fx1).sum(-1) ** 2
    den = Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


def gt_inliers(data: dict[str, np.ndarray], threshold: float = 2.0) -> np.ndarray:
    """(P, N) bool: valid correspondences whose Sampson distance to the ground-truth F is below ``threshold`` px."""
    F = gt_fundamental(data["K1"], data["K2"], data["dR"], data["dT"])
    c = data["coords"].astype(np.float64)
    return (sampson(F, c[..., :2], c[..., 2:]) < threshold) & data["mask"]
