"""Our RANSAC loop's parts: minimal-set sampling, the scorers and local optimisation (lo), and the
classical estimators and their library bindings (baselines: OpenCV, PoseLib, pydegensac).
"""
