"""The record's SIFT descriptors on every x86-64 CPU with AVX2 (issue #63, item 1): under the portable pins Intel IPP
inside OpenCV runs its AVX2 kernels, and rlsac.data.sift_record gives back the bins its AVX-512 kernels made in the
record. The record's machine itself runs the AVX-512 kernels where unpinned, so there this test sees both paths."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from rlsac.data import sift_record
from rlsac.data.tutorial import describe, load_gray

STRECHA = Path(os.environ.get("RLSAC_STRECHA", Path(__file__).resolve().parents[1] / "data" / "strecha"))


def _image_with_most_rows() -> tuple[str, str, dict]:
    name, rows = max(sift_record._table().items(), key=lambda kv: (len(kv[1]), kv[0]))
    scene, image = name.split("/")
    return scene, image, rows


@pytest.mark.skipif(not cv2.ipp.useIPP(), reason="this OpenCV runs without Intel IPP: no IPP kernels to pin")
def test_the_records_bins_come_back_on_ipps_avx2_kernels():
    # the pins took in this process: IPP at AVX2 on every CPU that has it (an AVX-512 one would say k0)
    assert "(l9)" in cv2.ipp.getIppVersion(), cv2.ipp.getIppVersion()
    scene, image, rows = _image_with_most_rows()
    img = load_gray(STRECHA / scene / "images" / f"{image}.jpg")
    xy = np.array(list(rows), np.float64)
    # the table's keypoints among others (a pixel away, which the table does not hold): those stay as computed
    xy = np.concatenate([xy, xy + 1.0])
    sift = cv2.SIFT_create()
    _, raw = sift.compute(img, [cv2.KeyPoint(float(x), float(y), sift_record.KP_SIZE, 0.0, 0.0, 0) for x, y in xy])
    table = np.stack(list(rows.values()))
    n = len(rows)
    # AVX2's kernels round each of these descriptors one bin away from the record's (AVX-512's)
    off = np.abs(raw[:n].astype(int) - table.astype(int))
    assert (off.sum(1) == 1).all() and off.max() == 1
    fixed = sift_record.apply(raw.copy(), xy, rows)
    assert (fixed[:n] == table).all() and (fixed[n:] == raw[n:]).all()
    # describe() puts them back before RootSIFT, so the stored features are the record's
    got = describe(sift, img, xy, sift_record.KP_SIZE, True, rows)
    assert np.array_equal(got[:n], np.sqrt(table / table.sum(1, keepdims=True)))
    assert sift_record.recorded(scene, image, sift_record.KP_SIZE + 1) == {}  # made at one keypoint size only
