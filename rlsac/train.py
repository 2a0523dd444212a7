"""``rlsac train``: build the configuration, load data, run SAC-Discrete, write checkpoints and MLflow.

Two files per run: ``out`` (actor weights + the configuration: small, what ``rlsac evaluate``
loads) and ``out.state.pt`` (critics, targets, temperature, optimisers, RNG: what ``--resume`` needs;
the replay buffer is not saved and refills for ``learning_starts`` transitions after a resume).
The actor kept in ``out`` is the one with the best validation mAA seen so far.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from rlsac.config import build, to_dict
from rlsac.data import load, slice_batch
from rlsac.devices import resolve_device
from rlsac.env import EnvConf
from rlsac.errors import RlsacError
from rlsac.io import atomic_path
from rlsac.policy import PolicyConf
from rlsac.rollout import in_channels, rlsac_estimate
from rlsac.sac import SACAgent, SACConf, seed_everything, train_loop
from rlsac.tasks import get_task
from rlsac.tracking import start_run


SELECTIONS = ("inlier_ratio", "val_mAA", "last")


@dataclass
class TrainConf:
    task: str = "line"
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


def train(options: dict, track: bool = True) -> dict:
    conf = build(TrainConf, options, "train")
    if not conf.data:
        raise RlsacError("train needs --data")
    if conf.sac.train_sampling not in ("prob", "max"):
        raise RlsacError(f"sac.train_sampling must be 'prob' or 'max', got {conf.sac.train_sampling!r}")
    if conf.selection not in SELECTIONS:
        raise RlsacError(f"selection must be one of {', '.join(SELECTIONS)}, got {conf.selection!r}")
    if conf.env.reward not in ("inlier_ratio", "improvement"):
        raise RlsacError(f"env.reward must be 'inlier_ratio' or 'improvement', got {conf.env.reward!r}")
    if conf.threads > 0:
        torch.set_num_threads(conf.threads)
    device = resolve_device(conf.device)
    task = get_task(conf.task, **conf.task_options)
    data = load(conf.task, conf.data, device)
    data["features"] = task.features(data)
    if conf.sac.warm_start_updates > 0:
        data["labels"] = task.true_inliers(data)
    if int(data["mask"].sum(-1).min()) < task.sample_size:
        raise RlsacError(f"{conf.data}: an instance has fewer than {task.sample_size} points")
    val = load(conf.task, conf.val_data, device) if conf.val_data else None
    if val is not None:
        val = slice_batch(val, slice(0, conf.val_instances))

    gen = seed_everything(conf.seed)
    if device.type != "cpu":
        gen = torch.Generator(device=device).manual_seed(conf.seed)
    agent = SACAgent(in_channels(task), conf.policy, conf.sac).to(device)
    out = Path(conf.out)
    state_path = out.with_suffix(".state.pt")
    start, best, history = 0, {"score": -1.0}, []
    if conf.resume:
        if not state_path.is_file():
            raise RlsacError(f"{state_path}: nothing to resume from")
        st = torch.load(state_path, map_location=device, weights_only=False)
        agent.load_state_dict(st["agent"])
        for name in ("q_opt", "actor_opt", "alpha_opt"):
            getattr(agent, name).load_state_dict(st[name])
        start, best, history = st["step"], {"score": -1.0, **st["best"]}, st.get("history", [])
        gen.set_state(st["generator"].to(gen.device) if device.type == "cpu" else st["generator"])
    conf_dict = to_dict(conf)
    run_name = conf.run_name or f"train {conf.task} {Path(conf.data).stem}"

    def save_actor(step: int, metrics: dict) -> None:
        with atomic_path(out) as tmp:
            torch.save({"actor": agent.actor.state_dict(), "conf": conf_dict, "in_channels": in_channels(task),
                        "step": step, "val": metrics, "selection": conf.selection, "history": history}, tmp)

    def save_state(step: int, _buffer=None) -> None:
        with atomic_path(state_path) as tmp:
            torch.save({"agent": agent.state_dict(), "q_opt": agent.q_opt.state_dict(),
                        "actor_opt": agent.actor_opt.state_dict(), "alpha_opt": agent.alpha_opt.state_dict(),
                        "step": step, "best": best, "history": history, "generator": gen.get_state(),
                        "conf": conf_dict}, tmp)
        if val is None or conf.selection == "last":  # the latest actor is the one to keep
            save_actor(step, history[-1] if history else {})

    with start_run(task_experiment(conf.task), run_name, conf_dict, tags=conf.tags, enabled=track) as run:
        def validate(step: int) -> dict:
            summ = validation_metrics(task, val, agent, conf, device)
            history.append({"step": step, **summ})
            score = summ[SELECTION_KEY.get(conf.selection, "charts/val_mAA")]
            if conf.selection != "last" and score > best["score"]:
                best.update(score=score, step=step, **summ)
                save_actor(step, summ)
            return summ

        t0 = time.time()
        train_loop(agent, task, data, conf.env, start, gen, log=run.metrics,
                   validate=validate if val is not None else None, val_every=conf.val_every,
                   checkpoint=save_state, ckpt_every=conf.ckpt_every)
        done_before = bool(history) and history[-1]["step"] == conf.sac.total_steps
        final = ({} if val is None else history[-1] if done_before else validate(conf.sac.total_steps))
        save_state(conf.sac.total_steps)
        seconds = time.time() - t0
        run.metrics({"time/train_seconds": seconds})
        run.artifact(out, "checkpoint")
    summary = {"checkpoint": str(out), "state": str(state_path), "steps": conf.sac.total_steps,
               "seconds": round(seconds, 1), "selection": conf.selection, "best_score": best["score"],
               "best_step": best.get("step"), "final_val": final}
    return summary


SELECTION_KEY = {"inlier_ratio": "charts/val_inlier_ratio", "val_mAA": "charts/val_mAA"}


@torch.no_grad()
def validation_metrics(task, val: dict, agent: SACAgent, conf: TrainConf, device) -> dict:
    """The actor on the validation set at ``val_iterations`` (fixed seed): the task's metrics (ground
    truth) and the mean inlier ratio of the final hypotheses (no ground truth), as ``charts/val_*``."""
    agent.actor.eval()
    res = rlsac_estimate(task, val, agent.actor, conf.val_iterations, conf.env,
                         generator=torch.Generator(device=device).manual_seed(1234))
    agent.actor.train()
    errs = task.errors(res["hyp"].cpu().numpy(), res["valid"].cpu().numpy(), res["inliers"].cpu().numpy(),
                       to_numpy(val))
    summ = {f"charts/val_{k}": v for k, v in task.summarize(errs).items() if k != "n"}
    ratio = res["inliers"].sum(-1).float() / val["mask"].sum(-1).clamp_min(1)
    summ["charts/val_inlier_ratio"] = float(ratio.mean())
    return summ


def task_experiment(task: str) -> str:
    return {"line": "lines"}.get(task, task)


def to_numpy(batch: dict) -> dict:
    return {k: (v.cpu().numpy() if torch.is_tensor(v) else v) for k, v in batch.items()}



