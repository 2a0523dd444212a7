"""What the numbers of a data file mean, checked per instance (issue #28, item 1), for the three readers:
rlsac.data.fundamental (the fundamental and essential tasks) and rlsac.data.lines.

A file can have the right keys, shapes and finite values and still describe no camera or no line: a K with a
focal length of 1e-3 px (det 1e-6 passes an absolute singularity test), a negative focal length, a "rotation"
scaled by 2 (every rotation error is then 0 and mAA_R = 1), a zero baseline (no translation direction to
score), points a thousand image widths away. Each check below takes the arrays of P instances and returns
``[(reason, bad)]``: fixed reason texts (so that a summary can count them) and a (P,) bool mask each.
``first_problem`` merges them into one reason per instance; ``keep_usable`` drops the unusable instances of an
otherwise good file (the reader reports them, evaluate counts them in its summary and in MLflow) and rejects a
file where none is usable. The usable instances are passed on unchanged.

Thresholds are loose on purpose: they catch numbers that cannot come from a camera or from the generator, not
unusual but real data. The real Strecha folds (1024 x 683 px, f = 920 px) are far inside every one of them.
"""

from __future__ import annotations

import numpy as np

from rlsac.errors import RlsacError

Checks = list[tuple[str, np.ndarray]]

# K with pixels divided by the image's larger side (so that the test is relative, not in pixel units): its condition
# number is 1.9 for Strecha (f = 920 px, 1024 px wide), 14 at f = 100 px, 1400 at f = 1 px (a 180-degree view) and
# 1.4e6 at f = 1e-3 px (det 1e-6); 980 at f = 1e6 px (a 0.06-degree view). Above the bound K is near-singular.
MAX_K_COND = 1e3
# R R^T - I (largest entry) of a ground-truth rotation. Strecha's dR = R2 R1^T from camera files with six
# decimals: 2.4e-6. R scaled by 2 gives 3, a reflection passes this and fails det > 0.
ROTATION_TOL = 1e-3
# Ground-truth translation norm (scene units) below which the two cameras share a centre: no epipolar geometry and
# no translation direction to score. Strecha: 0.69 m at least.
MIN_BASELINE = 1e-9
# How far outside the image (a fraction of its side) a correspondence may lie: keypoints at the border, coordinates
# after undistortion. Further out, the coordinates are not pixels of this image (another unit, another size).
IMAGE_MARGIN = 0.25
MIN_CORRESPONDENCES = 8  # the 8-point solver's minimum (the fundamental task; the essential task needs 5)
REPORT = "unusable"  # the readers' attrs key of ``keep_usable``'s report, present only when an instance was dropped


# ------------------------------------------------------------------------------------- two-view pairs


def image_sizes(size1: np.ndarray, size2: np.ndarray) -> Checks:
    """size1, size2 (P, 2) the images' (width, height) in pixels -> [(reason, bad (P,))]: at least 1 x 1."""
    return [(f"image {j + 1} has no size (width or height < 1)", ~(np.asarray(size).min(-1) >= 1))
            for j, size in enumerate((size1, size2))]


def intrinsics(K: np.ndarray, size: np.ndarray, name: str) -> Checks:
    """K (P, 3, 3) in pixels, size (P, 2) its image's (width, height) -> [(reason, bad (P,))]: last row (0, 0, 1),
    positive focal lengths, and well-conditioned relative to the image (MAX_K_COND)."""
    K = np.asarray(K, np.float64)
    last_row = np.abs(K[:, 2] - np.array([0.0, 0.0, 1.0])).max(-1) > 1e-6
    focal = ~((K[:, 0, 0] > 0) & (K[:, 1, 1] > 0))
    scaled = K.copy()
    scaled[:, :2] /= np.maximum(np.asarray(size, np.float64).max(-1), 1.0)[:, None, None]
    sv = np.linalg.svd(scaled, compute_uv=False)  # (P, 3), descending
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = sv[:, 0] / sv[:, 2]
    near_singular = ~(cond <= MAX_K_COND)  # inf and NaN (a zero K) are near-singular too
    return [(f"{name} is not an intrinsic matrix (last row must be 0 0 1)", last_row),
            (f"{name} has a focal length <= 0", focal),
            (f"{name} is near-singular for its image (condition number > {MAX_K_COND:g} with pixels divided by the "
             "image size)", near_singular)]


def rotations(R: np.ndarray, name: str = "dR") -> Checks:
    """R (P, 3, 3) -> [(reason, bad (P,))]: orthonormal (R R^T = I within ROTATION_TOL) with det +1."""
    R = np.asarray(R, np.float64)
    off = np.abs(R @ R.swapaxes(-1, -2) - np.eye(3)).max((-2, -1))
    return [(f"{name} is not a rotation (R R^T != I)", ~(off <= ROTATION_TOL)),
            (f"{name} is a reflection, not a rotation (det < 0)", np.linalg.det(R) <= 0)]


def translations(t: np.ndarray, name: str = "dT") -> Checks:
    """t (P, 3) -> [(reason, bad (P,))]: a baseline of at least MIN_BASELINE."""
    return [(f"{name} is zero (no baseline: no translation direction)",
             ~(np.linalg.norm(np.asarray(t, np.float64), axis=-1) >= MIN_BASELINE))]


def correspondences(coords: np.ndarray, mask: np.ndarray) -> Checks:
    """coords (P, N, 4), mask (P, N) valid rows -> [(reason, bad (P,))]: at least MIN_CORRESPONDENCES valid
    correspondences, and not all of them identical (degenerate: no model can be fitted)."""
    P = len(coords)
    first = coords[np.arange(P), mask.argmax(1)][:, None]  # the first valid correspondence of each pair
    same = np.all((coords == first) | ~mask[..., None], axis=(1, 2))
    few = mask.sum(1) < MIN_CORRESPONDENCES
    return [(f"fewer than {MIN_CORRESPONDENCES} valid correspondences", few),
            ("degenerate data: all valid correspondences are identical", same & ~few)]


