"""The scheduling loop: stages handed to Ray in dependency order, highest bottom level first and only
as many as fit; a lost worker's stage retried; each finished stage's lock entry written once."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Callable

from rlsac.errors import Interrupted
from rlsac.runners.cluster import _is_gpu_stage
from rlsac.runners.stage_task import LOG_DIR, first_error_line, run_direct, run_remote, run_stage
from rlsac.signals import name as signal_name

# environment the driver passes to every stage (a worker on another node has its own environment otherwise)
FORWARD_ENV = ("MLFLOW_TRACKING_URI", "OMP_NUM_THREADS", "MLFLOW_LOGGING_LEVEL")


def _descendants(address: str, dependents: dict[str, list[str]]) -> set[str]:
    out, stack = set(), [address]
    while stack:
        for d in dependents.get(stack.pop(), []):
            if d not in out:
                out.add(d)
                stack.append(d)
    return out


def _bring_back(plan: dict, r: dict) -> None:
    """--remote: a finished stage's log and outputs into the driver's workspace, before its lock entry is written
    and before any dependent starts (a stage whose outputs do not come back failed)."""
    from rlsac.runners.dvc_stage import write_atomic

    outs, text = r.pop("outs", None), r.pop("log_text", None)
    if text is not None:
        r["log"] = str(plan["root"] / LOG_DIR / (re.sub(r"[^\w.@-]", "_", r["stage"]) + ".log"))
        Path(r["log"]).parent.mkdir(parents=True, exist_ok=True)
        write_atomic(Path(r["log"]), text)
    if r["status"] == "done":
        r["ignore"] = [str(plan["root"] / p) for p in r.get("ignore") or []]
        try:
            plan["remote"].bring_back(outs or [])
        except Exception as e:
            r.update(status="failed", error=f"outputs not brought back from {plan['remote'].store.url}: "
                                            f"{e.__class__.__name__}: {' '.join(str(e).split())[:300]}")


def _record(plan: dict, address: str, r: dict) -> None:
    """A direct-run stage that finished: its lock entry into dvc.lock (a stage whose entry cannot be written failed:
    the next run re-runs it); the entry leaves the result."""
    if plan.get("remote") is not None:
        _bring_back(plan, r)
    entry, ignore = r.pop("entry", None), r.pop("ignore", None)
    if r["status"] != "done" or entry is None:
        return
    try:
        plan["writer"].record(plan["specs"][address], {"entry": entry, "ignore": ignore or []})
    except Exception as e:
        why = " ".join(str(e).split())[:300]
        r.update(status="failed", error=f"dvc.lock not updated: {e.__class__.__name__}: {why}")


# Ray's errors for a task whose worker or node died, not for the stage's own failure (its command's non-zero exit is
# a result, "failed"; an exception of the task's body is RayTaskError): a stage is idempotent (its outputs are removed
# before its command runs), so such a stage is run again, up to --retries times
SYSTEM_FAILURES = ("WorkerCrashedError", "NodeDiedError", "LocalRayletDiedError", "OutOfMemoryError",
                   "ObjectLostError", "OwnerDiedError")


def _system_failure(e: BaseException) -> bool:
    return any(c.__name__ in SYSTEM_FAILURES for c in type(e).__mro__)


def _fitting(ready: list[str], running: dict, o: dict, ray) -> list[str]:
    """Of ``ready`` (highest bottom level first), those the cluster has room for now, in that order: each task
    holds one CPU (and a training stage ``gpus_per_train`` GPUs). Submitting only these keeps the order ours: a
    stage that became ready later with a longer path ahead is not queued in Ray behind short ones. The cluster's
    size is read each time (a node lost or added counts); other jobs' use of it is not known, so this may still
    queue in Ray. With nothing running, the first ready stage goes anyway (Ray waits for room)."""
    total = ray.cluster_resources()

    def gpus(a: str) -> float:
        return o["gpus_per_train"] if o["gpus_per_train"] > 0 and _is_gpu_stage(a, o["gpu_stages"]) else 0.0

    cpus, gpu = total.get("CPU", 0) - len(running), total.get("GPU", 0) - sum(gpus(a) for a in running.values())
    out = []
    for a in ready:
        if cpus >= 1 and gpus(a) <= gpu:
            out.append(a)
            cpus, gpu = cpus - 1, gpu - gpus(a)
    return out or ([ready[0]] if ready and not running else [])


def _main_parent(a: str, plan: dict, placed: dict[str, tuple[str, int]]) -> str | None:
    """--remote: the node that ran the stage's parent with the most output bytes (what the stage would otherwise
    fetch from the bucket): its dependents prefer that node, whose cache holds those outputs."""
    parents = [(placed[d][1], d) for d in plan["deps"][a] if d in placed]
    return placed[max(parents)[1]][0] if parents else None


def _submitter(plan: dict, o: dict, ray) -> Callable[[str, str | None], Any]:
    """-> submit(address, preferred node id or None) -> the Ray task's reference."""
    root = str(plan["root"])
    env = {k: os.environ[k] for k in FORWARD_ENV if k in os.environ}
    env.setdefault("OMP_NUM_THREADS", "1")
    task, direct, remote = ray.remote(run_stage), ray.remote(run_direct), ray.remote(run_remote)
    ws = plan.get("remote")  # --remote: rlsac.runners.transfer.Workspace

    def submit(a: str, node: str | None):
        opts: dict[str, Any] = {"num_cpus": 1, "max_retries": 0}  # retries are the driver's (schedule)
        if o["gpus_per_train"] > 0 and _is_gpu_stage(a, o["gpu_stages"]):
            opts["num_gpus"] = o["gpus_per_train"]
        log = str(plan["root"] / LOG_DIR / (re.sub(r"[^\w.@-]", "_", a) + ".log"))
        if ws is not None:  # its inputs into the bucket first: the task fetches them on its node
            if node is not None:  # soft: any node, when that one is gone or full
                from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

                opts["scheduling_strategy"] = NodeAffinitySchedulingStrategy(node_id=node, soft=True)
            deps = ws.send(plan["paths"][a])
            rel = os.path.relpath(log, plan["root"])
            return remote.options(**opts).remote(ws.conf, ws.tree, a, plan["specs"][a], deps, env, rel, ws.sub)
        if a in plan.get("specs", {}):
            return direct.options(**opts).remote(root, a, plan["specs"][a], env, log)
        return task.options(**opts).remote(root, a, env, log)

    return submit


