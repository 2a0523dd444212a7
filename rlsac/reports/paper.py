"""The paper's published numbers (Nie et al., ICCV 2023), Tables 1-3, as data.

Copied from the LaTeX source of the paper; nothing here is computed. Medians are in degrees.
"""

from __future__ import annotations

# Table 1, 2D line fitting at 150 iterations: method -> outlier rate -> (mAA@0.5 deg, median error deg).
TABLE1: dict[str, dict[float, tuple[float, float]]] = {
    "RANSAC": {0.1: (0.870, 0.049), 0.2: (0.863, 0.052), 0.3: (0.850, 0.056), 0.4: (0.829, 0.061),
               0.5: (0.796, 0.071), 0.6: (0.746, 0.087), 0.7: (0.608, 0.135)},
    "Ours": {0.1: (0.875, 0.047), 0.2: (0.874, 0.049), 0.3: (0.872, 0.048), 0.4: (0.865, 0.050),
             0.5: (0.858, 0.052), 0.6: (0.845, 0.056), 0.7: (0.824, 0.062)},
    "Ours-0.5": {0.1: (0.849, 0.053), 0.2: (0.850, 0.055), 0.3: (0.854, 0.053), 0.4: (0.858, 0.052),
                 0.5: (0.858, 0.052), 0.6: (0.864, 0.050), 0.7: (0.849, 0.054)},
}
TABLE1_RATES = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)

# Table 2, fundamental matrices at 1k iterations: method -> (mAA@10 R, mAA@10 t, median eps_R, median eps_t).
TABLE2: dict[str, tuple[float, float, float, float]] = {
    "RANSAC": (0.644, 0.488, 2.307, 5.100),
    "USAC": (0.741, 0.604, 1.036, 2.157),
    "MAGSAC++": (0.753, 0.614, 0.924, 1.895),
    "Ours": (0.760, 0.622, 0.926, 1.751),
}

# Table 3, ablations on fundamental matrices: (group, row label, our variant directory, numbers or None).
# The "full" model appears once per group in the paper, with the same numbers.
_FULL = TABLE2["Ours"]
TABLE3: list[tuple[str, str, str, tuple[float, float, float, float]]] = [
    ("(a)", "Ours (w/o descriptors)", "no_descriptors", (0.702, 0.568, 1.400, 2.963)),
    ("(a)", "Ours (full, with 128-D descriptors)", "full", _FULL),
    ("(b)", "Ours (max sampling in training, max in testing)", "train_max-test_max", (0.730, 0.591, 1.132, 2.331)),
    ("(b)", "Ours (max sampling in training, prob. in testing)", "train_max-test_prob", (0.706, 0.531, 1.415, 2.893)),
    ("(b)", "Ours (prob. sampling in training, prob. in testing)", "train_prob-test_prob",
     (0.720, 0.581, 1.150, 2.508)),
    ("(b)", "Ours (full, prob. sampling in training, max in testing)", "full", _FULL),
    ("(c)", "Ours (N=100 points)", "n100", (0.727, 0.588, 1.216, 2.464)),
    ("(c)", "Ours (N=200 points)", "n200", (0.747, 0.604, 1.050, 2.108)),
    ("(c)", "Ours (N=300 points)", "n300", (0.733, 0.594, 1.180, 2.364)),
    ("(c)", "Ours (full, N=150 points)", "full", _FULL),
]
