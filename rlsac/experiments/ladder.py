"""Where the learner stops (issue #61): a ladder of environments from the positive control to the fold's real pairs.

RLSAC learns to sample on synthetic pairs whose SNN channel separates the inliers (the positive control) and learns
nothing over uniform sets on the castle fold's real pairs. Each rung changes one thing on the way from one to the
other; every rung trains the fold recipe (folds.train.rlsac-scale's sizes: 16 episodes per step, batch 32, the first
update after 300 transitions, onednn kernels) for ``steps`` steps with each seed of ``seeds``:

  control-<r>  separable SNN, every pair at inlier ratio r (the positive control run to convergence);
  rung0        separable SNN, each pair's inlier ratio drawn from the real training pairs' (the fitted statistics);
  rung1        rung0 with the real pairs' overlap of inlier and outlier SNN ratios (the fitted SNN quantiles);
  rung2        rung1 with the real outliers' image positions (the fitted generator as it stands);
  rung3a       the fold's real pairs (coordinates, geometry, labels), the SNN channel redrawn per label as in rung2;
  rung3        the fold's real pairs as they are (the scale study's redraw arm: its 3000-step actors, not re-run);
  supervised   rung3's inputs, the actor trained on ground-truth labels instead (per-point cross-entropy toward the
               uniform distribution over the true inliers, one update per step as SAC's): the ceiling of this policy;
  reward       rung3 with the reward's inlier threshold at the evaluation's (the uniform control's tuned threshold);
  improvement  rung3 with the improvement reward (the gain over the episode's best inlier ratio so far).

Every sampler of a rung runs in the same environment (rlsac.rl.rollout.rlsac_estimate: episodes, de-duplication,
scoring, refinement, budget): uniform sets, guided sets (SNN softmax at T = 0.1), the oracle (sets drawn from the
ground-truth inliers only: the ceiling of sampling) and RLSAC's policy. Beside mAA each has pi(inliers), its
probability mass on the ground-truth inliers (the policy's at its first step): how much the rung's inputs tell.

Ground truth: synthetic pairs carry their generated inliers; real pairs are labelled by the ground-truth F at the
training reward's threshold (FundamentalTask.true_inliers, 2 px). Settings: synthetic rungs are measured at the task's
threshold (2 px) with no pre-filter (the control's); real rungs at the uniform control's threshold tuned on the fold's
validation pairs, pre-filter off for every sampler (rung 3a's redrawn SNN would make a pre-filter mean another thing).
The curve is measured on held-out pairs every ``every`` steps at ``curve_iterations``: synthetic rungs on their test
pairs (nothing is chosen on them), real rungs on the fold's validation pairs; the fold's test pairs are read once, by
the final measurement of each run.

Files: experiments/ladder/<rung>/s<seed>.json (a run: curve and per-pair test errors), .../controls.json (the rung's
uniform, guided and oracle samplers), checkpoints/ladder/<rung>/s<seed>.pt (the final actor). The report:
rlsac.reports.ladder (reports/learner.md).
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlsac.errors import RlsacError
from rlsac.layout.ladder_layout import (
    Rung,
    actor_file,
    conf,
    controls_file,
    run_file,
    rungs,
)

GUIDED_T = 0.1  # the guided control's temperature (rlsac.experiments.positive_control's)
MEASURE_SEED = 7  # every sampler's draws at measurement (the positive control's)
SNN_SEED = 13  # rung 3a's redrawn SNN channel
# the oracle's logit of an outlier: drawn only where a pair has fewer inliers than a set
ORACLE_OUTLIER_LOGIT = -1e4

# ------------------------------------------------------------------------------------------------ the rung's pairs

def _statistics() -> dict[str, Any]:
    """The fold's fitted match statistics (stage synthetic_fit, reports/synthetic_fit.json: its training pairs')."""
    path = Path("reports/synthetic_fit.json")
    if not path.is_file():
        raise RlsacError(f"{path}: no fitted statistics (run `rlsac scale --stage fit` first)")
    return json.loads(path.read_text())["real"]

def synthetic_pairs(rung: Rung, n_pairs: int, seed: int) -> dict[str, Any]:
    """A synthetic rung's pairs (seed 11: training, 12: test, as the positive control) as a labelled batch."""
    from rlsac.data import fundamental as fdata
    from rlsac.data.synthetic_pairs import SyntheticPairsConf, generate

    stats = _statistics() if "fitted" in (rung.snn, rung.ratios, rung.positions) else {}
    arrays = generate(SyntheticPairsConf(n_pairs=n_pairs, inlier_ratio=rung.inlier_ratio, snn=rung.snn, seed=seed,
                                         statistics=stats, ratios=rung.ratios, positions=rung.positions))
    batch = fdata.to_batch(arrays)
    batch["inliers"] = torch.from_numpy(arrays["inliers"]) & batch["mask"]
    return batch

