"""``rlsac pipeline``: the DVC pipeline's out-of-date stages as Ray tasks, in dependency order (issue #30).

The plan comes from DVC's stage graph (``Repo.index.graph``) and DVC's rules on dvc.lock with each file hashed once
(rlsac.runners.stage_status: ``Stage.changed`` per stage took minutes), once: a stage runs when it changed or when a
stage it depends on runs; frozen stages and stages without a command never run. Each stage is one Ray task
(``num_cpus=1``; ``num_gpus`` for the stages matching ``gpu_stages`` when ``gpus_per_train`` > 0). With the direct
runner (the default, issue #50) the task runs the stage's own command as DVC would and computes its lock entry with
DVC's code, and this process, the one writer, merges the entries into ``dvc.lock`` by an atomic rename
(rlsac.runners.dvc_stage): no DVC repository lock is held while stages run, and the lock is byte for byte a serial
``dvc repro``'s. With ``runner="dvc"`` the task runs ``dvc --wait-for-lock repro -s <stage>`` (DVC parses and
rewrites the whole lock under its repository lock for each stage). A stage found up to date when its turn comes (its
inputs came back the same) is reported skipped. A failed stage stops its dependents; every other stage still runs;
running the command again resumes (what finished is up to date). A stage whose worker or node died runs again, up to
``retries`` times (it is idempotent: its outputs are removed before its command runs), then counts as failed. On a
cluster (``address``) every stage logs to MLFLOW_TRACKING_URI, which must then be an http(s) server.

Of the stages ready to run, the one with the longest expected path to the end of the plan starts first
(``bottom_levels``; times from earlier runs' ``stage_s`` metrics), and only as many are handed to Ray as the cluster
has room for, so Ray's queue keeps that order. With ``remote`` a stage prefers (softly) the node where its parent with
the largest outputs ran: that node's cache holds them (rlsac.runners.transfer.NodeCache).

A task's process group is watched by a small guard process: if the Ray worker dies (killed, node lost, driver
interrupted), the guard sends the stage SIGTERM (an ``rlsac`` command ends its MLflow run KILLED) and, 10 s later,
SIGKILL, so no orphaned stage keeps writing outputs. Logs: ``logs/pipeline/<stage>.log`` under the repository.

Ray is imported only here, when the command runs (``rlsac --help`` stays fast).
"""

from __future__ import annotations

import contextlib
import os
import time
from typing import Any, Callable

from rlsac.errors import Interrupted, RlsacError

# the parts of the command, one concern each (issue #65)
from rlsac.runners.cluster import _auto_address, _check_address, _check_resources, _check_tracking_server, _start_ray
from rlsac.runners.plan import load_plan
from rlsac.runners.priority import _priorities, stage_metric
from rlsac.runners.recovery import _dvc_root, _note_driver, _restore_interrupted, format_recovery, recover
from rlsac.runners.schedule import schedule
from rlsac.runners.summary import _summary
from rlsac.signals import StopOnSignal

DEFAULTS: dict[str, Any] = {
    "repo": ".",  # the DVC repository (its root)
    "stages": None,  # comma-separated addresses, foreach names or fnmatch patterns; None = every stage
    "workers": None,  # local Ray cluster size; None = os.cpu_count()
    "address": None,  # join this Ray cluster instead of starting one
    "gpus_per_train": 0.0,  # num_gpus of a stage matching gpu_stages
    "gpu_stages": "*train*",  # fnmatch pattern(s), comma-separated, on the stage address
    "dry_run": False,  # print the plan, run nothing
    # direct: the stage's command, its lock entry by the driver (rlsac.runners.dvc_stage); dvc: repro -s
    "runner": "direct",
    "remote": None,  # s3://bucket/prefix or a DVC remote's name: nodes share no disk, files travel by it (transfer)
    "retries": 2,  # runs again of a stage whose worker or node died (not of one whose command failed)
}


RUNNERS = ("direct", "dvc")


def _check_options(o: dict) -> None:
    if o["workers"] is not None and o["workers"] < 1:
        raise RlsacError(f"--workers {o['workers']}: must be at least 1")
    if o["workers"] is not None and o["address"]:
        raise RlsacError("--workers sizes a local Ray cluster; with --address the cluster's own resources count")
    if not 0 <= o["gpus_per_train"] < float("inf"):  # nan and inf pass click's FloatRange
        raise RlsacError(f"--gpus-per-train {o['gpus_per_train']}: must be a finite number >= 0")
    cpus = os.cpu_count() or 1
    if o["workers"] is not None and o["workers"] > cpus:  # ray.init hung on --workers 1000000000
        raise RlsacError(f"--workers {o['workers']}: this machine has {cpus} CPUs (a local Ray cluster has at most "
                         "as many)")
    if o["address"]:
        _check_tracking_server()
    if o["retries"] < 0:
        raise RlsacError(f"--retries {o['retries']}: must be at least 0")
    if o["runner"] not in RUNNERS:
        raise RlsacError(f"--runner {o['runner']}: one of {', '.join(RUNNERS)}")
    if o["address"] == "auto":  # checked too: Ray retried a stale cluster file's dead address for 900 s (issue #64)
        address, found = _auto_address()
        _check_address(address, f"auto (Ray's address {address}, {found})")
    elif o["address"]:
        _check_address(o["address"])
    if o["remote"] is not None:
        from rlsac.runners.transfer import check_url

        check_url(o["remote"])
        if o["runner"] != "direct":  # `dvc repro -s` reads and writes the driver's folder
            raise RlsacError("--remote runs stages with the direct runner only (--runner dvc needs a shared folder)")


