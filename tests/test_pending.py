"""experiments/pending/: the finished runs of a model whose training spans sessions (RLSAC at scale, issue #46),
committed at their final paths under experiments/pending/ until every run is in. Each must be a finished run of the
recipe params.yaml holds for it, exactly as its `fold_train_pool(_seed)` stage would write it, so that moving it into
checkpoints/ and recording its dvc.lock entry (`dvc commit`) describes the truth."""

from __future__ import annotations

from pathlib import Path

import pytest

from rlsac import folds
from rlsac.checkpoint import read
from rlsac.config import load_params
from rlsac.learners.harness import check, stored_conf

ROOT = Path(__file__).resolve().parents[1]
PENDING = ROOT / "experiments" / "pending"
WAITING = "rlsac-scale"  # the model whose runs wait here (params.yaml: recipe defined, outside the stage lists)
FILES = sorted(p.relative_to(PENDING) for p in PENDING.rglob("*") if p.is_file() and p.name != "README.md")


def listed_protocol() -> tuple[dict, dict]:
    """params.yaml with the waiting model listed as it will be once its runs are in (models, seed_models,
    pool_models) -> (protocol, params)."""
    params = load_params(ROOT / "params.yaml")
    p = folds.protocol(params)
    p = folds.protocol({"folds": {**params["folds"], "pool_models": p["pool_models"] + [WAITING],
                                  "models": p["models"] + [WAITING], "seed_models": p["seed_models"] + [WAITING],
                                  "file_models": None, "file_seed_models": None}})
    return p, params


def expected_conf(rel: Path) -> tuple[dict, int]:
    """The stored configuration and the step count of the run that writes ``rel`` (checkpoints/folds/<regime>/
    <fold>/<model>.pt): what `rlsac folds --stage train` builds for it."""
    p, params = listed_protocol()
    _, _, regime, fold, name = rel.parts
    opts = folds.train_options(p, params, regime, fold, name.removesuffix(".pt"), {"device": "auto", "threads": 1})
    conf = check(opts, track=False)
    return stored_conf(conf), conf.sac.total_steps


def test_only_the_waiting_models_checkpoints_wait_and_none_is_in_place_yet():
    p, _ = listed_protocol()
    runs = {f"{WAITING}{suffix}" for suffix in [""] + [f"-s{s}" for s in p["seeds"]]}
    for rel in FILES:
        assert rel.parts[:3] == ("checkpoints", "folds", p["model_regime"]), rel
        assert rel.parts[3] in p["test"] and rel.suffix == ".pt" and rel.stem in runs, rel
        # while it waits, nothing in checkpoints/ (read by reports and figures) holds its runs
        assert not (ROOT / rel).exists(), f"{rel} is both pending and in place"
    assert not list((ROOT / "checkpoints").rglob(f"{WAITING}*.pt"))


@pytest.mark.parametrize("rel", FILES, ids=str)
def test_a_pending_checkpoint_is_a_finished_run_of_its_recipe(rel):
    ck = read(PENDING / rel)
    want, steps = expected_conf(rel)
    assert ck["conf"] == want  # the recipe (kernels included), the fold's files, the seed, the output path
    assert ck["step"] >= steps and ck["selection"] == "last"  # the final actor of a run that went the whole way
    assert ck["history"] and ck["history"][-1]["step"] == steps