def redraw_snn(batch: dict, inliers: torch.Tensor, stats: dict, seed: int) -> dict:
    """``batch`` with its SNN channel (features[..., 4]) drawn per ground-truth label from the fitted quantiles:
    rung 3a's inputs (real geometry, the synthetic rungs' information in the SNN channel)."""
    from rlsac.data import match_statistics as ms

    rng = np.random.default_rng(seed)
    shape = tuple(inliers.shape)
    drawn = np.where(inliers.numpy(), ms.sample_snn(rng, stats["snn_inliers"], int(np.prod(shape))).reshape(shape),
                     ms.sample_snn(rng, stats["snn_outliers"], int(np.prod(shape))).reshape(shape))
    out = dict(batch)
    out["features"] = batch["features"].clone()
    out["features"][..., 4] = torch.as_tensor(drawn, dtype=batch["features"].dtype)
    return out

def real_pairs(rung: Rung, c: dict, which: str, task, prefilter: float | None = None) -> dict:
    """The fold's pairs of ``which`` (train: the pool the redraw arm draws episodes from; val; test) with their
    ground-truth labels (``inliers``: at the training reward's threshold), SNN redrawn for rung 3a."""
    from rlsac.experiments.folds import data_dir
    from rlsac.layout import scale_layout as lay
    from rlsac.tasks import read_batch

    path = lay.pool_file(c["fold"]) if which == "train" else data_dir(c["regime"], c["fold"]) / f"{which}.h5"
    if not Path(path).is_file():
        raise RlsacError(f"{path}: missing (run `dvc repro {'scale_pool' if which == 'train' else 'fold_data'}`)")
    batch, _ = read_batch("fundamental", str(path), "cpu")
    d = dict(batch)
    d["coords"] = batch["coords"].double()  # the ground-truth test in float64, as the fitted statistics
    batch["inliers"] = task.true_inliers(d)
    if rung.snn == "redrawn":
        batch = redraw_snn(batch, batch["inliers"], _statistics(), SNN_SEED + ("train", "val", "test").index(which))
    if prefilter is not None:  # the evaluation's pre-filter: what no sampler sees (rlsac.tasks.prefiltered)
        from rlsac.tasks.registry import prefiltered

        batch = prefiltered(task, batch, prefilter)
        batch["inliers"] = batch["inliers"] & batch["mask"]
    return batch

def eval_settings(c: dict, params: dict) -> tuple[float, float]:
    """The settings a real rung is measured at: the settings_from row's threshold (in the task's unit) and SNN
    pre-filter, tuned on the fold's validation pairs."""
    from rlsac.config import section
    from rlsac.evaluation.tune import tuned_settings
    from rlsac.experiments.folds import for_task, protocol, scene_list, split_scenes
    from rlsac.tasks.fundamental import FundamentalTask

    p = for_task(protocol(params), params, "fundamental")
    train_scenes, test_scenes = (scene_list(x) for x in split_scenes(p, c["fold"]))
    s = tuned_settings(section(params, "evaluate", "fundamental"), c["regime"], c["fold"], c["settings_from"],
                       train_scenes, test_scenes)
    return FundamentalTask().px_thresholds(float(s["threshold_px"]))[0], float(s.get("prefilter") or 1.0)

# ---------------------------------------------------------------------------------------------------- measurement

def oracle_logits(inliers: torch.Tensor) -> torch.Tensor:
    """Per-point logits that draw minimal sets from the ground-truth inliers only (a pair with fewer inliers than a
    set fills it with outliers)."""
    return torch.where(inliers, 0.0, ORACLE_OUTLIER_LOGIT)

