"""The names of the evaluation methods, in one place (no heavy imports: the CLI reads them for --help).

How each is built lives in ``rlsac.evaluate.make_estimator``.
"""

from __future__ import annotations

OPENCV_METHODS = ("opencv_ransac", "usac", "usac_accurate", "magsac", "prosac")  # fundamental only
OPENCV_FLAG = {"opencv_ransac": "ransac", "usac": "usac", "usac_accurate": "usac_accurate", "magsac": "magsac",
               "prosac": "prosac"}  # -> rlsac.baselines.OPENCV_F_METHODS
# not in the paper: the same samplers with local optimisation and the `lo` options' score (rlsac.lo)
LO_METHODS = ("ransac-lo", "uniform-lo", "rlsac-lo")
METHODS = ("ransac", "rlsac", "uniform", "guided", "oracle") + OPENCV_METHODS + LO_METHODS