def schedule(plan: dict, o: dict, ray, progress: Callable[[dict], None] | None = None,
             results: dict[str, dict] | None = None, running: dict | None = None,
             stop: Callable[[], int] | None = None) -> dict[str, dict]:
    """Run ``plan["todo"]`` as Ray tasks, each once its dependencies are done, as many at once as the cluster
    has room for, the ready stage with the highest ``plan["priority"]`` (its bottom level) first. A stage whose
    worker or node died is run again, up to ``o["retries"]`` times. -> {address: result}; a stage that never ran:
    {"status": "not run", "after": <failed stage>}. ``results`` and ``running`` (task -> address), when given, are
    filled as it goes: what an interrupted pipeline reports; ``stop()`` true (a signal's number) ends the loop with
    ``Interrupted``."""
    todo = plan["todo"]
    submit = _submitter(plan, o, ray)
    priority = plan.get("priority") or {}
    waiting = {a: {d for d in plan["deps"][a] if d in todo} for a in todo}
    dependents: dict[str, list[str]] = {a: [] for a in todo}
    for a, ds in waiting.items():
        for d in ds:
            dependents[d].append(a)
    lost: dict[str, list[str]] = {a: [] for a in todo}  # each attempt's error, of a stage whose worker died
    placed: dict[str, tuple[str, int]] = {}  # --remote: a finished stage's node and output bytes
    results = {} if results is None else results
    running = {} if running is None else running
    while waiting or running:
        ready = sorted((a for a in waiting if not waiting[a]), key=lambda a: (-priority.get(a, 0.0), a))
        for a in _fitting(ready, running, o, ray) if ready else []:
            del waiting[a]
            running[submit(a, _main_parent(a, plan, placed))] = a
        if not running:  # nothing runnable is left: the rest waits on a failed stage (already marked)
            break
        done, _ = ray.wait(list(running), num_returns=1, timeout=None if stop is None else 0.5)
        if stop is not None and stop():
            raise Interrupted(f"interrupted by {signal_name(stop.signum)}", stop.signum)
        for ref in done:
            a = running.pop(ref)
            try:
                r = ray.get(ref)
            except Exception as e:  # the worker died (killed, out of memory, node lost), or the task's body raised
                error = f"{e.__class__.__name__}: {first_error_line(str(e))}"
                if _system_failure(e) and len(lost[a]) < o["retries"]:
                    lost[a].append(error)
                    waiting[a] = set()  # ready again: its next turn as its bottom level says
                    continue
                r = {"stage": a, "status": "failed", "seconds": None, "rc": None, "log": None, "node": None,
                     "error": error + (f" (tried {len(lost[a]) + 1} times)" if lost[a] else "")}
            if lost[a]:
                r["retried"] = lost[a]
            _record(plan, a, r)  # once per stage, whatever its tries: one lock entry
            results[a] = r
            if r.get("node_id") and r["status"] == "done":
                placed[a] = (r["node_id"], r.get("out_bytes", 0))
            _settle(a, r, waiting, dependents, results)
            if progress is not None:
                progress(r)
    return {a: results[a] for a in todo if a in results}


def _settle(a: str, r: dict, waiting: dict, dependents: dict, results: dict) -> None:
    """A finished stage: a failed one's descendants are not run; a done (or skipped) one frees its dependents."""
    if r["status"] == "failed":
        for d in _descendants(a, dependents):
            if d in waiting:
                del waiting[d]
                results[d] = {"stage": d, "status": "not run", "after": a}
    else:
        for d in dependents[a]:
            waiting.get(d, set()).discard(a)