def sampler_mass(name: str, batch: dict, task, agent_actor=None, state_threshold: float | None = None) -> np.ndarray:
    """Per pair, a sampler's probability mass on the ground-truth inliers (the policy's at its first step) -> (B,)."""
    from rlsac.rl.env import EnvConf, SampleConsensusEnv
    from rlsac.rl.sac import masked_policy

    inl, mask = batch["inliers"].float(), batch["mask"]
    if name == "uniform":
        return ((inl * mask).sum(-1) / mask.sum(-1).clamp_min(1)).numpy()
    if name == "oracle":
        return (inl.sum(-1) > 0).float().numpy()
    if name == "guided":
        p = torch.softmax((-task.match_quality(batch) / GUIDED_T).masked_fill(~mask, -float("inf")), -1)
        return (p * inl).sum(-1).numpy()
    env = SampleConsensusEnv(task, EnvConf(), training=False, state_threshold=state_threshold)
    feats = task.features(batch)
    with torch.no_grad():
        state = env.reset(batch, feats, 1, generator=torch.Generator().manual_seed(0))
        p, _ = masked_policy(agent_actor(state, env.mask, agent_actor.graph(feats, batch["mask"])), env.mask)
    return (p * inl).sum(-1).numpy()

def measure(name: str, batch: dict, task, iterations: int, actor=None, state_threshold: float | None = None,
            env_conf=None) -> dict[str, Any]:
    """One sampler on ``batch`` at ``iterations`` hypotheses -> per-pair err_R, err_t (degrees) and pi(inliers)."""
    from rlsac.rl.rollout import rlsac_estimate

    guide = {"guided": lambda: -task.match_quality(batch) / GUIDED_T,
             "oracle": lambda: oracle_logits(batch["inliers"])}.get(name, lambda: None)()
    with torch.no_grad():
        res = rlsac_estimate(task, batch, actor if name == "rlsac" else None, iterations, env_conf=env_conf,
                             generator=torch.Generator().manual_seed(MEASURE_SEED), guide=guide,
                             state_threshold=state_threshold)
    errs = task.errors(res["hyp"].numpy(), res["valid"].numpy(), res["inliers"].numpy(),
                       {k: (v.numpy() if torch.is_tensor(v) else v) for k, v in batch.items()})
    pi = sampler_mass(name, batch, task, actor, state_threshold)
    return {"err_R": np.round(errs["err_R"], 5).tolist(), "err_t": np.round(errs["err_t"], 5).tolist(),
            "pi_inliers": np.round(pi, 5).tolist()}

def summary(m: dict[str, Any]) -> dict[str, float]:
    """Per-pair results -> mAA_R, mAA_t (Table 2's mAA@10 deg) and mean pi(inliers)."""
    from rlsac.maths import metrics

    return {"mAA_R": round(metrics.mAA(np.asarray(m["err_R"]), 10.0), 4),
            "mAA_t": round(metrics.mAA(np.asarray(m["err_t"]), 10.0), 4),
            "pi_inliers": round(float(np.mean(m["pi_inliers"])), 4)}

# ------------------------------------------------------------------------------------------------------ training

def recipe(params: dict, c: dict):
    """The fold recipe's TrainConf (folds.train.rlsac-scale over train.fundamental, total steps = ladder.steps)."""
    from rlsac.config import build, deep_update
    from rlsac.experiments.folds import for_task, protocol
    from rlsac.experiments.folds import train_options as fold_train_options
    from rlsac.learners.harness import TrainConf

    p = for_task(protocol(params), params, "fundamental")
    opts = fold_train_options(p, params, c["regime"], c["fold"], "rlsac-scale", {"device": "cpu", "threads": 1})
    opts = deep_update(opts, {"sac": {"total_steps": int(c["steps"])}})
    return build(TrainConf, opts, "train")