def in_images(coords: np.ndarray, mask: np.ndarray, size1: np.ndarray, size2: np.ndarray) -> Checks:
    """coords (P, N, 4) pixels x1, y1, x2, y2, mask (P, N), size1, size2 (P, 2) (width, height) ->
    [(reason, bad (P,))]: every valid correspondence within IMAGE_MARGIN of its two images."""
    out = []
    for j, size in enumerate((size1, size2)):
        wh = np.asarray(size, np.float64)[:, None, :]  # (P, 1, 2)
        xy = np.asarray(coords[..., 2 * j: 2 * j + 2], np.float64)
        inside = (xy >= -IMAGE_MARGIN * wh) & (xy <= (1 + IMAGE_MARGIN) * wh)
        out.append((f"a correspondence lies outside image {j + 1} (more than {IMAGE_MARGIN:g} of its size beyond "
                    "the border)", ~np.all(inside.all(-1) | ~mask, axis=1)))
    return out


# ------------------------------------------------------------------------------------------- lines


def line_points(points: np.ndarray, picture_size: float) -> Checks:
    """points (P, N, 2) in a [0, picture_size]^2 picture -> [(reason, bad (P,))]: not all identical, and every
    point within IMAGE_MARGIN of the picture."""
    same = np.all(points == points[:, :1], axis=(1, 2))
    lo, hi = -IMAGE_MARGIN * picture_size, (1 + IMAGE_MARGIN) * picture_size
    return [("degenerate data: all points are identical (no line can be fitted)", same),
            (f"a point lies outside the {picture_size:g} x {picture_size:g} picture (more than {IMAGE_MARGIN:g} of "
             "its size beyond the border)", ~np.all((points >= lo) & (points <= hi), axis=(1, 2)))]


def ground_truth_lines(line: np.ndarray, picture_size: float) -> Checks:
    """line (P, 3) as (a, b, c), a x + b y + c = 0 -> [(reason, bad (P,))]: a non-zero normal (a, b), and the line
    meets the picture (distance from its centre at most the half-diagonal, plus IMAGE_MARGIN)."""
    normal = np.linalg.norm(line[:, :2], axis=1)
    centre = picture_size / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.abs(line[:, 0] * centre + line[:, 1] * centre + line[:, 2]) / normal
    zero = ~(normal >= 1e-12)
    misses = ~zero & ~(dist <= picture_size * (np.sqrt(0.5) + IMAGE_MARGIN))
    return [("line is not a line (its normal (a, b) is zero)", zero), ("line misses the picture", misses)]


# ------------------------------------------------------------------------------------------ merging


def first_problem(checks: Checks, n: int) -> np.ndarray:
    """[(reason, bad (P,))] -> (P,) object array: the first reason that applies to each instance, "" if none."""
    out = np.full(n, "", dtype=object)
    for reason, bad in checks:
        out[np.asarray(bad, bool) & (out == "")] = reason
    return out


def keep_usable(arrays: dict[str, np.ndarray], problems: np.ndarray, labels, path, what: str
                ) -> tuple[dict[str, np.ndarray], dict | None]:
    """Drop the unusable instances (``problems`` != "") from every (P, ...) array of a file.

    arrays: the reader's arrays, all with P rows; problems (P,) from ``first_problem``; labels (P,) names of the
    instances for the message (pair keys, or None for indices); what: "pair" or "instance".
    -> (arrays unchanged when every instance is usable, else their usable rows; the report or None):
    report = {"count", "of" (P), "rows": the file rows dropped, "why": their reasons, "reasons": [[reason, count]]};
    RlsacError when none is usable.
    """
    bad = problems != ""
    if not bad.any():
        return arrays, None
    P = len(problems)
    rows = np.flatnonzero(bad)
    first = int(rows[0])
    name = f"{what} {first}" + (f" ({labels[first]})" if labels is not None else "")
    if bad.all():
        raise RlsacError(f"{path}: no usable {what} ({P} of {P} unusable; {name}: {problems[first]})")
    reasons, counts = np.unique(problems[bad].astype(str), return_counts=True)
    keep = ~bad
    report = {"count": int(bad.sum()), "of": P, "rows": [int(r) for r in rows],
              "why": [str(problems[r]) for r in rows],
              # [reason, count] pairs, not a mapping: MLflow's flattened param names cannot hold the reasons' text
              "reasons": [[str(r), int(c)] for r, c in zip(reasons, counts, strict=True)]}
    return {k: v[keep] for k, v in arrays.items()}, report


def kept_rows(report: dict | None, n_kept: int) -> np.ndarray:
    """The file rows of the instances a reader kept: (n_kept,) int, 0..n-1 when it dropped none."""
    if not report:
        return np.arange(n_kept)
    return np.delete(np.arange(report["of"]), report["rows"])


def row_position(report: dict | None, row: int, n_kept: int, path, what: str) -> int:
    """The position among a reader's kept instances of file row ``row`` (an index a user gave, e.g. rlsac plot's
    pair); RlsacError when it is out of range or the reader left it out as unusable."""
    n = report["of"] if report else n_kept
    if not 0 <= row < n:
        raise RlsacError(f"{what} {row} out of range (0..{n - 1}) in {path}")
    if report and row in report["rows"]:
        raise RlsacError(f"{what} {row} of {path} is unusable: {report['why'][report['rows'].index(row)]}")
    return int(np.searchsorted(kept_rows(report, n_kept), row))
