"""The ladder's committed run records (experiments/ladder, issue #61) are what their command writes with params.yaml:
the runs land one by one across sessions, before their stages join dvc.yaml, so nothing else checks them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from rlsac.layout.ladder_layout import ROOT as LADDER
from rlsac.layout.ladder_layout import actor_file, conf, rungs
from rlsac.rl import checkpoint

REPO = Path(__file__).resolve().parents[1]
C = conf(yaml.safe_load((REPO / "params.yaml").read_text()))
RUNS = sorted((REPO / LADDER).glob("*/s*.json"))
CONTROLS = sorted((REPO / LADDER).glob("*/controls.json"))


def test_every_record_is_a_rung_and_seed_of_params():
    names = set(rungs(C))
    for path in RUNS:
        assert path.parent.name in names, path
        assert int(path.stem[1:]) in C["seeds"], path
    for path in CONTROLS:
        assert path.parent.name in names, path


@pytest.mark.parametrize("path", RUNS, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_run_record(path):
    rec = json.loads(path.read_text())
    rung = rungs(C)[path.parent.name]
    assert rec["rung"] == rung.name and rec["seed"] == int(path.stem[1:]) and rec["steps"] == C["steps"]
    assert sorted(rec["final"], key=int) == [str(i) for i in C["iterations"]]
    steps = [row["step"] for row in rec["curve"]]
    if rung.learner == "scale":  # the scale study's snapshots up to ladder.steps
        assert steps[-1] == C["steps"]
    else:
        assert steps == list(range(0, C["steps"] + 1, C["every"]))
    for m in rec["final"].values():
        assert len(m["err_R"]) == len(m["err_t"]) == len(m["pi_inliers"]) == rec["pairs"]
    ckpt = checkpoint.read(REPO / actor_file(rung.name, rec["seed"]))
    assert ckpt["conf"]["ladder"] == rung.name and ckpt["step"] == C["steps"]


@pytest.mark.parametrize("path", CONTROLS, ids=lambda p: p.parent.name)
def test_controls_record(path):
    rec = json.loads(path.read_text())
    assert set(rec["samplers"]) == {"uniform", "guided", "oracle"}
    for per in rec["samplers"].values():
        assert sorted(per, key=int) == [str(i) for i in C["iterations"]]


def test_ladder_record_lists_exactly_the_committed_runs():
    """params ladder_record names one dvc.yaml stage per committed record, under its rung's kind: a record missing
    from it is not reproducible by `dvc repro`, a listed run missing from the tree is a stage that would run."""
    record = yaml.safe_load((REPO / "params.yaml").read_text())["ladder_record"]
    all_rungs = rungs(C)
    listed = {}
    for kind in ("synthetic", "real"):
        for name, item in record[kind].items():
            assert name == f"{item['arm']}-s{item['seed']}", name
            assert all_rungs[item["arm"]].data == kind, name
            listed[(item["arm"], item["seed"])] = kind
    committed = {(p.parent.name, int(p.stem[1:])) for p in RUNS}
    assert set(listed) == committed
    for kind in ("synthetic", "real"):
        for arm in record[f"{kind}_controls"]:
            assert all_rungs[arm].data == kind and not all_rungs[arm].controls_from, arm
    controls = [a for k in ("synthetic", "real") for a in record[f"{k}_controls"]]
    assert sorted(controls) == sorted(p.parent.name for p in CONTROLS)
