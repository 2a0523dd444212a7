"""The maths of two views and of the scores: epipolar geometry (minimal solvers, Sampson errors, pose
recovery) and the error metrics (rotation / translation errors, mAA), pure batched functions.
"""
