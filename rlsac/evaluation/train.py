"""``rlsac train``: the options checked on the shared harness (rlsac.learners.harness), then the learner of
``--method`` from the registry (rlsac.learners: ``rlsac``, the SAC agent; ``ngransac``, NG-RANSAC's network).
"""

from __future__ import annotations

import torch

from rlsac.devices import resolve_device
from rlsac.learners import LEARNERS

# the harness's public names, re-exported for the callers of the command's module (rlsac.experiments.scale, the CLI's
# tests)
from rlsac.learners.harness import (  # noqa: F401
    LATER_DEFAULTS,
    OWN_SECTIONS,
    SELECTION_KEY,
    SELECTIONS,
    TrainConf,
    check,
    check_params,
    selection_score,
    stored_conf,
)


def train(options: dict, track: bool = True, snapshots: list | None = None) -> dict:
    """``rlsac train``: options -> TrainConf; the learner of its ``method`` trains and keeps the selected actor in
    ``out``; -> a summary. ``snapshots``: a list that receives the checkpoint payload of every validated actor, kept
    or not (rlsac.experiments.selection replays a fold model's training to measure the choice; RLSAC's learner only)."""
    conf = check(options, track)
    if conf.threads > 0:
        torch.set_num_threads(conf.threads)
    resolve_device(conf.device)  # "cuda" without a GPU: refused before the learner reads anything
    return LEARNERS[conf.method](conf, track, snapshots)
