"""The learned samplers' trainers, peers over one training harness (rlsac.learners.harness): ``sac`` (the RLSAC
agent: SAC-Discrete over the environment) and ``ngransac`` (NG-RANSAC's network). A new learner is one module here
that decorates its ``train(conf, track, snapshots)`` with ``@register_learner`` (and is imported below); `rlsac train
--method` picks it from ``LEARNERS`` (rlsac.evaluation.train). Neither learner imports the other.
"""

from __future__ import annotations

from rlsac.learners.harness import LEARNERS, OWN_SECTIONS, register_learner  # noqa: F401

# isort: split
from rlsac.learners import sac, ngransac  # noqa: E402,F401,I001  (each registers itself; this order in --help)
