"""The RLSAC checkpoint format, in one place: written by ``rlsac train``, read by evaluate, the
figures, the benchmarks and the tests through the functions below.

A checkpoint is ``torch.save`` of a dict:
    actor        the Actor's state_dict (rlsac.rl.policy)
    conf         the resolved training configuration (rlsac.learners.harness.TrainConf as a dict): task, task_options,
                 env (the environment it was trained in), policy (the network's shape), sac, selection, ...
    in_channels  the actor's input channels (the task's data features + the environment's memory)
    step         the training step of this actor; val: its validation metrics; selection: how it was kept
    history      every validation of the run (the learning curve)
    state_scales the scales of the policy's state features it was trained with (issue #46), in the task's own
                 units: {"residual_threshold": eps_train}; the environment computes the residual feature with these
                 at any evaluation threshold. Absent in checkpoints written before the key: those are evaluated
                 with the residual feature at the evaluation threshold, as the record made them (``state_scales``)
    kind         absent for an RLSAC actor; "ngransac" for NG-RANSAC's sampling network (rlsac.rl.ngransac: the same
                 keys, ``actor`` its weights, ``in_channels`` the task's data features, no environment memory)
Training state for ``--resume`` (rlsac.learners.sac) is a separate file beside it and never read here.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import torch

from rlsac.config import build
from rlsac.errors import RlsacError
from rlsac.io import atomic_path, load_torch
from rlsac.rl.env import EnvConf
from rlsac.rl.policy import Actor, PolicyConf


def actor_payload(actor: torch.nn.Module, conf: dict[str, Any], in_channels: int, step: int, val: dict,
                  selection: str, history: list, state_scales: dict[str, float] | None = None) -> dict[str, Any]:
    """The checkpoint dict of ``actor`` (its weights copied: later optimiser steps do not change it);
    ``state_scales``: the scales of its state features (``training_scales``), stored when given."""
    payload = {"actor": {k: v.detach().clone() for k, v in actor.state_dict().items()}, "conf": conf,
               "in_channels": int(in_channels), "step": step, "val": val, "selection": selection,
               "history": list(history)}
    if state_scales is not None:
        payload["state_scales"] = {k: float(v) for k, v in state_scales.items()}
    return payload


def training_scales(task) -> dict[str, float]:
    """The state scales of a policy trained on ``task``: its inlier threshold is the residual feature's unit."""
    return {"residual_threshold": float(task.threshold)}


# how far a checkpoint's residual scale may be from the evaluation's threshold (both in the task's unit) before it is
# refused as no training threshold: a policy trained at 2 px and evaluated at 0.1 px is a ratio of 400 in px^2
SCALE_RATIO = 1e6


def state_scales(path: str | Path, device: str | torch.device = "cpu", unit: float | None = None
                 ) -> dict[str, float] | None:
    """The ``state_scales`` a checkpoint carries; None for one written before the key, and the caller says so (its
    policy then sees residuals at the evaluation threshold, as the record was made). RlsacError on a value that is
    not a positive finite number (issue #64: ``true`` was read as 1), or, given the task's threshold ``unit``, one
    more than ``SCALE_RATIO`` times off it (an absurd scale saturates or flattens the policy's residual channel)."""
    scales = read(path, device).get("state_scales")
    if scales is None:
        return None
    eps = scales.get("residual_threshold") if isinstance(scales, dict) else None
    if (not isinstance(eps, (int, float)) or isinstance(eps, bool) or not math.isfinite(eps) or not eps > 0
            or (isinstance(scales, dict) and set(scales) != {"residual_threshold"})):
        raise RlsacError(f"{path}: state_scales must be {{residual_threshold: <a positive number>}}, got "
                         f"{scales!r:.80}")
    if unit is not None and not unit / SCALE_RATIO <= eps <= unit * SCALE_RATIO:
        raise RlsacError(f"{path}: state_scales.residual_threshold {eps!r} is more than {SCALE_RATIO:g} times off "
                         f"the task's threshold {unit:g} (same unit): not a training threshold")
    return {"residual_threshold": float(eps)}


