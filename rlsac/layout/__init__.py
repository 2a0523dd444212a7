"""The protocol's vocabulary: the fold benchmark's rows, names, paths and budgets (protocol), and the
scale study's and the learner ladder's (scale_layout, ladder_layout); no heavy imports.
"""