def pipeline(options: dict[str, Any], track: bool = True) -> dict:
    """Check the options and the pipeline, then run the out-of-date stages. -> {"root", "results" {address:
    result}, "counts" {status: n}, "n_selected", "wall_s", "workers", "run_id", "dry_run"}."""
    from rlsac.tracking import check_store, start_run

    o = {**DEFAULTS, **{k: v for k, v in options.items() if v is not None}}
    _check_options(o)
    remote = o["remote"] is not None and not o["dry_run"]
    if remote and _dvc_root(o["repo"]) is not None:  # a remote's name or URL before anything is read or written
        from rlsac.runners.transfer import resolve

        resolve(o["remote"], _dvc_root(o["repo"]))
    if not o["dry_run"]:  # a killed driver's set-aside outputs back before the plan reads the tree
        line = format_recovery(recover(o["repo"]))
        if line:
            print(line)
    plan = load_plan(o["repo"], o["stages"], None if o["dry_run"] else o["runner"], remote=remote)
    skipped = [a for a in plan["order"] if a not in plan["todo"]]
    base = {"root": str(plan["root"]), "n_selected": len(plan["order"]), "todo": plan["todo"], "run_id": None}
    if o["dry_run"]:
        return {**base, "dry_run": True, "results": {a: {"stage": a, "status": "skipped"} for a in skipped},
                "counts": {"skipped": len(skipped)}, "wall_s": 0.0, "workers": None, "why": plan["why"],
                "how": plan["how"]}
    if not o["address"] and plan["todo"]:  # a local cluster has this machine's GPUs: known before Ray starts
        import torch

        _check_resources(o, plan, {"GPU": torch.cuda.device_count()})
    if remote and plan["todo"]:  # the bucket answers and holds the code tree before the tracking store, Ray or
        # MLflow is touched: a bad --remote leaves no store file and no run (issue #64)
        from rlsac.runners.transfer import Workspace

        plan["remote"] = Workspace(o["remote"], plan["root"])
    params = {k: o[k] for k in ("stages", "workers", "address", "gpus_per_train", "gpu_stages", "runner", "remote",
                                "retries")}
    params.update(repo=str(plan["root"]), n_todo=len(plan["todo"]))
    t0 = time.time()
    try:
        check_store(track, "pipeline")
        plan["priority"] = _priorities(plan, track)
        # Ray before the MLflow run: a cluster that cannot start or lacks the GPUs asked for fails with no run
        ray, started = _start_ray(o) if plan["todo"] else (None, False)
    except BaseException:
        if plan.get("remote") is not None:
            plan["remote"].close()
        raise
    note = _note_driver(plan["root"], ray) if started and not o["address"] else None
    try:
        resources = ray.cluster_resources() if ray is not None else {}
        workers = int(resources.get("CPU", 0))
        _check_resources(o, plan, resources)
        with start_run("pipeline", f"pipeline {len(plan['todo'])} stages", params=params, enabled=track) as run:
            results, running = {}, {}
            # ray.init replaced the SIGTERM handler (exit 134, no summary), and an exception raised inside Ray's
            # C calls comes out as a SystemError: the signal sets a flag that the scheduling loop checks
            stop = StopOnSignal("rlsac pipeline", "the next check (within a second), cancelling the running stages",
                                "without the summary; running the command again resumes")
            try:
                with stop:
                    _run(plan, o, ray, run, results, running, stop)
            except Interrupted as e:  # the summary of what ran, the in-flight stages' tasks cancelled
                for ref, a in running.items():
                    results[a] = {"stage": a, "status": "interrupted", "seconds": None}
                    with contextlib.suppress(Exception):  # kills the worker: its guard SIGTERMs the stage, whose
                        ray.cancel(ref, force=True)  # rlsac command ends its own run KILLED
                _restore_interrupted(plan, running.values())
                e.summary = _summary(plan, base, skipped, results, time.time() - t0, workers, run, track)
                raise
            summary = _summary(plan, base, skipped, results, time.time() - t0, workers, run, track)
    finally:
        if started:
            ray.shutdown()
        if note is not None:
            note.unlink(missing_ok=True)
        if plan.get("remote") is not None:
            plan["remote"].close()
    return summary


def _run(plan: dict, o: dict, ray, run, results: dict, running: dict, stop: Callable[[], int]) -> None:
    from rlsac.progress import tqdm

    bar = tqdm(total=len(plan["todo"]), desc="pipeline", unit="stage")

    def progress(r: dict) -> None:
        bar.set_postfix_str(f"{r['status']} {r['stage']}", refresh=False)
        bar.update(1)
        if r.get("seconds") is not None and r["status"] != "skipped":  # logged as each stage ends, so an
            # interrupted run keeps the times of what it finished (pipeline_projection.py --from-mlflow)
            run.metrics({stage_metric(r["stage"]): r["seconds"]})

    try:
        if plan["todo"]:
            schedule(plan, o, ray, progress, results, running, stop)
    finally:
        bar.close()
        if plan.get("writer") is not None:
            plan["writer"].close()
