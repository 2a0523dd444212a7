"""Checkpoint selection measured (issue #27, item 3): which validated actor a fold model's training keeps, and what
the choice is worth on the fold's test pairs.

A fold model's checkpoint holds one actor: the validated one with the best score of its selection rule (the paper's
unsupervised validation inlier ratio). The others are gone, so ``select_fold`` replays the training with the same
options and seed (rlsac.evaluation.train is deterministic on the CPU; the replay must give the kept actor bit for bit,
or the stage fails) and keeps every validated actor. Each is evaluated on the fold's test pairs at
``folds.select_iterations`` with the settings tuned for the kept actor (its tuning record: chosen on validation pairs
only); the kept actor's errors are read from its own evaluation (fold_eval*), which the replay just showed is the same
actor's.

Outputs, per (regime, fold, model) under reports/selection/: ``<model>.csv`` (step, iterations, pair, err_R, err_t of
every validated actor) and ``<model>.json`` (the validation history, the kept and the last step, each step's test
mAA). ``candidates`` names the steps validation cannot tell from the kept one; rlsac.reports.folds turns the files into
the report's section (kept vs last, and the test spread between the candidates).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import pandas as pd

from rlsac.errors import RlsacError
from rlsac.io import atomic_path, check_writable, write_json

ROOT = Path("reports") / "selection"


def paths(regime: str, fold: str, model: str, root: str | Path = ROOT) -> tuple[Path, Path]:
    """-> (<root>/<regime>/<fold>/<model>.csv, .json)."""
    d = Path(root) / regime / fold
    return d / f"{model}.csv", d / f"{model}.json"


def candidates(history: list[dict[str, Any]], kept_step: int, tie: float, key: str = "charts/val_inlier_ratio"
               ) -> list[int]:
    """Steps of ``history`` whose validation score ``key`` (the selection rule's, rlsac.learners.harness's
    selection_score) lies within ``tie`` of the kept step's (the kept one included): the actors the selection signal
    cannot tell apart."""
    score = {int(h["step"]): float(h[key]) for h in history}
    if kept_step not in score:
        raise RlsacError(f"kept step {kept_step} is not a validated step {sorted(score)}")
    return [s for s in sorted(score) if abs(score[s] - score[kept_step]) <= tie]


def replay(train_opts: dict[str, Any], kept: dict[str, Any], where: Path, name: str | None = None
           ) -> list[dict[str, Any]]:
    """Train again with ``train_opts`` (output under ``where``, untracked) -> the payload of every validated actor;
    RlsacError unless the actor of ``kept``'s step is ``kept``'s actor, tensor for tensor. ``name``: the checkpoint
    as the user gave it, for the message (its stored ``out`` may be another machine's path)."""
    import torch

    from rlsac.evaluation.train import train

    snaps: list[dict[str, Any]] = []
    train({**train_opts, "out": str(where / "replay.pt")}, track=False, snapshots=snaps)
    same = [s for s in snaps if s["step"] == kept.get("step")]
    if not same or set(same[0]["actor"]) != set(kept["actor"]) or not all(
            torch.equal(same[0]["actor"][k].cpu(), kept["actor"][k].cpu()) for k in kept["actor"]):
        raise RlsacError(f"{name or train_opts['out']}: the replayed training does not give the kept actor of step "
                         f"{kept.get('step')} (a checkpoint from other options, code or hardware)")
    if "state_scales" not in kept:  # a checkpoint from before the key: its snapshots are evaluated as it was
        for s in snaps:
            s.pop("state_scales", None)
    return snaps


def select_fold(p: dict, params: dict, regime: str, fold: str, model: str, o: dict, track: bool = True
                ) -> dict[str, Any]:
    """Replay ``model``'s training on (regime, fold), evaluate every validated actor on the test pairs; write the
    two files and log an MLflow run (each step's test mAA, the seconds) -> a summary."""
    import time

    from rlsac.config import section
    from rlsac.evaluation.evaluate import check_options, resolve_device, score
    from rlsac.evaluation.results import read_errors, read_summary
    from rlsac.evaluation.tune import tuned_settings
    from rlsac.layout.protocol import data_dir, eval_dir, row_options, rows, scene_list, split_scenes, train_options
    from rlsac.learners.harness import selection_score
    from rlsac.rl import checkpoint
    from rlsac.tasks import task_class
    from rlsac.tracking import check_store, start_run

    row = rows(p, fold, regime)[model]
    iterations = list(p["select_iterations"])
    task = p["task"]
    ev = section(params, "evaluate", task)
    train_scenes, test_scenes = (scene_list(s) for s in split_scenes(p, fold))
    settings = tuned_settings(ev, regime, fold, model, train_scenes, test_scenes, task)
    kept = checkpoint.read(row["checkpoint"])
    test = data_dir(regime, fold) / "test.h5"
    data, _ = task_class(task).read(test)
    pairs = [f"{a}/{b}" for a, b in zip(data["scene"], data["pair"], strict=True)]
    kept_eval = {}
    for it in iterations:  # the kept actor's own evaluation, read and matched to the test pairs before the replay
        d = eval_dir(regime, fold, model, it, task)
        if not (d / "errors.csv").is_file() or not (d / "summary.json").is_file():
            raise RlsacError(f"{d}: no evaluation of the kept actor at {it} iterations (run its fold_eval stage)")
        err = read_errors(d / "errors.csv", ("err_R", "err_t"))
        if [f"{a}/{b}" for a, b in zip(err["scene"], err["pair"], strict=True)] != pairs:
            raise RlsacError(f"{d}: its pairs are not those of {test}")
        kept_eval[it] = (err, read_summary(d / "summary.json"))
    csv_path, json_path = paths(regime, fold, model)
    for path in (csv_path, json_path):
        check_writable(path)
    train_opts = train_options(p, params, regime, fold, model, o)
    for key in ("data", "val_data"):  # before the run, not inside it
        if train_opts.get(key) and not Path(str(train_opts[key])).is_file():
            raise RlsacError(f"{train_opts[key]}: no such file (the {key} {model} was trained on; run the fold's "
                             "data stage)")
    experiment = task_class(task).experiment
    check_store(track, experiment)
    device = resolve_device(o["device"])
    frames, test_maa = [], {}
    tags = {"command": "folds", "benchmark": "folds", "regime": regime, "fold": fold, "model": model}
    with tempfile.TemporaryDirectory(prefix="rlsac-select-") as tmp, start_run(
            experiment, f"select folds {regime} {fold} {model}", params={"iterations": iterations,
                                                                        "tie": p["select_tie"], **settings},
            tags=tags, enabled=track) as mlrun:
        t0 = time.perf_counter()
        snaps = replay(train_opts, kept, Path(tmp), str(row["checkpoint"]))
        mlrun.metrics({"time/replay_seconds": time.perf_counter() - t0})
        for snap in snaps:
            step = int(snap["step"])
            for it in iterations:
                if step == kept["step"]:
                    err, summ = kept_eval[it]
                    got = {"err_R": err["err_R"].to_numpy(), "err_t": err["err_t"].to_numpy()}
                else:
                    path = Path(tmp) / f"step{step}.pt"
                    checkpoint.write(path, snap)
                    opts = {**row_options(row, p, ev, o), **settings, "checkpoint": str(path), "data": str(test),
                            "iterations": int(it)}
                    summ, got = score(check_options(opts), data, device)
                frames.append(pd.DataFrame({"step": step, "iterations": int(it), "scene": data["scene"],
                                            "pair": data["pair"], "err_R": got["err_R"], "err_t": got["err_t"]}))
                test_maa.setdefault(str(step), {})[str(it)] = {k: float(summ[k]) for k in ("mAA", "mAA_R", "mAA_t")}
                mlrun.metrics({f"test_{k}/step{step}/i{it}": v for k, v in test_maa[str(step)][str(it)].items()})
        mlrun.metrics({"time/seconds": time.perf_counter() - t0})
    history = [dict(h) for h in kept.get("history", [])]
    score = selection_score(str(kept.get("selection")))
    record = {"regime": regime, "fold": fold, "model": model, "checkpoint": str(row["checkpoint"]),
              "selection": kept.get("selection"), "score": score, "kept_step": int(kept["step"]),
              "last_step": int(max(int(s["step"]) for s in snaps)), "steps": sorted(int(s["step"]) for s in snaps),
              "reproduced": True, "tie": float(p["select_tie"]),
              "candidates": candidates(history, int(kept["step"]), float(p["select_tie"]), score),
              "iterations": iterations,
              "settings": settings, "history": history, "test": test_maa}
    with atomic_path(csv_path) as t:
        pd.concat(frames, ignore_index=True).to_csv(t, index=False, float_format="%.6g")
    write_json(json_path, record)
    return {"model": model, "kept_step": record["kept_step"], "last_step": record["last_step"],
            "steps": record["steps"], "test": test_maa, "files": [str(csv_path), str(json_path)]}


# ----------------------------------------------------------------------------------- a model of one data file (lines)


def first_best(history: list[dict[str, Any]], key: str) -> int:
    """The step a training keeping ``key``'s best would keep: the first maximum (a later actor is kept only when it
    is strictly better, rlsac.evaluation.train)."""
    best = max(float(h[key]) for h in history)
    return next(int(h["step"]) for h in history if float(h[key]) == best)


def out_files(stem: str | Path) -> tuple[Path, Path]:
    """``<stem>.csv`` and ``<stem>.json`` (appended: a stem such as o0.7-s1 has a dot that is not a suffix)."""
    return Path(f"{stem}.csv"), Path(f"{stem}.json")


def check_select_options(o: dict[str, Any], params: dict) -> dict[str, Any]:
    """``rlsac select``'s options with their defaults and checks, before any work -> complete options."""
    from rlsac.config import check_value, section
    from rlsac.io import check_writable

    for key in ("checkpoint", "data", "kept_eval", "out"):
        if not o.get(key):
            raise RlsacError(f"select needs --{key.replace('_', '-')}")
    for key in ("checkpoint", "data"):
        if not Path(o[key]).is_file():
            raise RlsacError(f"{o[key]}: no such file")
    for name in ("errors.csv", "summary.json"):
        if not (Path(o["kept_eval"]) / name).is_file():
            raise RlsacError(f"{o['kept_eval']}: no {name} (the kept checkpoint's own evaluation, rlsac evaluate)")
    o = dict(o)
    o["tie"] = check_value("tie", 0.005 if o.get("tie") is None else o["tie"], float, "[0, inf)")
    if o.get("iterations") is not None:
        o["iterations"] = check_value("iterations", o["iterations"], int, "[1, inf)")
    for path in out_files(o["out"]):
        check_writable(path)
    section(params, "evaluate")  # a params file without the section fails here, not after the replay
    return o


def select_checkpoint(o: dict[str, Any], params: dict, track: bool = True) -> dict[str, Any]:
    """Checkpoint selection measured for a model trained on one data file (the line models of Table 1): replay the
    training of ``o['checkpoint']`` from its own options (its ``conf``: the same data, options and seed), test every
    validated actor on ``o['data']`` with evaluate.<task>'s settings at ``o['iterations']``, and write
    ``<out>.csv`` (step, instance, the task's errors) and ``<out>.json`` (the validation history; the kept, the last
    and the inlier-ratio-best step; the candidates within ``tie`` of the kept one's validation score; each step's
    test summary). The kept actor must come back tensor for tensor and give the test mAA of its committed evaluation
    ``o['kept_eval']``, or nothing is written (RlsacError). -> a summary."""
    import time

    from rlsac.config import section
    from rlsac.evaluation.evaluate import check_options, resolve_device, score
    from rlsac.evaluation.results import read_errors, read_summary
    from rlsac.learners.harness import SELECTION_KEY, selection_score
    from rlsac.rl import checkpoint
    from rlsac.tasks import task_class
    from rlsac.tracking import check_store, start_run

    o = check_select_options(o, params)
    kept = checkpoint.read(o["checkpoint"])
    if checkpoint.kind_of(kept) != "rlsac" or not isinstance(kept.get("conf"), dict) or "actor" not in kept:
        raise RlsacError(f"{o['checkpoint']}: not an RLSAC checkpoint (select replays RLSAC's training)")
    conf = dict(kept["conf"])
    task = str(conf.get("task"))
    task_cls = task_class(task)
    # the kept evaluation and the training files, all checked before the run (issue #49: a corrupt or list
    # summary was a traceback, a missing training file failed inside the run)
    kept_summary = read_summary(Path(o["kept_eval"]) / "summary.json")
    read_errors(Path(o["kept_eval"]) / "errors.csv")
    for key in ("data", "val_data"):
        if conf.get(key) and not Path(str(conf[key])).is_file():
            raise RlsacError(f"{o['checkpoint']}: trained on {key} {conf[key]}, which is absent here (select "
                             "replays the training on it)")
    if Path(str(kept_summary.get("checkpoint", ""))).resolve() != Path(o["checkpoint"]).resolve() or Path(
            str(kept_summary.get("data", ""))).resolve() != Path(o["data"]).resolve():
        raise RlsacError(f"{o['kept_eval']}: an evaluation of {kept_summary.get('checkpoint')} on "
                         f"{kept_summary.get('data')}, not of {o['checkpoint']} on {o['data']}")
    ev = section(params, "evaluate", task)
    iterations = int(o["iterations"] or ev.get("iterations") or task_cls.default_iterations)
    if int(kept_summary.get("iterations", -1)) != iterations:
        raise RlsacError(f"{o['kept_eval']}: evaluated at {kept_summary.get('iterations')} iterations, not "
                         f"{iterations}")
    data, _ = task_cls.read(o["data"])
    device = resolve_device(o.get("device"))
    check_store(track, task_cls.experiment)
    out = Path(o["out"])
    frames, test = [], {}
    with tempfile.TemporaryDirectory(prefix="rlsac-select-") as tmp, start_run(
            task_cls.experiment, f"select {out.name}", params={"checkpoint": o["checkpoint"], "data": o["data"],
                                                               "iterations": iterations, "tie": o["tie"]},
            tags={"command": "select"}, enabled=track) as mlrun:
        t0 = time.perf_counter()
        snaps = replay({**conf, "resume": False, "device": o.get("device") or "cpu"}, kept, Path(tmp),
                       o["checkpoint"])
        mlrun.metrics({"time/replay_seconds": time.perf_counter() - t0})
        for snap in snaps:
            step = int(snap["step"])
            path = Path(tmp) / f"step{step}.pt"
            checkpoint.write(path, snap)
            opts = {**ev, "task": task, "method": "rlsac", "checkpoint": str(path), "data": o["data"],
                    "iterations": iterations}
            summ, got = score(check_options(opts), data, device)
            if step == int(kept["step"]) and float(summ["mAA"]) != float(kept_summary.get("mAA", float("nan"))):
                raise RlsacError(f"{o['kept_eval']}: the replayed kept actor's test mAA {summ['mAA']} is not the "
                                 f"committed evaluation's {kept_summary.get('mAA')}")
            errs = {k: v for k, v in got.items() if k.startswith("err")}
            frames.append(pd.DataFrame({"step": step, "instance": range(len(next(iter(errs.values())))), **errs}))
            test[str(step)] = {k: float(v) for k, v in summ.items() if isinstance(v, (int, float)) and k in (
                "mAA", "median_deg", "mAA_R", "mAA_t")}
            mlrun.metrics({f"test_{k}/step{step}": v for k, v in test[str(step)].items()})
        mlrun.metrics({"time/seconds": time.perf_counter() - t0})
    history = [{"step": int(s["step"]), **{k: float(v) for k, v in (s.get("val") or {}).items()}} for s in snaps]
    selection = str(kept.get("selection") or conf.get("selection") or "val_mAA")
    key = selection_score(selection)
    record = {"checkpoint": str(o["checkpoint"]), "data": str(o["data"]), "task": task, "seed": int(conf["seed"]),
              "selection": selection, "score": key, "kept_step": int(kept["step"]),
              "last_step": max(int(s["step"]) for s in snaps), "steps": [int(s["step"]) for s in snaps],
              "inlier_ratio_step": first_best(history, SELECTION_KEY["inlier_ratio"]),
              "val_mAA_step": first_best(history, SELECTION_KEY["val_mAA"]), "reproduced": True,
              "tie": float(o["tie"]), "candidates": candidates(history, int(kept["step"]), float(o["tie"]), key),
              "iterations": iterations, "history": history, "test": test}
    csv_path, json_path = out_files(out)
    with atomic_path(csv_path) as t:
        pd.concat(frames, ignore_index=True).to_csv(t, index=False, float_format="%.6g")
    write_json(json_path, record)
    return {"kept_step": record["kept_step"], "last_step": record["last_step"], "steps": record["steps"],
            "test": test, "files": [str(csv_path), str(json_path)]}
