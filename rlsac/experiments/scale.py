"""``rlsac scale``: is RLSAC starved? One fold of the benchmark trained at growing scale (issue #46).

Stages (params.yaml ``scale``, rlsac.layout.scale_layout):
  pool      the fold's training pairs prepared again with the pool's size (the hard regime's 1000 lowest-SNN
            matches per pair, descriptors included): what the redraw arm draws its episodes from;
  train     one run per (arm, seed): the fold recipe (train.fundamental <- folds.train.rlsac) run for the largest of
            ``steps``, its actor kept at every step of ``steps`` (the curve's points) and by the recipe's selection;
            arm ``fixed`` sees the training file's 150 points of a pair in every episode (the record), arm ``redraw``
            a fresh 150 of the pair's pool per episode with the images swapped at random (rlsac.rl.episodes); arm
            ``pretrain`` first ``pretrain.steps`` steps on the synthetic pairs, then redraw's from those networks;
  fit       the synthetic generator's statistics fitted to the fold's training pairs, beside its own pairs';
  synthetic the pretrain arm's synthetic pairs (``pretrain.pairs``, drawn with those statistics);
  control   the learner's positive control on synthetic pairs (rlsac.experiments.positive_control,
            params positive_control);
  validate  every kept actor on the fold's validation pairs at ``iterations``, with the settings below: what
            chooses the recipe to carry forward (the pre-filter arm sees the pre-filter it would be tested with);
  evaluate  every kept actor on the fold's test pairs at ``iterations`` (``evaluate-final``: the actors of
            ``final_steps`` at ``final_iterations``), with the inlier threshold and pre-filter tuned on the fold's
            validation pairs for ``settings_from`` (the uniform control): the policy's state no longer depends on
            the threshold (checkpoint state_scales), so the sampler-free control's setting scores both alike, and
            RLSAC - uniform is the sampler alone.
The test pairs are read once per actor, after training; nothing here chooses anything on them.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError
from rlsac.layout import scale_layout as lay

STAGES = ("pool", "train", "evaluate", "evaluate-final", "validate", "control", "fit", "synthetic", "ladder")


def scale(options: dict[str, Any], track: bool = True) -> dict[str, Any]:
    """Run one stage (``options``: stage, arm, seed, params, device, threads) -> a summary."""
    from rlsac.config import check_value, read_params
    from rlsac.experiments.folds import for_task, protocol

    stage = options.get("stage")
    if stage not in STAGES:
        raise RlsacError(f"scale --stage must be one of {', '.join(STAGES)}, got {stage!r}")
    threads = check_value("--threads", options.get("threads") or 0, int, "[0, inf)")  # as `rlsac evaluate`'s
    params = read_params(options.get("params") or "params.yaml")
    if threads > 0:
        import torch

        torch.set_num_threads(threads)
    if stage == "ladder":  # issue #61: where the learner stops (rlsac.experiments.ladder); --arm names the rung
        from rlsac.experiments.ladder import run as ladder

        seed = options.get("seed")
        return ladder(params, options.get("arm") or "", None if seed is None else int(seed), threads or 1,
                      options.get("device") or "cpu", track)
    if stage == "control":
        from rlsac.experiments.positive_control import run as control

        t0 = time.time()
        return {"stage": stage, **control(params, track=track), "seconds": round(time.time() - t0, 1)}
    s = lay.protocol(params)
    p = for_task(protocol(params), params, "fundamental")
    if s["fold"] not in p["test"] or s["regime"] not in p["regimes"]:
        raise RlsacError(f"scale.fold {s['fold']!r} / scale.regime {s['regime']!r}: not a fold / regime of params "
                         "folds")
    if stage not in ("pool", "fit", "synthetic"):
        arm, seed = options.get("arm"), options.get("seed")
        if arm not in s["arms"] or seed is None or seed not in s["seeds"]:
            raise RlsacError(f"scale --stage {stage} needs --arm (one of {', '.join(s['arms'])}) and --seed (one of "
                             f"{s['seeds']})")
    t0 = time.time()
    if stage == "pool":
        out = make_pool(p, params, s, track)
    elif stage == "fit":
        out = fit_synthetic(s, track)
    elif stage == "synthetic":
        out = make_synthetic(s, track)
    elif stage == "train":
        out = train_run(p, params, s, options["arm"], int(options["seed"]), options, track)
    else:
        out = evaluate_run(p, params, s, options["arm"], int(options["seed"]), options, track,
                           which={"evaluate": "test", "evaluate-final": "final", "validate": "val"}[stage])
    return {"stage": stage, **out, "seconds": round(time.time() - t0, 1)}


def make_pool(p: dict, params: dict, s: dict, track: bool) -> dict[str, Any]:
    """The fold's training pairs (the train holdout of its training buildings) with the pool's points each
    (rlsac.experiments.folds.prepare_pool, as the fold benchmark's pools)."""
    from rlsac.experiments.folds import prepare_pool

    made = prepare_pool(p, params, s["fold"], int(s["pool"]), lay.pool_file(s["fold"]), track)
    return {"pool": made["out"], "pairs": made["pairs"]}


def fit_synthetic(s: dict, track: bool = True) -> dict[str, Any]:
    """The synthetic generator's statistics fitted to the fold's training pairs (the fixed arm's inputs, inliers by the
    training reward's threshold), then ``synthetic_pairs`` pairs drawn with them and measured the same way: both, and
    the comparison, in reports/synthetic_fit.json (scale.md shows them)."""
    import json

    from rlsac.data import match_statistics as ms
    from rlsac.data.synthetic_pairs import SyntheticPairsConf, generate
    from rlsac.io import atomic_path
    from rlsac.tasks.fundamental import FundamentalTask
    from rlsac.tracking import check_store, start_run

    check_store(track, "scale")
    task = FundamentalTask()
    fitted, n = fitted_statistics(s, task)
    t0 = time.process_time()
    syn = generate(SyntheticPairsConf(n_pairs=int(s["synthetic_pairs"]), n_points=n, snn="fitted", statistics=fitted,
                                      seed=0))
    per_s = int(s["synthetic_pairs"]) / max(time.process_time() - t0, 1e-9)
    tb = task.to_batch(syn)
    tb["coords"] = tb["coords"].double()
    mine = ms.fit(syn, task.true_inliers(tb).numpy())
    out = Path("reports") / "synthetic_fit.json"
    comparison = ms.compare(fitted, mine)
    with start_run("scale", f"synthetic fit {s['fold']}", params={"fold": s["fold"], "regime": s["regime"],
                                                                   "synthetic_pairs": int(s["synthetic_pairs"])},
                   enabled=track) as run:
        with atomic_path(out) as tmp:
            tmp.write_text(json.dumps({"fold": s["fold"], "regime": s["regime"], "real": fitted, "synthetic": mine,
                                       "comparison": comparison}, indent=1) + "\n")
        run.metrics({"pairs_per_cpu_minute": 60 * per_s,
                     **{f"synthetic/{i:02d}": r["synthetic"] for i, r in enumerate(comparison)},
                     **{f"real/{i:02d}": r["real"] for i, r in enumerate(comparison)}})
        run.artifact(out, "synthetic_fit")
    return {"file": str(out), "real_pairs": fitted["pairs"], "synthetic_pairs": mine["pairs"],
            "pairs_per_cpu_minute": round(60 * per_s)}


def fitted_statistics(s: dict, task) -> tuple[dict, int]:
    """The match statistics of the fold's training pairs (inliers by the training reward's threshold) and their points
    per pair."""
    from rlsac.data import match_statistics as ms
    from rlsac.experiments.folds import data_dir
    from rlsac.tasks import as_numpy, read_batch

    path = data_dir(s["regime"], s["fold"]) / "train.h5"
    if not path.is_file():
        raise RlsacError(f"{path}: no training file (run `rlsac folds --stage data` first)")
    real, _ = read_batch("fundamental", str(path), "cpu")
    real["coords"] = real["coords"].double()  # the inlier test in float64, for real and synthetic pairs alike
    fitted = ms.fit({k: as_numpy(v) for k, v in real.items()}, task.true_inliers(real).numpy())
    return fitted, int(real["mask"].shape[1])


def make_synthetic(s: dict, track: bool = True) -> dict[str, Any]:
    """The pretrain arm's ``pretrain.pairs`` synthetic pairs, drawn with the fold's fitted statistics (seed 0), as a
    prepared file: the pretraining's episodes (each pair's points, the images swapped at random)."""
    from rlsac.data.fundamental import KIND
    from rlsac.data.synthetic_pairs import SyntheticPairsConf, generate
    from rlsac.data.tutorial import write
    from rlsac.tasks.fundamental import FundamentalTask
    from rlsac.tracking import check_store, start_run

    check_store(track, "scale")
    fitted, n = fitted_statistics(s, FundamentalTask())
    pairs = int(s["pretrain"]["pairs"])
    syn = generate(SyntheticPairsConf(n_pairs=pairs, n_points=n, snn="fitted", statistics=fitted, seed=0))
    syn.pop("inliers")  # a prepared file holds what real pairs have: no labels
    out = lay.synthetic_file(s["fold"])
    out.parent.mkdir(parents=True, exist_ok=True)
    with start_run("scale", f"synthetic pairs {s['fold']}", params={"fold": s["fold"], "regime": s["regime"],
                                                                    "pairs": pairs, "n_points": n},
                   enabled=track):
        write(out, syn, {"kind": KIND, "n_points": n, "split": "synthetic", "scenes": "synthetic",
                         "source": f"rlsac.data.synthetic_pairs snn=fitted to fold {s['fold']} ({s['regime']})"})
    return {"file": str(out), "pairs": pairs}


def train_options(p: dict, params: dict, s: dict, arm: str, seed: int, o: dict) -> dict[str, Any]:
    """The fold recipe of model rlsac, run to the largest step with its snapshots; the arm's episodes."""
    from rlsac.config import deep_update
    from rlsac.experiments.folds import train_options as fold_train_options

    base = fold_train_options(p, params, s["regime"], s["fold"], "rlsac",
                              {"device": o.get("device") or "cpu", "threads": int(o.get("threads") or 1)})
    steps = lay.arm_steps(s, arm)
    extra: dict[str, Any] = {"seed": int(seed), "out": str(lay.run_dir(s["fold"], arm, seed) / "final.pt"),
                             "sac": {"total_steps": int(steps[-1])}, "snapshot_steps": [int(k) for k in steps],
                             "val_every": int(s["val_every"]), "ckpt_every": int(steps[-1]),
                             "run_name": f"train scale {s['fold']} {lay.run_name(arm, seed)}",
                             "tags": {"command": "scale", "benchmark": "scale", "fold": s["fold"], "arm": arm,
                                      "seed": str(seed)}}
    if arm != "fixed":
        n = int(params.get("fundamental", {}).get("n_points", 150))
        extra["episodes"] = {"pool": str(lay.pool_file(s["fold"])), "points": n, "swap": True}
    if arm == "prefilter":  # the pre-filters the tuning chooses from (params tuning.prefilter), one per episode
        extra["episodes"]["prefilter"] = [float(r) for r in (params.get("tuning") or {}).get("prefilter", [])]
    if arm == "pretrain":  # the real phase starts from the synthetic phase's networks
        extra["init"] = str(lay.pretrained(s["fold"], seed).with_suffix(".state.pt"))
    return deep_update(base, extra)


def pretrain_options(opts: dict, s: dict, seed: int) -> dict[str, Any]:
    """The pretrain arm's synthetic phase: the real phase's recipe on the synthetic pairs (each episode a pair's
    points, the images swapped at random) for ``pretrain.steps`` steps, validated on the fold's validation pairs."""
    from rlsac.config import deep_update

    syn, steps = str(lay.synthetic_file(s["fold"])), int(s["pretrain"]["steps"])
    base = {k: v for k, v in opts.items() if k not in ("init", "snapshot_steps")}
    return deep_update(base, {"data": syn, "out": str(lay.pretrained(s["fold"], seed)), "sac": {"total_steps": steps},
                              "ckpt_every": steps, "episodes": {"pool": syn},
                              "run_name": f"train scale {s['fold']} {lay.run_name('pretrain', seed)} synthetic"})


def train_run(p: dict, params: dict, s: dict, arm: str, seed: int, o: dict, track: bool) -> dict[str, Any]:
    """The run in its legs (scale.legs): a leg a saved state of this run has reached is skipped, the next one
    resumes from that state. Each leg stores the conf it was run with (total_steps = its end, its snapshots), so a
    run re-made from nothing writes the same files as one extended leg by leg across sessions."""
    from rlsac.config import deep_update
    from rlsac.evaluation.train import train
    from rlsac.learners.harness import saved_step

    opts = train_options(p, params, s, arm, seed, o)
    if arm != "fixed" and not lay.pool_file(s["fold"]).is_file():
        raise RlsacError(f"{lay.pool_file(s['fold'])}: no pool file (run `rlsac scale --stage pool` first)")
    if arm == "pretrain" and not lay.synthetic_file(s["fold"]).is_file():
        raise RlsacError(f"{lay.synthetic_file(s['fold'])}: no synthetic pairs (run `rlsac scale --stage synthetic`)")
    if arm == "pretrain":
        pre = pretrain_options(opts, s, seed)
        if saved_step(pre) < pre["sac"]["total_steps"]:  # one leg: a state of this recipe is complete
            train(pre, track=track)
    done, summ = saved_step(opts), None
    for end in lay.arm_legs(s, arm):
        if done >= end:
            continue
        leg = deep_update(opts, {"sac": {"total_steps": int(end)}, "ckpt_every": int(end), "resume": done > 0,
                                 "snapshot_steps": [k for k in opts["snapshot_steps"] if k <= end]})
        summ = train(leg, track=track)
        done = end
    if summ is None:  # every leg was there: what the checkpoint says
        from rlsac.rl import checkpoint

        kept = checkpoint.read(Path(opts["out"]))
        summ = {"checkpoint": opts["out"], "steps": done, "best_step": kept.get("step"), "seconds": 0.0}
    return {"run": lay.run_name(arm, seed), "checkpoint": summ["checkpoint"], "steps": summ["steps"],
            "best_step": summ["best_step"], "train_seconds": summ["seconds"]}


def evaluate_run(p: dict, params: dict, s: dict, arm: str, seed: int, o: dict, track: bool,
                 which: str = "test") -> dict[str, Any]:
    """A run's actors with the control's tuned settings: ``test`` every kept step on the test pairs at
    ``iterations``; ``final`` those of its final steps at ``final_iterations``; ``val`` every kept step on the fold's
    validation pairs at ``iterations`` (what chooses the recipe: the test's settings, the validation pairs)."""
    from rlsac.config import section
    from rlsac.evaluation.evaluate import check_all, evaluate
    from rlsac.experiments.folds import data_dir, scene_list, split_scenes, tuned_settings

    ev = section(params, "evaluate", "fundamental")
    train_scenes, test_scenes = (scene_list(x) for x in split_scenes(p, s["fold"]))
    settings = tuned_settings(ev, s["regime"], s["fold"], s["settings_from"], train_scenes, test_scenes)
    final = which == "final"
    data = data_dir(s["regime"], s["fold"]) / ("val.h5" if which == "val" else "test.h5")
    where = lay.val_dir if which == "val" else lay.eval_dir
    jobs = [{"task": "fundamental", "method": "rlsac", "sampling": "max", "seed": int(p["seed"]),
             "checkpoint": str(lay.snapshot(s["fold"], arm, seed, k)), "device": o.get("device") or "cpu",
             "sets_per_step": 1, "confidence": 0.0, **settings, "data": str(data), "iterations": int(it),
             "out_dir": str(where(s["fold"], it, arm, seed, k)),
             "tags": {"benchmark": "scale", "fold": s["fold"], "arm": arm, "seed": str(seed), "step": str(k),
                      "split": "val" if which == "val" else "test"}}
            for it in ([s["final_iterations"]] if final else [s["iterations"]]) if it > 0
            for k in (lay.arm_final_steps(s, arm) if final else lay.arm_steps(s, arm))]
    check_all(jobs, track)  # every checkpoint and the test file read before the first evaluation writes
    out = []
    for opts in jobs:
        r = evaluate(opts, track=track)
        out.append({"checkpoint": opts["checkpoint"], "iterations": opts["iterations"], "mAA_R": r["mAA_R"],
                    "mAA_t": r["mAA_t"]})
    return {"run": lay.run_name(arm, seed), "evaluations": out}


def format_summary(s: dict[str, Any]) -> str:
    if s["stage"] == "control":
        return (f"positive control ({s['seconds']} s): mean π(inliers) after training "
                + ", ".join(f"{v:.3f} at inlier ratio {k}" for k, v in s["final"].items())
                + f" -> {', '.join(s['files'])}")
    if s["stage"] == "ladder":
        return (f"ladder ({s['seconds']} s): " + ", ".join(f"{k} {v:.3f}" for k, v in s["summary"].items())
                + f" -> {s['file']}")
    if s["stage"] == "pool":
        return f"scale pool ({s['seconds']} s): {s['pairs']} pairs -> {s['pool']}"
    if s["stage"] == "synthetic":
        return f"scale synthetic pairs ({s['seconds']} s): {s['pairs']} pairs -> {s['file']}"
    if s["stage"] == "fit":
        return (f"synthetic fit ({s['seconds']} s): statistics of {s['real_pairs']} training pairs, "
                f"{s['synthetic_pairs']} synthetic pairs drawn with them ({s['pairs_per_cpu_minute']} per CPU minute) "
                f"-> {s['file']}")
    if s["stage"] == "train":
        return (f"scale train {s['run']} ({s['seconds']} s): {s['steps']} steps, kept step {s['best_step']} -> "
                f"{s['checkpoint']} and its step snapshots")
    lines = [f"scale evaluate {s['run']} ({s['seconds']} s):"]
    lines += [f"  {e['checkpoint']} at {e['iterations']}: mAA_R {e['mAA_R']:.3f}, mAA_t {e['mAA_t']:.3f}"
              for e in s["evaluations"]]
    return "\n".join(lines)
