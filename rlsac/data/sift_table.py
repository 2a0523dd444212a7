"""Makes rlsac.data.sift_record's table again (issue #63, item 1), on a CPU with AVX-512 only (where IPP's k0 runs):
each image's matched keypoints in RAW (default data/raw/strecha) described by IPP's AVX-512 and by its AVX2 kernels,
in two processes (IPP reads ``OPENCV_IPP`` when OpenCV loads). ``python -m rlsac.data.sift_table [RAW]``. Apart from
sift_record so that the importer (rlsac.data.tutorial), which reads the table, is not imported by it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from rlsac.data.sift_record import KP_SIZE, TABLE

_DESCRIBE = """
import sys, numpy as np, rlsac, cv2
from rlsac.data.sift_table import image_keypoints
out = {}
sift = cv2.SIFT_create()
for name, (img_path, xy) in image_keypoints(sys.argv[1]).items():
    img = cv2.imread(img_path, cv2.IMREAD_GRAYSCALE)
    _, d = sift.compute(img, [cv2.KeyPoint(float(x), float(y), %r, 0.0, 0.0, 0) for x, y in xy])
    out[name] = d
np.savez(sys.argv[2], ipp=cv2.ipp.getIppVersion(), **out)
""" % KP_SIZE


def image_keypoints(raw: str | Path) -> dict[str, tuple[str, np.ndarray]]:
    """'scene/image' -> (its image file, every distinct float32 (x, y) of its matches in the import RAW)."""
    import h5py

    from rlsac.data.tutorial import list_scenes, split_key

    out = {}
    for scene in list_scenes(raw, "all"):
        d = Path(raw) / "all" / scene
        pts: dict[str, list[np.ndarray]] = {}
        with h5py.File(d / "matches.h5") as f, h5py.File(d / "R.h5") as r:
            ids = set(r.keys())
            for key in f:
                a, b = split_key(key, ids, str(d / "matches.h5"))
                m = f[key][()].astype(np.float32)
                pts.setdefault(a, []).append(m[:, :2])
                pts.setdefault(b, []).append(m[:, 2:])
        for image, xy in sorted(pts.items()):
            out[f"{scene}/{image}"] = (str(d / "images" / f"{image}.jpg"), np.unique(np.concatenate(xy), axis=0))
    return out


def _describe_all(raw: str, ipp: str | None, path: Path) -> dict:
    """Every image's descriptors in a child process, OpenCV's own kernels at AVX2 as in the portable mode and IPP's
    at ``ipp`` ('avx2'), or None: IPP's own choice, as when the record was made (OPENCV_IPP=avx512 is not that)."""
    from rlsac.numerics import OPENCV_PIN

    env = {k: v for k, v in os.environ.items() if k not in ("RLSAC_NUMERICS", "OPENCV_IPP")}
    env.update({"OPENCV_IPP": ipp} if ipp else {"RLSAC_NUMERICS": "native", OPENCV_PIN[0]: OPENCV_PIN[1]})
    subprocess.run([sys.executable, "-c", _DESCRIBE, raw, str(path)], env=env, check=True)
    return dict(np.load(path))


def make(raw: str = "data/raw/strecha") -> dict:
    """The table: the rows where IPP's AVX-512 kernels (the record's) and its AVX2 kernels differ."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        k0 = _describe_all(raw, None, Path(tmp) / "k0.npz")
        l9 = _describe_all(raw, "avx2", Path(tmp) / "l9.npz")
    if "(k0)" not in str(k0["ipp"]):
        raise SystemExit(f"IPP runs {k0['ipp']} here: the record's descriptors need its AVX-512 kernels (k0)")
    xy = {name: v[1] for name, v in image_keypoints(raw).items()}
    images = {}
    for name in sorted(xy):
        rows = np.nonzero((k0[name] != l9[name]).any(1))[0]
        if len(rows):
            images[name] = [[float(xy[name][i, 0]), float(xy[name][i, 1]), k0[name][i].astype(int).tolist()]
                            for i in rows]
    return {"kp_size": KP_SIZE, "made_with": str(k0["ipp"]), "replaces": str(l9["ipp"]),
            "keypoints": int(sum(len(v) for v in xy.values())), "images": images}


if __name__ == "__main__":
    table = make(*sys.argv[1:2])
    TABLE.write_text(json.dumps(table, separators=(",", ":")) + "\n")
    print(f"{TABLE}: {sum(len(v) for v in table['images'].values())} of {table['keypoints']} descriptors")