def train_rung(rung: Rung, seed: int, params: dict, c: dict, device: str = "cpu") -> dict[str, Any]:
    """Train one run of a rung (or load the scale study's actor for rung 3) and measure it -> the run record."""
    from dataclasses import asdict, replace

    from rlsac.rl import checkpoint
    from rlsac.rl.episodes import RedrawnPairs, pool_tensors
    from rlsac.rl.rollout import in_channels
    from rlsac.rl.sac import SACAgent, seed_everything, train_loop
    from rlsac.tasks.fundamental import FundamentalTask

    tc = recipe(params, c)
    dev = torch.device(device)
    thr, pf = eval_settings(c, params) if rung.data == "real" else (None, None)
    pf = pf if rung.prefilter else None
    train_task = FundamentalTask(threshold=thr) if rung.reward_threshold == "eval" else FundamentalTask()
    label_task = FundamentalTask()
    eval_task = FundamentalTask(threshold=thr) if thr is not None else FundamentalTask()
    state_threshold = float(train_task.threshold)  # the policy's residual channel keeps its training unit
    env_conf = replace(tc.env, reward=rung.reward)
    if rung.data == "synthetic":
        train, curve = synthetic_pairs(rung, c["train_pairs"], 11), synthetic_pairs(rung, c["test_pairs"], 12)
        test = curve
    else:
        train = real_pairs(rung, c, "train", label_task)
        curve, test = real_pairs(rung, c, "val", label_task, pf), None  # the test pairs: read after training
    rows: list[dict] = []

    def at_step(actor, step: int, updates: int, alpha: float | None = None) -> dict:
        """The curve's point: measured on the CPU (a copy of an actor that trains on another device); ``alpha``,
        SAC's temperature then (what the drift after a peak may follow)."""
        actor.eval()
        on_cpu = actor if dev.type == "cpu" else copy.deepcopy(actor).cpu()
        m = measure("rlsac", curve, eval_task, c["curve_iterations"], on_cpu, state_threshold, env_conf)
        rows.append({"step": step, "updates": updates, **summary(m),
                     **({} if alpha is None else {"alpha": round(alpha, 6)})})
        actor.train()
        return {}

    if rung.learner == "scale":  # the scale study's redraw arm (same recipe, aten kernels): its snapshots
        from rlsac.layout import scale_layout as lay

        actor = None
        for k in sorted(s for s in lay.arm_steps(lay.protocol(params), "redraw") if s <= c["steps"]):
            actor, _ = checkpoint.load_actor(lay.snapshot(c["fold"], "redraw", seed, k))
            at_step(actor, int(k), -1)
        actor.eval()
    else:
        gen = seed_everything(int(seed))
        if dev.type != "cpu":  # a preview on an accelerator (never the record): its own generator and kernels
            gen = torch.Generator(device=dev).manual_seed(int(seed))
            tc = replace(tc, kernels="aten", neighbour_max="eager")
        sac = tc.sac
        if rung.learner == "supervised":  # every update's actor step is the cross-entropy to the labels
            sac = replace(sac, warm_start_updates=int(c["steps"]) * sac.updates_per_step)
        if rung.entropy_target is not None:
            sac = replace(sac, target_entropy_scale=float(rung.entropy_target))
        agent = SACAgent(in_channels(train_task), tc.policy, sac).to(dev).set_kernels(tc.kernels, tc.neighbour_max)
        on_dev = {k: (v.to(dev) if torch.is_tensor(v) else v) for k, v in train.items()}
        if rung.data == "synthetic":
            data = {"coords": on_dev["coords"], "mask": on_dev["mask"], "features": train_task.features(on_dev)}
            if rung.learner == "supervised":
                data["labels"] = on_dev["inliers"]
            episodes = None
        else:
            data = {"mask": on_dev["mask"]}
            labels = on_dev["inliers"] if rung.learner == "supervised" else None
            episodes = RedrawnPairs(train_task, pool_tensors(on_dev, dev), agent.actor, tc.episodes.points,
                                    tc.episodes.swap, labels=labels)
        at_step(agent.actor, 0, 0, float(agent.log_alpha.detach().exp()))
        train_loop(agent, train_task, data, env_conf, 0, gen, log=lambda m, s: None,
                   validate=lambda step: at_step(agent.actor, step, int(agent.n_updates),
                                                 float(agent.log_alpha.detach().exp())), val_every=c["every"],
                   episodes=episodes)
        actor = agent.actor.eval().cpu()
    out = actor_file(rung.name, seed)  # the measured actor (rung 3: the scale study's, copied)
    out.parent.mkdir(parents=True, exist_ok=True)
    checkpoint.write(out, checkpoint.actor_payload(
        actor, {"ladder": rung.name, "policy": asdict(tc.policy), "env": asdict(env_conf)}, in_channels(train_task),
        int(c["steps"]), {}, "last", [], checkpoint.training_scales(train_task)))
    if test is None:
        test = real_pairs(rung, c, "test", label_task, pf)
    final = {str(it): measure("rlsac", test, eval_task, int(it), actor, state_threshold, env_conf)
             for it in c["iterations"]}
    return {"rung": rung.name, "seed": int(seed), "why": rung.why, "steps": int(c["steps"]),
            "curve": rows, "final": final, "pairs": len(final[str(c["iterations"][0])]["err_R"]),
            "threshold": float(eval_task.threshold)}

