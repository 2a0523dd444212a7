"""``rlsac train``: build the configuration, load data, run SAC-Discrete, write checkpoints and MLflow.

Two files per run: ``out`` (actor weights + the configuration: small, what ``rlsac evaluate``
loads) and ``out.state.pt`` (critics, targets, temperature, optimisers, RNG, the filled part of the
replay buffer, the kept actor and the MLflow run id: what ``--resume`` needs). States are saved at the
end of an episode, so ``--resume`` after a kill reproduces the uninterrupted run exactly (same seed ->
same final and kept models). The state file is the reference: on ``--resume`` an ``out`` left from
another step by a kill between the two writes is rewritten from it, and stale temporary files are removed.
SIGINT / SIGTERM stop at the end of the running episode, save the state and end the MLflow run KILLED;
``--resume`` continues the same MLflow run.
The actor kept in ``out`` is the one with the best validation mAA seen so far.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from rlsac import checkpoint
from rlsac.config import build, to_dict
from rlsac.data import n_unusable, slice_batch
from rlsac.devices import resolve_device
from rlsac.env import EnvConf
from rlsac.episodes import EpisodeConf, RedrawnPairs, pool_tensors
from rlsac.errors import Interrupted, RlsacError
from rlsac.io import atomic_path, check_writable, clean_stale_temps, load_torch
from rlsac.ngransac import NGRansacConf
from rlsac.policy import PolicyConf
from rlsac.rollout import in_channels, rlsac_estimate
from rlsac.sac import ReplayBuffer, SACAgent, SACConf, seed_everything, train_loop
from rlsac.signals import StopOnSignal as _StopOnSignal  # shared with every command (rlsac.signals)
from rlsac.tasks import TASKS, Task, get_task, read_batch, task_class
from rlsac.tracking import check_store, start_run

SELECTIONS = ("inlier_ratio", "val_mAA", "last")
TRAINED_METHODS = ("rlsac", "ngransac")  # what `rlsac train --method` trains (their evaluate methods' names)


@dataclass
class TrainConf:
    task: str = "line"
    # "rlsac": SAC-Discrete (env, policy, sac); "ngransac": NG-RANSAC's training (rlsac.ngransac: policy, ngransac)
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
    # (rlsac.episodes); the default, no pool, is the record's recipe (the training file's points every episode)
    episodes: EpisodeConf = field(default_factory=EpisodeConf)
    # also write the actor of these steps (a scale curve from one run: <out stem>.step<k>.pt beside ``out``)
    snapshot_steps: list[int] = field(default_factory=list)

    # checked by rlsac.config.build for every source (params.yaml, --set); nested sections have their own
    ranges = {"task": TASKS, "method": TRAINED_METHODS, "device": ("auto", "cpu", "cuda"), "seed": "[0, 4294967295]",
              "threads": "[0, inf)", "val_instances": "[1, inf)", "val_iterations": "[1, inf)",
              "val_every": "[1, inf)", "ckpt_every": "[1, inf)", "selection": SELECTIONS, "snapshot_steps": "[1, inf)"}


# the sections of one trained method only: a checkpoint stores its own method's (an RLSAC checkpoint's conf, and so its
# bytes, are what they were before NG-RANSAC: `rlsac verify --include-train` compares them with the committed ones)
OWN_SECTIONS = {"rlsac": ("env", "sac"), "ngransac": ("ngransac",)}


# options added after the record, left out of a stored configuration while at their default: the record's
# checkpoints (and so their bytes) are what they were (rlsac verify --include-train)
LATER_DEFAULTS = {"episodes": to_dict(EpisodeConf()), "snapshot_steps": []}


def stored_conf(conf: TrainConf) -> dict:
    """The configuration a checkpoint and its MLflow run keep: every field but the other methods' sections (and, for
    RLSAC, the ``method`` key: its default; ``LATER_DEFAULTS`` at their defaults)."""
    other = {s for m, secs in OWN_SECTIONS.items() if m != conf.method for s in secs}
    return {k: v for k, v in to_dict(conf).items() if k not in other and not (k == "method" and conf.method == "rlsac")
            and not (k in LATER_DEFAULTS and v == LATER_DEFAULTS[k])}


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
    out = check_writable(conf.out, "checkpoint")
    check_writable(out.with_suffix(".state.pt"), "training state")
    check_store(track, task_experiment(conf.task))
    return conf


def train(options: dict, track: bool = True, snapshots: list | None = None) -> dict:
    """``rlsac train``: options -> TrainConf; train, keep the selected actor in ``out``; -> a summary.
    ``snapshots``: a list that receives the checkpoint payload of every validated actor, kept or not (rlsac.selection
    replays a fold model's training to measure the choice; nothing of the run itself changes)."""
    conf = check(options, track)
    out, state_path = Path(conf.out), Path(conf.out).with_suffix(".state.pt")
    if conf.threads > 0:
        torch.set_num_threads(conf.threads)
    device = resolve_device(conf.device)
    if conf.method == "ngransac" and snapshots is not None:
        raise RlsacError("train: snapshots of every validated actor are RLSAC's training's (rlsac.selection)")
    if conf.method == "ngransac":  # its own training (rlsac.ngransac): same data, validation and selection
        from rlsac import ngransac

        return ngransac.train(conf, track)
    task, data, val, unusable = load_data(conf, device)
    gen = seed_everything(conf.seed)
    if device.type != "cpu":
        gen = torch.Generator(device=device).manual_seed(conf.seed)
    agent = SACAgent(in_channels(task), conf.policy, conf.sac).to(device)
    episodes = None
    if conf.episodes.pool:  # issue #46: a fresh draw of each pair's pool per episode
        pool, _ = read_batch(conf.task, conf.episodes.pool, device)
        episodes = RedrawnPairs(task, pool_tensors(pool, device), agent.actor, conf.episodes.points, conf.episodes.swap)
    for p in (out, state_path):  # left by a process killed while saving
        clean_stale_temps(p)
    run = _TrainingRun(conf, task, agent, gen, val, out, state_path, device)
    run.snapshots = snapshots
    if conf.resume:
        run.resume(data)

    stop = run.stop = _StopOnSignal()
    with start_run(task_experiment(conf.task), run.name(), run.logged_conf(), tags=run.tags(), enabled=track,
                   run_id=run.old_run_id) as mlflow_run, stop:
        run.mlflow_id = mlflow_run.run_id
        mlflow_run.metrics(unusable)  # instances the readers left out (rlsac.data.validity), 0 when none
        t0 = time.time()
        run.buffer = train_loop(agent, task, data, conf.env, run.start, gen, log=mlflow_run.metrics,
                                validate=run.validate if val is not None else None, val_every=conf.val_every,
                                checkpoint=run.save_state, ckpt_every=conf.ckpt_every, buffer=run.buffer, stop=stop,
                                episodes=episodes, on_step=run.snapshot if conf.snapshot_steps else None)
        if stop.signum and run.saved["after_signal"] and run.saved["step"] < conf.sac.total_steps:
            raise Interrupted(f"interrupted by {signal.Signals(stop.signum).name} at step {run.saved['step']} of "
                              f"{conf.sac.total_steps}: state saved to {state_path}; continue with --resume",
                              stop.signum)
        final = run.finish()
        seconds = time.time() - t0
        mlflow_run.metrics({"time/train_seconds": seconds})
        mlflow_run.artifact(out, "checkpoint")
    return {"checkpoint": str(out), "state": str(state_path), "steps": conf.sac.total_steps,
            "seconds": round(seconds, 1), "selection": conf.selection, "best_score": run.best["score"],
            "best_step": run.best.get("step"), "final_val": final,
            **{k.replace("/", "_"): v for k, v in unusable.items() if v}}


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


class _TrainingRun:
    """What one training run keeps between the training loop's callbacks: the validation history, the
    best score, the kept actor (``out``) and the training state (``out.state.pt``) with their writes."""

    def __init__(self, conf: TrainConf, task: Task, agent: SACAgent, gen: torch.Generator, val: dict | None,
                 out: Path, state_path: Path, device) -> None:
        self.conf, self.task, self.agent, self.gen, self.val = conf, task, agent, gen, val
        self.out, self.state_path, self.device = out, state_path, device
        self.conf_dict = stored_conf(conf)
        self.start, self.best, self.history = 0, {"score": -1.0}, []
        self.buffer: ReplayBuffer | None = None
        self.kept: dict | None = None  # the checkpoint payload of the kept actor
        self.old_run_id: str | None = None
        self.mlflow_id: str | None = None
        self.saved = {"step": 0, "after_signal": False}  # the last state saved, and whether a signal preceded it
        self.stop: _StopOnSignal | None = None
        self.snapshots: list | None = None  # every validated actor's payload, when a caller asks (train's snapshots)

    # ------------------------------------------------------------ MLflow run
    def name(self) -> str:
        conf = self.conf
        name = conf.run_name or f"train {conf.task} {self.out.stem} ({Path(conf.data).stem})"
        return name + (f" resumed at {self.start}" if conf.resume else "")

    def logged_conf(self) -> dict:
        return {k: v for k, v in self.conf_dict.items() if k != "resume"}

    def tags(self) -> dict:
        tags = {"command": "train", **self.conf.tags, "out": str(self.out)}
        if self.old_run_id:
            tags["resumed_from"] = self.old_run_id
        return tags

    # ------------------------------------------------------------ resume
    def resume(self, data: dict) -> None:
        """Restore agent, optimisers, RNG, buffer, history and kept actor from the state file; rewrite
        ``out`` from it when a kill between the two writes left another step there."""
        agent = self.agent
        if not self.state_path.is_file():
            raise RlsacError(f"{self.state_path}: nothing to resume from")
        st = load_torch(self.state_path, self.device, "training state")
        saved_on = st.get("generator_device", self.device.type)  # states written before the key: their own device
        if saved_on != self.device.type:  # a torch generator's stream is device-specific: it cannot carry across
            raise RlsacError(f"{self.state_path}: written by a run on {saved_on}; resume it with --device {saved_on}")
        try:
            agent.load_state_dict(st["agent"])
            for name in ("q_opt", "actor_opt", "alpha_opt"):
                getattr(agent, name).load_state_dict(st[name])
            self.start, self.best, self.history = st["step"], {"score": -1.0, **st["best"]}, st.get("history", [])
            self.gen.set_state(st["generator"].cpu())  # a generator's state is a CPU byte tensor on every device
            if st.get("buffer") is not None:
                pool = bool(self.conf.episodes.pool)
                self.buffer = ReplayBuffer(self.conf.sac.buffer_size,
                                           self.conf.episodes.points if pool else data["mask"].shape[1],
                                           self.task.sample_size, self.device,
                                           extra=self.conf.episodes.points + 1 if pool else 0)
                self.buffer.load_state_dict(st["buffer"])
        except (KeyError, RuntimeError, ValueError, TypeError) as e:
            raise RlsacError(f"{self.state_path}: does not fit this configuration and data "
                             f"({e.__class__.__name__}: {' '.join(str(e).split())[:100]})") from None
        self.old_run_id, self.kept = st.get("mlflow_run_id"), st.get("kept_actor")
        self.saved["step"] = self.start
        if self.kept is not None:  # the pair: out must hold the actor the state kept
            try:
                on_disk = checkpoint.read(self.out)
            except RlsacError:
                on_disk = {}
            if on_disk.get("step") != self.kept.get("step"):
                checkpoint.write(self.out, self.kept)

    # ------------------------------------------------------------ callbacks of the training loop
    def validate(self, step: int) -> dict:
        """Validate the actor; keep it (``out``) when it beats the best score of the selection rule."""
        summ = validation_metrics(self.task, self.val, self.agent, self.conf, self.device)
        self.history.append({"step": step, **summ})
        if self.snapshots is not None:
            self.snapshots.append(checkpoint.actor_payload(self.agent.actor, self.conf_dict, in_channels(self.task),
                                                           step, summ, self.conf.selection, self.history,
                                                           checkpoint.training_scales(self.task)))
        score = summ[selection_score(self.conf.selection)]
        if self.conf.selection != "last" and score > self.best["score"]:
            self.best.update(score=score, step=step, **summ)
            self.save_actor(step, summ)
        return summ

    def save_actor(self, step: int, metrics: dict) -> None:
        self.kept = checkpoint.actor_payload(self.agent.actor, self.conf_dict, in_channels(self.task), step, metrics,
                                             self.conf.selection, self.history, checkpoint.training_scales(self.task))
        checkpoint.write(self.out, self.kept)

    def snapshot(self, step: int) -> None:
        """After vector-env step ``step``: the actor of a step in ``snapshot_steps`` -> <out stem>.step<step>.pt."""
        if step in self.conf.snapshot_steps:
            checkpoint.write(snapshot_path(self.out, step), checkpoint.actor_payload(
                self.agent.actor, self.conf_dict, in_channels(self.task), step, {}, "step",
                self.history, checkpoint.training_scales(self.task)))

    def save_state(self, step: int, buf=None) -> None:
        """Everything a resume needs, the kept actor included, in one file: a kill between this write and
        the actor's leaves a pair that --resume repairs from here."""
        agent = self.agent
        self.buffer = buf if buf is not None else self.buffer
        if self.val is None or self.conf.selection == "last":  # the latest actor is the one to keep
            self.save_actor(step, self.history[-1] if self.history else {})
        with atomic_path(self.state_path) as tmp:
            torch.save({"agent": agent.state_dict(), "q_opt": agent.q_opt.state_dict(),
                        "actor_opt": agent.actor_opt.state_dict(), "alpha_opt": agent.alpha_opt.state_dict(),
                        "step": step, "best": self.best, "history": self.history, "generator": self.gen.get_state(),
                        "generator_device": self.gen.device.type,
                        "buffer": self.buffer.state_dict() if self.buffer is not None else None,
                        "kept_actor": self.kept, "mlflow_run_id": self.mlflow_id, "conf": self.conf_dict}, tmp)
        self.saved.update(step=step, after_signal=bool(self.stop is not None and self.stop.signum))

    def finish(self) -> dict:
        """The final validation (unless the last one was at the final step), the kept actor with the whole
        learning curve, and the final state; -> the final validation metrics."""
        conf, steps = self.conf, self.conf.sac.total_steps
        done_before = bool(self.history) and self.history[-1]["step"] == steps
        final = {} if self.val is None else self.history[-1] if done_before else self.validate(steps)
        if self.kept is not None and conf.selection != "last":  # the kept actor carries the whole curve
            self.kept["history"] = list(self.history)
            checkpoint.write(self.out, self.kept)
        self.save_state(steps)
        return final


def snapshot_path(out: str | Path, step: int) -> Path:
    """Where ``snapshot_steps`` writes the actor of ``step``: beside ``out``, <stem>.step<step>.pt."""
    out = Path(out)
    return out.with_name(f"{out.stem}.step{int(step)}.pt")


SELECTION_KEY = {"inlier_ratio": "charts/val_inlier_ratio", "val_mAA": "charts/val_mAA"}


def selection_score(selection: str) -> str:
    """The validation metric a selection rule ranks actors by (``last`` keeps the final one; its validations are
    still scored by validation mAA)."""
    return SELECTION_KEY.get(selection, "charts/val_mAA")


@torch.no_grad()
def validation_metrics(task, val: dict, agent: SACAgent, conf: TrainConf, device) -> dict:
    """The actor on the validation set at ``val_iterations`` (fixed seed): the task's metrics (ground
    truth) and the mean inlier ratio of the final hypotheses (no ground truth), as ``charts/val_*``."""
    agent.actor.eval()
    res = rlsac_estimate(task, val, agent.actor, conf.val_iterations, conf.env,
                         generator=torch.Generator(device=device).manual_seed(1234))
    agent.actor.train()
    return validation_summary(task, val, res)


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



