"""The studies built from those runs: the fold benchmark (folds, folds_retune, selection), the
ablations, the scale study, the positive control, the learner ladder, line calibration, quick.
"""