def to_bytes(payload: dict[str, Any]) -> bytes:
    """The checkpoint's bytes: equal payloads give equal bytes. (torch.save to a path names the zip archive
    inside after the file, so the random temporary name of an atomic write would change the md5.)"""
    buf = io.BytesIO()
    torch.save(payload, buf)
    return buf.getvalue()


def write(path: str | Path, payload: dict[str, Any]) -> None:
    """Write a checkpoint atomically (a killed write leaves the previous file)."""
    data = to_bytes(payload)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def read(path: str | Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    """The checkpoint dict (tensors on ``device``); RlsacError on a missing file or one that is not a
    torch file (a text or h5 file: one-line error)."""
    path = Path(path)
    if not path.is_file():
        raise RlsacError(f"{path}: no such checkpoint")
    return load_torch(path, device)


def kind_of(ckpt: dict[str, Any]) -> str:
    """Which trained sampler a checkpoint dict holds, named as its evaluate method: "rlsac" (no ``kind`` key: every
    RLSAC checkpoint, whose bytes stay as they were) or its ``kind`` ("ngransac")."""
    kind = ckpt.get("kind", "rlsac") if isinstance(ckpt, dict) else "unknown"
    return kind if isinstance(kind, str) else "unknown"


def load_actor(path: str | Path, device: str | torch.device = "cpu", kind: str = "rlsac") -> tuple[Actor, dict]:
    """Load an actor-shaped network of ``kind`` ("rlsac", or "ngransac": NG-RANSAC's network) -> (network in eval
    mode, training conf); RlsacError on a missing or bad file, or on a checkpoint of another kind."""
    ckpt = read(path, device)
    if kind_of(ckpt) != kind:
        raise RlsacError(f"{path}: a {kind_of(ckpt)} checkpoint, not an {kind} one (evaluate it with --method "
                         f"{kind_of(ckpt)})")
    try:
        conf = ckpt["conf"]
        actor = Actor(ckpt["in_channels"], build(PolicyConf, conf["policy"])).to(device)
        actor.load_state_dict(ckpt["actor"])
    except (KeyError, RuntimeError, EOFError, ValueError, TypeError) as e:
        raise RlsacError(f"{path}: not an {kind} checkpoint ({e.__class__.__name__}: {str(e)[:80]})") from None
    bad = [k for k, v in actor.state_dict().items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:  # a diverged training: every score would be NaN and every sample arbitrary
        raise RlsacError(f"{path}: non-finite weights in {bad[0]} ({len(bad)} tensor(s)); a diverged training?")
    actor.eval()
    actor.in_channels = int(ckpt["in_channels"])  # what ``check_reads`` compares with the sampler's input
    return actor, conf


def check_reads(path: str | Path, actor: Actor, want: int, kind: str) -> None:
    """The network must read the ``want`` channels ``kind``'s sampler feeds it: a checkpoint whose ``kind`` does not
    match its weights (an RLSAC actor labelled "ngransac") failed with a shape RuntimeError in the first batch."""
    have = getattr(actor, "in_channels", want)
    if have != want:
        raise RlsacError(f"{path}: its network reads {have} input channels, not the {want} a {kind} sampler gives "
                         "it (a 'kind' that does not match the weights?)")


def env_conf(ckpt_conf: dict | None, steps_per_episode: int | None = None) -> EnvConf:
    """The environment a checkpoint was trained with (its ``env`` section), psi optionally overridden."""
    env = dict((ckpt_conf or {}).get("env") or {})
    if steps_per_episode is not None:
        env["steps_per_episode"] = int(steps_per_episode)
    return build(EnvConf, env, "checkpoint env")


def task_options(ckpt_conf: dict[str, Any]) -> dict[str, Any]:
    """Task options stored in a checkpoint conf: ``task`` as a dict of options (with an optional
    ``name``), or ``task`` as the task name beside a ``task_options`` dict (rlsac.learners.harness.TrainConf)."""
    stored = ckpt_conf.get("task")
    if isinstance(stored, dict):
        return dict(stored)
    options = dict(ckpt_conf.get("task_options") or {})
    if isinstance(stored, str):
        options["name"] = stored
    return options
