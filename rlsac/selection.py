"""Checkpoint selection measured (issue #27, item 3): which validated actor a fold model's training keeps, and what
the choice is worth on the fold's test pairs.

A fold model's checkpoint holds one actor: the validated one with the best score of its selection rule (the paper's
unsupervised validation inlier ratio). The others are gone, so ``select_fold`` replays the training with the same
options and seed (rlsac.train is deterministic on the CPU; the replay must give the kept actor bit for bit, or the
stage fails) and keeps every validated actor. Each is evaluated on the fold's test pairs at ``folds.select_iterations``
with the settings tuned for the kept actor (its tuning record: chosen on validation pairs only); the kept actor's
errors are read from its own evaluation (fold_eval*), which the replay just showed is the same actor's.

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
    """Steps of ``history`` whose validation score ``key`` (the selection rule's, rlsac.train.selection_score) lies
    within ``tie`` of the kept step's (the kept one included): the actors the selection signal cannot tell apart."""
    score = {int(h["step"]): float(h[key]) for h in history}
    if kept_step not in score:
        raise RlsacError(f"kept step {kept_step} is not a validated step {sorted(score)}")
    return [s for s in sorted(score) if abs(score[s] - score[kept_step]) <= tie]


def replay(train_opts: dict[str, Any], kept: dict[str, Any], where: Path) -> list[dict[str, Any]]:
    """Train again with ``train_opts`` (output under ``where``, untracked) -> the payload of every validated actor;
    RlsacError unless the actor of ``kept``'s step is ``kept``'s actor, tensor for tensor."""
    import torch

    from rlsac.train import train

    snaps: list[dict[str, Any]] = []
    train({**train_opts, "out": str(where / "replay.pt")}, track=False, snapshots=snaps)
    same = [s for s in snaps if s["step"] == kept.get("step")]
    if not same or set(same[0]["actor"]) != set(kept["actor"]) or not all(
            torch.equal(same[0]["actor"][k].cpu(), kept["actor"][k].cpu()) for k in kept["actor"]):
        raise RlsacError(f"{train_opts['out']}: the replayed training does not give the kept actor of step "
                         f"{kept.get('step')} (a checkpoint from other options, code or hardware)")
    return snaps


def select_fold(p: dict, params: dict, regime: str, fold: str, model: str, o: dict, track: bool = True
                ) -> dict[str, Any]:
    """Replay ``model``'s training on (regime, fold), evaluate every validated actor on the test pairs; write the
    two files and log an MLflow run (each step's test mAA, the seconds) -> a summary."""
    import time

    from rlsac import checkpoint
    from rlsac.config import section
    from rlsac.evaluate import check_options, resolve_device, score
    from rlsac.folds import (
        data_dir,
        eval_dir,
        row_options,
        rows,
        scene_list,
        split_scenes,
        train_options,
        tuned_settings,
    )
    from rlsac.reports.tables import read_summary
    from rlsac.tasks import task_class
    from rlsac.tracking import check_store, start_run
    from rlsac.train import selection_score

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
        err = pd.read_csv(d / "errors.csv", dtype={"scene": str, "pair": str})
        if [f"{a}/{b}" for a, b in zip(err["scene"], err["pair"], strict=True)] != pairs:
            raise RlsacError(f"{d}: its pairs are not those of {test}")
        kept_eval[it] = (err, read_summary(d / "summary.json"))
    csv_path, json_path = paths(regime, fold, model)
    for path in (csv_path, json_path):
        check_writable(path)
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
        snaps = replay(train_options(p, params, regime, fold, model, o), kept, Path(tmp))
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
