"""Checkpoints recorded in dvc.lock by `dvc commit`, not written there by their stage: a model whose training spans
sessions (RLSAC at scale, issue #46: 4 folds x 5 seeds of 10000 steps) had each finished run committed at once and
its `fold_train_pool(_seed)` entries recorded when all 20 were in (docs/reproducing.md, "A model whose runs span
sessions"). `dvc commit` trusts the file it hashes, so this test holds each one to what its stage would write: a
finished run of the recipe params.yaml holds for it, with the stage's own options."""

from __future__ import annotations

from pathlib import Path

import pytest

from rlsac.config import load_params
from rlsac.experiments import folds
from rlsac.learners.harness import check, stored_conf
from rlsac.rl.checkpoint import read

ROOT = Path(__file__).resolve().parents[1]
RECORDED = ("rlsac-scale",)  # the models whose training stages were recorded with `dvc commit`
PARAMS = load_params(ROOT / "params.yaml")
PROTOCOL = folds.protocol(PARAMS)


def runs() -> list[Path]:
    """Every run of the recorded models the protocol lists: checkpoints/folds/<model_regime>/<fold>/<model>.pt."""
    names = [f"{m}{s}" for m in RECORDED for s in [""] + [f"-s{k}" for k in PROTOCOL["seeds"]]]
    return [Path("checkpoints", "folds", PROTOCOL["model_regime"], fold, f"{name}.pt")
            for fold in PROTOCOL["test"] for name in names]


def expected_conf(rel: Path) -> tuple[dict, int]:
    """The stored configuration and the step count of the run that writes ``rel``: what `rlsac folds --stage train`
    builds for it."""
    _, _, regime, fold, name = rel.parts
    opts = folds.train_options(PROTOCOL, PARAMS, regime, fold, name.removesuffix(".pt"),
                               {"device": "auto", "threads": 1})
    conf = check(opts, track=False)
    return stored_conf(conf), conf.sac.total_steps


def test_the_recorded_models_are_listed_with_every_seed():
    for model in RECORDED:
        assert model in PROTOCOL["models"] and model in PROTOCOL["seed_models"], model
    assert len(runs()) == 20


@pytest.mark.parametrize("rel", runs(), ids=str)
def test_a_recorded_checkpoint_is_a_finished_run_of_its_recipe(rel):
    ck = read(ROOT / rel)
    want, steps = expected_conf(rel)
    assert ck["conf"] == want  # the recipe (kernels included), the fold's files, the seed, the output path
    assert ck["step"] >= steps and ck["selection"] == "last"  # the final actor of a run that went the whole way
    assert ck["history"] and ck["history"][-1]["step"] == steps
