"""The policy's state is decoupled from the evaluation threshold (issue #46).

A checkpoint carries the residual scale its policy was trained with (``state_scales``); evaluating it at another
inlier threshold changes which points count as inliers, never the residual feature the policy sees. A checkpoint
written before the key keeps the record's behaviour (the feature at the evaluation threshold).
"""

from __future__ import annotations

import pytest
import torch

from rlsac.evaluation.evaluate import EvalOptions
from rlsac.evaluation.methods import METHODS
from rlsac.rl import checkpoint
from rlsac.rl.policy import Actor, PolicyConf
from rlsac.rl.rollout import in_channels
from rlsac.tasks.fundamental import FundamentalTask
from tests.test_speed_equivalence import two_view_batch

POLICY = {"k": 8, "widths": [8, 8], "global_width": 8, "head_width": 8, "graph_dims": 4}


def _checkpoint(path, scales):
    torch.manual_seed(0)
    task = FundamentalTask()
    actor = Actor(in_channels(task), PolicyConf(**POLICY))
    conf = {"task": "fundamental", "task_options": {}, "policy": POLICY, "env": {}}
    checkpoint.write(path, checkpoint.actor_payload(actor, conf, in_channels(task), 1, {}, "last", [], scales))
    return path


def _first_memories(path, threshold_px, monkeypatch):
    """The memory channels of the policy's first call when the checkpoint is evaluated at ``threshold_px``."""
    seen = []
    forward = Actor.forward_memory

    def spy(self, prep, memory):
        seen.append(memory.clone())
        return forward(self, prep, memory)

    monkeypatch.setattr(Actor, "forward_memory", spy)
    o = EvalOptions(task="fundamental", method="rlsac", data="", checkpoint=str(path), iterations=30,
                    threshold_px=threshold_px, steps_per_episode=15)
    task, estimate, extra = METHODS["rlsac"].build(o, "cpu")
    estimate(two_view_batch(2, N=60, seed=3), torch.Generator().manual_seed(7))
    return task, extra, seen[0]


def test_two_evaluation_thresholds_give_the_policy_the_same_state(tmp_path, monkeypatch):
    path = _checkpoint(tmp_path / "m.pt", checkpoint.training_scales(FundamentalTask()))  # 4 px^2 = 2 px
    task_a, extra_a, mem_a = _first_memories(path, 0.75, monkeypatch)
    task_b, extra_b, mem_b = _first_memories(path, 3.0, monkeypatch)
    assert (task_a.threshold, task_b.threshold) == (0.5625, 9.0)  # the evaluations do score differently
    assert extra_a["state_threshold"] == extra_b["state_threshold"] == 4.0  # recorded in config.json
    assert torch.equal(mem_a, mem_b)  # same random first set (same seed): the same state, so the same logits
    # the residual channel is min(r / 4, 5) / 5 of the training unit: a point at r = 2 px^2 reads 0.1
    assert 0.0 <= float(mem_a[..., 1].min()) and float(mem_a[..., 1].max()) == 1.0


def test_a_checkpoint_from_before_the_key_sees_the_evaluation_threshold(tmp_path, monkeypatch):
    path = _checkpoint(tmp_path / "old.pt", None)
    assert "state_scales" not in checkpoint.read(path)
    _, extra_a, mem_a = _first_memories(path, 0.75, monkeypatch)
    _, extra_b, mem_b = _first_memories(path, 3.0, monkeypatch)
    assert "state_threshold" not in extra_a  # its config.json stays as the record wrote it
    assert not torch.equal(mem_a[..., 1], mem_b[..., 1])  # coupled: the record's behaviour
    assert torch.equal(mem_a[..., 0], mem_b[..., 0])  # only the residual channel moves


def test_training_writes_the_scales_and_a_bad_value_is_refused(tmp_path):
    assert checkpoint.training_scales(FundamentalTask(threshold=2.25)) == {"residual_threshold": 2.25}
    bad = _checkpoint(tmp_path / "bad.pt", {"residual_threshold": -1.0})
    from rlsac.errors import RlsacError

    with pytest.raises(RlsacError, match="state_scales must be {residual_threshold: <a positive number>}"):
        checkpoint.state_scales(bad)


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    from test_reliability import _fundamental  # tests/ is on sys.path (pytest prepend mode)

    return _fundamental(tmp_path_factory.mktemp("pairs"))


@pytest.mark.parametrize("scales, fragment", [
    ({"residual_threshold": True}, "state_scales must be {residual_threshold: <a positive number>}, got "
                                   "{'residual_threshold': True}"),
    ({"residual_threshold": float("nan")}, "state_scales must be"),
    ({"residual_threshold": 0.0}, "state_scales must be"),
    ({"residual_threshold": 4.0, "other": 1.0}, "state_scales must be"),
    ({"residual_threshold": 1e-300}, "state_scales.residual_threshold 1e-300 is more than 1e+06 times off"),
    ({"residual_threshold": 1e300}, "state_scales.residual_threshold 1e+300 is more than 1e+06 times off"),
], ids=["bool", "nan", "zero", "unknown-key", "tiny", "huge"])
def test_evaluate_refuses_a_checkpoint_whose_state_scales_are_no_scale(tmp_path, monkeypatch, pairs, scales,
                                                                      fragment):
    """Issue #64: a bool scale was read as 1 (the residual channel scaled by 1 px^2 without a word), absurd ones
    saturated or flattened it; each is now an error naming the checkpoint, before any evaluation."""
    from click.testing import CliRunner

    from rlsac.cli import cli

    monkeypatch.chdir(tmp_path)
    path = _checkpoint(tmp_path / "m.pt", None)
    payload = checkpoint.read(path)
    payload["state_scales"] = scales  # as written (actor_payload would make a float of the bool)
    checkpoint.write(path, payload)
    h5 = pairs
    r = CliRunner().invoke(cli, ["evaluate", "--task", "fundamental", "--method", "rlsac", "--checkpoint", str(path),
                                 "--data", str(h5), "--out-dir", "ev", "--params", "", "--no-tracking"])
    assert r.exit_code == 2, r.output
    err = r.stderr.strip()
    assert err.startswith(f"error: {path}: ") and "\n" not in err and fragment in err, err
    assert not (tmp_path / "ev").exists()


def test_a_checkpoint_without_state_scales_says_so_where_it_falls_back(tmp_path, monkeypatch, capsys):
    path = _checkpoint(tmp_path / "old.pt", None)
    _first_memories(path, 0.75, monkeypatch)
    err = capsys.readouterr().err
    assert f"note: {path} has no state_scales" in err and "evaluation threshold 0.5625" in err, err
