"""The Strecha SIFT descriptors whose bytes the record's CPU decided (issue #63, item 1).

OpenCV's SIFT calls ``hal::exp32f`` and ``hal::magnitude32f``, which OpenCV hands to Intel IPP; IPP picks its kernels
from CPUID by itself (``cv2.ipp.getIppVersion()``), past ``OPENCV_CPU_DISABLE``. The committed fold data were made
with IPP's AVX-512 kernels (k0); on a CPU without AVX-512 IPP runs its AVX2 ones (l9), whose exp and magnitude round
some samples differently, and 37 of the 235,059 descriptors at the Strecha import's matched keypoints then differ in
one bin by 1 (data/folds/hard/entry 68313507 -> 68313470 bytes, measured on the record's machine with
``OPENCV_IPP=avx2``: exactly the bytes CI's AVX2 EPYC made). An AVX2 CPU cannot run k0 and no rounding of the output
recovers its bins, so the portable mode pins IPP at AVX2 (rlsac.numerics.PINS) and this table gives back the record's
bins where the two differ: the record's descriptors on every x86-64 CPU with AVX2, with the record's bytes unchanged.

``python -m rlsac.data.sift_table [RAW]`` makes the table again, on a CPU with AVX-512 only (where IPP's k0 runs):
each image's matched keypoints in RAW (default data/raw/strecha) described by IPP's AVX-512 and by its AVX2 kernels,
in two processes (IPP reads ``OPENCV_IPP`` when OpenCV loads).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np

TABLE = Path(__file__).with_name("sift_avx512.json")
KP_SIZE = 12.0  # the keypoint diameter the table was made at (PrepareConf.kp_size)


@functools.cache
def _table() -> dict[str, dict[tuple[float, float], np.ndarray]]:
    """'scene/image' -> {(x, y) as float32: the record's raw SIFT descriptor (128,) float32}."""
    rec = json.loads(TABLE.read_text())
    return {img: {(float(np.float32(x)), float(np.float32(y))): np.asarray(d, np.float32) for x, y, d in rows}
            for img, rows in rec["images"].items()}


def recorded(scene: str, image: str, size: float) -> dict[tuple[float, float], np.ndarray]:
    """The record's descriptors of one image ({} for another keypoint size than the table's)."""
    return _table().get(f"{scene}/{image}", {}) if float(size) == KP_SIZE else {}


def apply(desc: np.ndarray, xy: np.ndarray, rec: dict[tuple[float, float], np.ndarray]) -> np.ndarray:
    """Raw SIFT descriptors (M, 128) at ``xy`` (M, 2) with the record's rows put back where the table has them."""
    if not rec:
        return desc
    xy32 = np.asarray(xy, np.float32)  # cv2.KeyPoint holds float32: the table's key
    for i, (x, y) in enumerate(xy32.tolist()):
        row = rec.get((x, y))
        if row is not None:
            desc[i] = row
    return desc


# --- making the table (a CPU with AVX-512) ----------------------------------------------------------------------
