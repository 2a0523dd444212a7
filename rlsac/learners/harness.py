"""The training harness the learned samplers share (rlsac.learners): their options, data, validation, selection key,
stored configuration and MLflow run, and the learner registry.

``TrainConf`` holds the options of `rlsac train` (every learner's sections); ``stored_conf`` the configuration a
checkpoint keeps; ``load_data`` the training and validation batches; ``validation_summary`` and ``selection_score`` the
validation metrics and the one that keeps an actor; ``task_experiment`` / ``logged_conf`` the MLflow experiment and run
parameters; ``register_learner`` / ``LEARNERS`` the registry `rlsac train --method` picks from.

The checkpoint format is rlsac.rl.checkpoint's (an actor payload; NG-RANSAC's with kind "ngransac").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import torch

from rlsac.config import build, to_dict
from rlsac.data import n_unusable, slice_batch
from rlsac.errors import RlsacError
from rlsac.io import check_writable
from rlsac.rl.env import EnvConf
from rlsac.rl.episodes import EpisodeConf
from rlsac.rl.kernels import KERNELS, NEIGHBOUR_MAX, neighbour_max_for
from rlsac.rl.ngransac import NGRansacConf
from rlsac.rl.policy import PolicyConf
from rlsac.rl.sac import SACConf
from rlsac.tasks import TASKS, Task, get_task, read_batch, task_class
from rlsac.tracking import check_store

SELECTIONS = ("inlier_ratio", "val_mAA", "last")
# what `rlsac train --method` trains (their evaluate methods' names) -> the learner's train(conf, track, snapshots);
# filled by the learners' modules (rlsac.learners imports them, in this order)
LEARNERS: dict[str, Callable[..., dict]] = {}
# the sections of one trained method only: a checkpoint stores its own method's (an RLSAC checkpoint's conf, and so its
# bytes, are what they were before NG-RANSAC: `rlsac verify --include-train` compares them with the committed ones)
OWN_SECTIONS: dict[str, tuple[str, ...]] = {}


def register_learner(name: str, sections: tuple[str, ...]):
    """Decorator: register ``train(conf, track, snapshots) -> summary`` as learner ``name`` (`rlsac train --method
    name`), which alone reads the TrainConf ``sections``."""
    def deco(train):
        if name in LEARNERS:
            raise ValueError(f"learner '{name}' is registered twice")
        LEARNERS[name] = train
        OWN_SECTIONS[name] = tuple(sections)
        return train
    return deco


@dataclass
class TrainConf:
    task: str = "line"
    # "rlsac": SAC-Discrete (env, policy, sac); "ngransac": NG-RANSAC's training (rlsac.rl.ngransac: policy, ngransac)
    method: str = "rlsac"
    data: str = ""  # training file (lines h5 or prepared two-view h5)
    val_data: str = ""  # validation file; empty = no validation
    out: str = "checkpoints/line.pt"
    device: str = "auto"
    seed: int = 0
    resume: bool = False
    threads: int = 0  # torch CPU threads; 0 keeps torch's default
    val_instances: int = 200  # validation subset size: enough for a +-0.02 mAA estimate
    val_iterations: int = 150  # budget used for validation (Table 1 budget for lines)
    val_every: int = 500  # vector-env steps between validations
    ckpt_every: int = 500
    # Which validated actor is kept: "inlier_ratio" = the best mean inlier ratio of the final hypotheses
    # (the paper's unsupervised signal, no ground truth); "val_mAA" = the best validation mAA (ground-truth
    # poses: a departure from the paper, named in tables); "last" = the final actor.
    selection: str = "inlier_ratio"
    run_name: str = ""
    tags: dict = field(default_factory=dict)
    task_options: dict = field(default_factory=dict)  # passed to the task (threshold, residual, ...)
    env: EnvConf = field(default_factory=EnvConf)
    policy: PolicyConf = field(default_factory=PolicyConf)
    sac: SACConf = field(default_factory=SACConf)
    ngransac: NGRansacConf = field(default_factory=NGRansacConf)  # method "ngransac" only
    # not in the paper (issue #46): episodes redrawn from a pool of each pair's matches, images swapped at random
    # (rlsac.rl.episodes); the default, no pool, is the record's recipe (the training file's points every episode)
    episodes: EpisodeConf = field(default_factory=EpisodeConf)
    # also write the actor of these steps (a scale curve from one run: <out stem>.step<k>.pt beside ``out``)
    snapshot_steps: list[int] = field(default_factory=list)
    # the SAC update's dense products (rlsac.rl.kernels): "aten", the record's; "onednn", the same function about 1.5x
    # faster on CPU under the portable pins, other last bits (not in the paper: an implementation choice)
    kernels: str = "aten"
    # the SAC update's EdgeConv neighbour max (rlsac.rl.kernels): "eager", the record's; "compiled", torch.compile's
    # fused kernels (a C++ compiler at run time), the same bytes, 1.37x faster per update (reports/speed_training.json);
    # a speed setting, so a state trained with one resumes with the other
    neighbour_max: str = "eager"
    # not in the paper (issue #46, the pretraining arm): a training state (<out>.state.pt of another run) whose networks
    # (actor, critics, targets, temperature) start this run; its optimisers, replay buffer and step are not carried
    # (they belong to the other run's data): step 0, an empty buffer, fresh Adam moments. "" = random initialisation
    init: str = ""

    # checked by rlsac.config.build for every source (params.yaml, --set); nested sections have their own
    ranges = {"task": TASKS, "method": LEARNERS, "device": ("auto", "cpu", "cuda"), "seed": "[0, 4294967295]",
              "threads": "[0, inf)", "val_instances": "[1, inf)", "val_iterations": "[1, inf)",
              "val_every": "[1, inf)", "ckpt_every": "[1, inf)", "selection": SELECTIONS, "snapshot_steps": "[1, inf)",
              "kernels": KERNELS, "neighbour_max": NEIGHBOUR_MAX}


# options added after the record, left out of a stored configuration while at their default: the record's
# checkpoints (and so their bytes) are what they were (rlsac verify --include-train)
LATER_DEFAULTS = {"episodes": to_dict(EpisodeConf()), "snapshot_steps": [], "kernels": "aten", "init": ""}
# speed settings that leave every byte of a run as it is: never stored (a checkpoint is the same file either way, and a
# state resumes under either), logged with the run's parameters
SPEED_ONLY = ("neighbour_max",)
# keys added to a section after runs that stored it, left out while at their default (the scale study's states resume
# only a state whose stored configuration is their own: saved_step below)
LATER_SECTION_DEFAULTS = {"episodes": {"prefilter": []}}


# top-level options only RLSAC's learner reads (issue #64: `--method ngransac --set kernels=onednn` recorded kernels
# onednn in the checkpoint and the run): another learner refuses them away from their defaults
RLSAC_ONLY = ("episodes", "snapshot_steps", "kernels", "neighbour_max", "init")


def stored_conf(conf: TrainConf) -> dict:
    """The configuration a checkpoint and its MLflow run keep: every field but the other methods' sections (and, for
    RLSAC, the ``method`` key: its default; ``LATER_DEFAULTS`` at their defaults; ``SPEED_ONLY``)."""
    other = {s for m, secs in OWN_SECTIONS.items() if m != conf.method for s in secs}
    out = {k: v for k, v in to_dict(conf).items() if k not in other and not (k == "method" and conf.method == "rlsac")
           and not (k in LATER_DEFAULTS and v == LATER_DEFAULTS[k]) and k not in SPEED_ONLY}
    for sec, later in LATER_SECTION_DEFAULTS.items():
        if sec in out:
            out[sec] = {k: v for k, v in out[sec].items() if not (k in later and v == later[k])}
    return out


def check_params(params: dict) -> None:
    """params.yaml ``train``: per registered task, TrainConf options (every nested section typed, ranged)."""
    from rlsac.config import section

    for task in section(params, "train"):
        task_class(task)
        build(TrainConf, {**section(params, "train", task), "task": task}, "train")


def check(options: dict, track: bool = True) -> TrainConf:
    """A training's configuration, task options, outputs and tracking store checked (not its data files: the
    caller reads them, once when several trainings share them) -> the TrainConf."""
    conf = build(TrainConf, options, "train")  # types and ranges of every section (task, selection, sac, env, ...)
    if not conf.data:
        raise RlsacError("train needs --data")
    _task(conf)
    if conf.episodes.prefilter and not conf.episodes.pool:
        raise RlsacError("episodes.prefilter needs episodes.pool (pre-filters are drawn with redrawn episodes)")
    if conf.method != "rlsac":  # recorded in the checkpoint and the run, they would say it trained with them
        defaults = TrainConf()
        unread = [k for k in RLSAC_ONLY if getattr(conf, k) != getattr(defaults, k)]
        if unread:
            raise RlsacError(f"{unread[0]}: the {conf.method} learner does not read it (RLSAC's training only: "
                             f"{', '.join(RLSAC_ONLY)})")
    if conf.init and not conf.resume and not Path(conf.init).is_file():
        raise RlsacError(f"{conf.init}: no such training state to start from (train --set init=...)")
    out = check_writable(conf.out, "checkpoint")
    check_writable(out.with_suffix(".state.pt"), "training state")
    neighbour_max_for(conf.neighbour_max)  # a missing C++ compiler is named here, before any work
    check_store(track, task_experiment(conf.task))
    return conf


def logged_conf(conf_dict: dict) -> dict:
    """The MLflow run parameters of a training: its stored configuration but ``resume``."""
    return {k: v for k, v in conf_dict.items() if k != "resume"}


def load_data(conf: TrainConf, device) -> tuple[Task, dict, dict | None, dict[str, int]]:
    """-> (task, training batch with the network's features, validation batch or None, the instances of each
    file its reader left out as unusable: {"data/n_unusable", "val_data/n_unusable"})."""
    task = _task(conf)
    data, attrs = read_batch(conf.task, conf.data, device)
    unusable = {"data/n_unusable": n_unusable(attrs), "val_data/n_unusable": 0}
    data["features"] = task.features(data)
    if conf.sac.warm_start_updates > 0:
        data["labels"] = task.true_inliers(data)
    if int(data["mask"].sum(-1).min()) < task.sample_size:
        raise RlsacError(f"{conf.data}: an instance has fewer than {task.sample_size} points")
    val = None
    if conf.val_data:
        val, attrs = read_batch(conf.task, conf.val_data, device)
        val, unusable["val_data/n_unusable"] = slice_batch(val, slice(0, conf.val_instances)), n_unusable(attrs)
    return task, data, val, unusable


def _task(conf: TrainConf) -> Task:
    try:
        return get_task(conf.task, **conf.task_options)
    except TypeError as e:  # an unknown task option
        raise RlsacError(f"bad task_options for task '{conf.task}': {e}") from None


def snapshot_path(out: str | Path, step: int) -> Path:
    """Where ``snapshot_steps`` writes the actor of ``step``: beside ``out``, <stem>.step<step>.pt."""
    out = Path(out)
    return out.with_name(f"{out.stem}.step{int(step)}.pt")


SELECTION_KEY = {"inlier_ratio": "charts/val_inlier_ratio", "val_mAA": "charts/val_mAA"}


def selection_score(selection: str) -> str:
    """The validation metric a selection rule ranks actors by (``last`` keeps the final one; its validations are
    still scored by validation mAA)."""
    return SELECTION_KEY.get(selection, "charts/val_mAA")


def validation_summary(task, val: dict, res: dict) -> dict:
    """A sampler's result ``res`` (hyp, valid, inliers) on the validation batch -> the task's metrics (ground
    truth) and the mean inlier ratio of the final hypotheses (no ground truth) as ``charts/val_*``: the
    selection signals of every trained sampler (RLSAC, NG-RANSAC)."""
    errs = task.errors(res["hyp"].cpu().numpy(), res["valid"].cpu().numpy(), res["inliers"].cpu().numpy(),
                       to_numpy(val))
    summ = {f"charts/val_{k}": v for k, v in task.summarize(errs).items() if k != "n"}
    ratio = res["inliers"].sum(-1).float() / val["mask"].sum(-1).clamp_min(1)
    summ["charts/val_inlier_ratio"] = float(ratio.mean())
    return summ


def task_experiment(task: str) -> str:
    return task_class(task).experiment


def to_numpy(batch: dict) -> dict:
    return {k: (v.cpu().numpy() if torch.is_tensor(v) else v) for k, v in batch.items()}


def saved_step(opts: dict) -> int:
    """The step of the training state beside ``opts["out"]`` when this run's own configuration wrote it (its legs'
    ends and snapshots aside), else 0: a state of another recipe is never resumed, the run starts over. What lets a
    long training (the scale study's legs, a fold model killed at a session's end) resume instead of re-running."""
    state = Path(opts["out"]).with_suffix(".state.pt")
    if not state.is_file():
        return 0
    try:  # mmap: only the step and the conf are read, not the replay buffer (hundreds of MB at 10k steps)
        st = torch.load(state, map_location="cpu", weights_only=False, mmap=True)
    except Exception:  # noqa: BLE001 (any unreadable state: start over, as for a missing one)
        return 0

    def key(conf: dict) -> dict:
        conf = {k: v for k, v in conf.items() if k not in ("snapshot_steps", "ckpt_every", "resume")}
        return {**conf, "sac": {k: v for k, v in conf.get("sac", {}).items() if k != "total_steps"}}

    here = stored_conf(build(TrainConf, opts, "train"))
    return int(st.get("step", 0)) if key(st.get("conf", {})) == key(here) else 0
