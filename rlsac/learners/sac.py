"""The RLSAC learner (`rlsac train --method rlsac`): SAC-Discrete over the environment, on the shared harness
(rlsac.learners.harness: configuration, data, validation, selection, checkpoint format, MLflow).

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
from pathlib import Path

import torch

from rlsac.devices import resolve_device
from rlsac.errors import Interrupted, RlsacError
from rlsac.io import atomic_path, clean_stale_temps, load_torch
from rlsac.learners.harness import (
    SPEED_ONLY,
    TrainConf,
    load_data,
    logged_conf,
    register_learner,
    selection_score,
    snapshot_path,
    stored_conf,
    task_experiment,
    validation_summary,
)
from rlsac.rl import checkpoint
from rlsac.rl.episodes import RedrawnPairs, pool_tensors
from rlsac.rl.rollout import in_channels, rlsac_estimate
from rlsac.rl.sac import ReplayBuffer, SACAgent, seed_everything, train_loop
from rlsac.signals import StopOnSignal as _StopOnSignal  # shared with every command (rlsac.signals)
from rlsac.tasks import Task, read_batch
from rlsac.tracking import start_run


@register_learner("rlsac", sections=("env", "sac"))
def train(conf: TrainConf, track: bool = True, snapshots: list | None = None) -> dict:
    """RLSAC's training: ``conf`` a checked TrainConf (rlsac.learners.harness.check; method "rlsac"); train, keep the
    selected actor in ``out``; -> a summary. ``snapshots``: a list that receives the checkpoint payload of every
    validated actor, kept or not (rlsac.experiments.selection replays a fold model's training to measure the choice;
    nothing of the run itself changes)."""
    out, state_path = Path(conf.out), Path(conf.out).with_suffix(".state.pt")
    if conf.threads > 0:
        torch.set_num_threads(conf.threads)
    device = resolve_device(conf.device)
    task, data, val, unusable = load_data(conf, device)
    gen = seed_everything(conf.seed)
    if device.type != "cpu":
        gen = torch.Generator(device=device).manual_seed(conf.seed)
    agent = SACAgent(in_channels(task), conf.policy, conf.sac).to(device).set_kernels(conf.kernels, conf.neighbour_max)
    episodes = None
    if conf.episodes.pool:  # issue #46: a fresh draw of each pair's pool per episode
        pool, _ = read_batch(conf.task, conf.episodes.pool, device)
        episodes = RedrawnPairs(task, pool_tensors(pool, device), agent.actor, conf.episodes.points, conf.episodes.swap,
                                conf.episodes.prefilter)
    for p in (out, state_path):  # left by a process killed while saving
        clean_stale_temps(p)
    run = _TrainingRun(conf, task, agent, gen, val, out, state_path, device)
    run.snapshots = snapshots
    if conf.resume:
        run.resume(data, episodes)
    elif conf.init:
        run.start_from(conf.init)

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
        return {**logged_conf(self.conf_dict), **{k: getattr(self.conf, k) for k in SPEED_ONLY}}

    def tags(self) -> dict:
        tags = {"command": "train", **self.conf.tags, "out": str(self.out)}
        if self.old_run_id:
            tags["resumed_from"] = self.old_run_id
        return tags

    # ------------------------------------------------------------ resume
    def resume(self, data: dict, episodes: RedrawnPairs | None = None) -> None:
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
                self.buffer = ReplayBuffer(self.conf.sac.buffer_size,
                                           episodes.n_points if episodes else data["mask"].shape[1],
                                           self.task.sample_size, self.device,
                                           extra=episodes.extra_width if episodes else 0)
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

    def start_from(self, path: str) -> None:
        """The networks of another run's training state (``init``: pretraining), nothing else of it."""
        st = load_torch(path, self.device, "training state")
        try:
            self.agent.load_state_dict(st["agent"])
        except (KeyError, RuntimeError, TypeError) as e:
            raise RlsacError(f"{path}: its networks do not fit this configuration "
                             f"({e.__class__.__name__}: {' '.join(str(e).split())[:100]})") from None

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


@torch.no_grad()
def validation_metrics(task, val: dict, agent: SACAgent, conf: TrainConf, device) -> dict:
    """The actor on the validation set at ``val_iterations`` (fixed seed): the task's metrics (ground
    truth) and the mean inlier ratio of the final hypotheses (no ground truth), as ``charts/val_*``."""
    agent.actor.eval()
    res = rlsac_estimate(task, val, agent.actor, conf.val_iterations, conf.env,
                         generator=torch.Generator(device=device).manual_seed(1234))
    agent.actor.train()
    return validation_summary(task, val, res)