def rung_controls(rung: Rung, params: dict, c: dict) -> dict[str, Any]:
    """The rung's samplers that learn nothing (uniform, guided, oracle) on its test pairs at every budget."""
    from rlsac.tasks.fundamental import FundamentalTask

    thr, pf = eval_settings(c, params) if rung.data == "real" else (None, None)
    eval_task = FundamentalTask(threshold=thr) if thr is not None else FundamentalTask()
    test = synthetic_pairs(rung, c["test_pairs"], 12) if rung.data == "synthetic" else \
        real_pairs(rung, c, "test", FundamentalTask(), pf if rung.prefilter else None)
    return {"rung": rung.name, "threshold": float(eval_task.threshold),
            "samplers": {name: {str(it): measure(name, test, eval_task, int(it)) for it in c["iterations"]}
                         for name in ("uniform", "guided", "oracle")}}

def write_json(path: Path, obj: dict) -> None:
    from rlsac.io import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1) + "\n")

def check_inputs(rung: Rung, c: dict, params: dict, seed: int | None) -> None:
    """Every file the rung reads, there (and its tuned settings readable) -> None; RlsacError naming the first
    missing."""
    from rlsac.experiments.folds import data_dir
    from rlsac.layout import scale_layout as lay

    if rung.data == "synthetic" and "fitted" in (rung.snn, rung.ratios, rung.positions):
        _statistics()
    if rung.data == "real":
        if rung.snn == "redrawn":
            _statistics()
        need = [lay.pool_file(c["fold"]), *(data_dir(c["regime"], c["fold"]) / f"{w}.h5" for w in ("val", "test"))]
        if rung.learner == "scale" and seed is not None:
            need += [lay.snapshot(c["fold"], "redraw", seed, k) for k in lay.arm_steps(lay.protocol(params), "redraw")
                     if k <= c["steps"]]
        for path in need:
            if not Path(path).is_file():
                raise RlsacError(f"{path}: missing (the ladder's rung {rung.name} reads it; `dvc repro` its stage)")
        eval_settings(c, params)


def run(params: dict, rung_name: str, seed: int | None, threads: int = 1, device: str = "cpu",
        track: bool = False) -> dict[str, Any]:
    """``rlsac scale --stage ladder --arm <rung> --seed <s>`` (one run) or without a seed (the rung's controls);
    an MLflow run in experiment ``scale`` with ``track``."""
    from rlsac.tracking import check_store, start_run

    c = conf(params)
    all_rungs = rungs(c)
    if rung_name not in all_rungs:
        raise RlsacError(f"ladder rung must be one of {', '.join(all_rungs)}, got {rung_name!r}")
    if seed is not None and int(seed) not in c["seeds"]:
        raise RlsacError(f"ladder --seed must be one of {c['seeds']}, got {seed}")
    if threads > 0:
        torch.set_num_threads(threads)
    rung = all_rungs[rung_name]
    if seed is None and rung.controls_from:
        raise RlsacError(f"ladder rung {rung_name} is measured against rung {rung.controls_from}'s controls (the same "
                         f"pairs and settings): run `--arm {rung.controls_from}` without --seed")
    from rlsac.devices import resolve_device

    device = str(resolve_device(device))  # "auto": the accelerator where there is one (a preview, not the record)
    check_inputs(rung, c, params, seed)  # before the MLflow run: a missing input leaves no FAILED run behind
    check_store(track, "scale")
    t0 = time.time()
    name = f"ladder {c['fold']} {c['regime']} {rung_name} " + ("controls" if seed is None else f"s{seed}")
    with start_run("scale", name, params={"rung": rung_name, "seed": "controls" if seed is None else int(seed),
                                          "why": rung.why, **{k: str(v) for k, v in c.items()}},
                   tags={"command": "scale", "benchmark": "ladder", "fold": c["fold"], "regime": c["regime"]},
                   enabled=track) as mlrun:
        if seed is None:
            out, rec = controls_file(rung_name), rung_controls(rung, params, c)
            got = {f"{s}/{k}_i{it}": v for s, per in rec["samplers"].items() for it, m in per.items()
                   for k, v in summary(m).items()}
        else:
            out, rec = run_file(rung_name, int(seed)), train_rung(rung, int(seed), params, c, device)
            got = {f"rlsac/{k}_i{it}": v for it, m in rec["final"].items() for k, v in summary(m).items()}
        write_json(out, rec)
        mlrun.metrics(got)
        mlrun.artifact(out, "ladder")
    return {"stage": "ladder", "file": str(out), "seconds": round(time.time() - t0, 1),
            "summary": {k: v for k, v in got.items() if k.endswith(f"_i{c['curve_iterations']}")}}
