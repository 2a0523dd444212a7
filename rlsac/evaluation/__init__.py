"""One method or learner run once: the method registry, evaluate, train, tuning on validation
(tune, retune) and the readers of their result records (results).
"""
