"""Each imported image's SIFT bins at every keypoint its kept matches use, computed once by ``rlsac import-scenes``
(``<scene>/descriptors.h5``) and looked up by every file ``prepare`` makes from the scene (issue #63 item 8).

OpenCV's SIFT ``compute`` spends nearly all its time building the image's scale space; a descriptor depends on the
image and its own keypoint only (measured: the same bins whatever other keypoints share the call), so the data stages,
which described the same 103 images again in each of their 25 stages, read the import's bins instead and write the
same bytes. The bins are OpenCV's raw ones (integers 0-255, stored as uint8: lossless), before the record's bins
(rlsac.data.sift_record) and RootSIFT; a keypoint or an image the table lacks, or another keypoint size, is
described as before.

Layout: one group per image with ``xy`` (M,2) float32 (the keypoints, sorted), ``bins`` (M,128) uint8, attrs
``width`` and ``height``; root attrs ``kp_size`` and ``what``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import h5py
import numpy as np

from rlsac.io import atomic_path

FILE = "descriptors.h5"


def sift_bins(sift, img: np.ndarray, xy: np.ndarray, size: float) -> np.ndarray:
    """OpenCV SIFT's raw descriptors (M,128) float32 of ``img`` at the pixel locations ``xy`` (M,2): upright, of
    diameter ``size``."""
    if len(xy) == 0:
        return np.zeros((0, 128), np.float32)
    kps = [cv2.KeyPoint(float(x), float(y), size, 0.0, 0.0, 0) for x, y in xy]
    out, desc = sift.compute(img, kps)
    if desc is None or len(out) != len(kps):
        raise RuntimeError(f"OpenCV SIFT compute returned {0 if desc is None else len(out)} of {len(kps)} descriptors")
    return desc.astype(np.float32)


def keypoints(matches: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """{image id: its distinct keypoints (K,2) float32, sorted} over the kept pairs ``{"<a>-<b>": (M,4) x1 y1 x2 y2}``
    (``a``'s keypoints are columns 0-1, ``b``'s 2-3)."""
    found: dict[str, list[np.ndarray]] = {}
    for key, m in matches.items():
        a, b = key.split("-", 1)
        found.setdefault(a, []).append(np.asarray(m[:, :2], np.float32))
        found.setdefault(b, []).append(np.asarray(m[:, 2:4], np.float32))
    return {i: np.unique(np.concatenate(v), axis=0) for i, v in found.items()}


def write(path: Path, images: Path, matches: dict[str, np.ndarray], size: float) -> None:
    """The table of one scene at ``path``: every keypoint of ``matches`` described in its image
    (``images/<id>.jpg``) at diameter ``size``."""
    sift = cv2.SIFT_create()
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["kp_size"] = float(size)
        f.attrs["what"] = "OpenCV SIFT bins (raw, uint8) at every kept match's keypoint, upright, diameter kp_size"
        for image, xy in sorted(keypoints(matches).items()):
            img = cv2.imread(str(images / f"{image}.jpg"), cv2.IMREAD_GRAYSCALE)
            bins = sift_bins(sift, img, xy, float(size))
            if not np.array_equal(np.clip(np.round(bins), 0, 255), bins):  # OpenCV's bins are whole bytes
                raise RuntimeError(f"{image}: SIFT bins that are not whole numbers in 0-255")
            g = f.create_group(image)
            g.create_dataset("xy", data=xy)
            g.create_dataset("bins", data=bins.astype(np.uint8))
            g.attrs["width"], g.attrs["height"] = int(img.shape[1]), int(img.shape[0])


class Table:
    """One scene's table, opened for lookups (``None`` from ``open`` where there is none or its size differs)."""

    def __init__(self, f: h5py.File):
        self.f = f

    @classmethod
    def open(cls, scene_dir: Path, size: float) -> Table | None:
        path = Path(scene_dir) / FILE
        if not path.is_file():
            return None
        f = h5py.File(path, "r")
        if float(f.attrs.get("kp_size", -1.0)) != float(size):
            f.close()
            return None
        return cls(f)

    def close(self) -> None:
        self.f.close()

    def lookup(self, image: str, xy: np.ndarray) -> tuple[np.ndarray, tuple[int, int]] | None:
        """(the raw bins (M,128) float32 at ``xy`` (M,2), (width, height)), or None when the table lacks the image
        or one of the keypoints (as float32, exactly)."""
        if image not in self.f:
            return None
        g = self.f[image]
        table_xy, bins = g["xy"][()], g["bins"]
        q = np.ascontiguousarray(np.asarray(xy, np.float32))
        # row-wise search on the sorted (x, y) pairs as one structured key
        view = lambda a: a.view([("x", np.float32), ("y", np.float32)]).ravel()  # noqa: E731
        keys, want = view(np.ascontiguousarray(table_xy)), view(q)
        at = np.searchsorted(keys, want)
        if len(want) and (at.max() >= len(keys) or not np.array_equal(keys[np.minimum(at, len(keys) - 1)], want)):
            return None
        return bins[()][at].astype(np.float32), (int(g.attrs["width"]), int(g.attrs["height"]))
