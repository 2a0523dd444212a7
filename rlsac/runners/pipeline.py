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
import fnmatch
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

from rlsac.errors import Interrupted, RlsacError
from rlsac.signals import StopOnSignal
from rlsac.signals import name as signal_name

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
LOG_DIR = Path("logs") / "pipeline"
# environment the driver passes to every stage (a worker on another node has its own environment otherwise)
FORWARD_ENV = ("MLFLOW_TRACKING_URI", "OMP_NUM_THREADS", "MLFLOW_LOGGING_LEVEL")
STATUSES = ("done", "skipped", "failed", "not run", "interrupted")
ADDRESS_TIMEOUT_S = 10.0  # an unreachable --address (a head still starting gets this long): Ray retried for minutes
_ERROR_LINE = re.compile(r"^(error\b|ERROR\b|[A-Za-z_][\w.]*(Error|Exception|Interrupt)\b)")
_SKIPPED = re.compile(r"Stage '.*' didn't change, skipping")
KILL_GRACE_S = 10.0
LOCK_TRIES = 10  # a stage's outputs locked by another dvc process: seconds to wait before giving up


# ----------------------------------------------------------------------------------------------------- plan


def _address(stage, root: Path) -> str:
    """The stage's address from the repository root (``dvc stage list``): ``name``, ``sub/dvc.yaml:name``, or a
    .dvc file."""
    name, dvcfile = getattr(stage, "name", None), Path(os.path.relpath(stage.dvcfile.path, root)).as_posix()
    return dvcfile if name is None else name if dvcfile == "dvc.yaml" else f"{dvcfile}:{name}"


def load_plan(repo_dir: str | os.PathLike, names: str | None = None, runner: str | None = None,
              remote: bool = False) -> dict:
    """-> {"root", "order" (every runnable stage, dependencies first), "deps" {address: [addresses it needs]},
    "todo" (addresses to run, in order), "selected" (addresses considered), "specs" and "writer"}. With ``runner``
    "direct", "specs" {address: what a task needs to run it, rlsac.runners.dvc_stage.stage_spec} (a ``.dvc`` file's
    stage has none: it keeps ``dvc repro -s``) and "writer" (the lock files' one writer,
    rlsac.runners.dvc_stage.LockWriter), made while the repository lock is held; else {} and None. Raises RlsacError on
    a path that is not a DVC repository, an unreadable pipeline, a lock file not laid out as DVC writes it, or a name
    that matches no stage. With
    ``remote`` (nodes share no disk), "paths" {address: its dependencies that travel,
    rlsac.runners.transfer.stage_paths},
    and RlsacError for a stage to run that only ``dvc repro -s`` runs (a ``.dvc`` file's)."""
    import networkx as nx

    from rlsac.runners.verify import open_repo, pipeline_error

    repo = open_repo(repo_dir)
    try:
        root = Path(repo.root_dir)
        try:
            graph = repo.index.graph  # edges go from a stage to the stages it depends on
        except Exception as e:
            raise pipeline_error(repo_dir, e) from None
        addr = {s: _address(s, root) for s in graph.nodes}
        by_addr = {a: s for s, a in addr.items()}
        if names is not None:  # given: '' or ',' name no stage (an error), not every stage
            chosen = set()
            for name in filter(None, (n.strip() for n in names.split(","))):
                hits = [a for a in by_addr if a == name or fnmatch.fnmatchcase(a, name)
                        or fnmatch.fnmatchcase(a, name + "@*")]  # `train_lines` = every train_lines@...
                if not hits:
                    raise RlsacError(f"no stage matches '{name}' (`dvc stage list` shows the names)")
                chosen.update(hits)
            if not chosen:  # `rlsac pipeline ','` ran nothing at exit 0 (verify refuses the same)
                raise RlsacError(f"stages {names!r}: names no stage (`dvc stage list` shows the names)")
            # what the named stages need comes along (as `dvc repro <stage>`)
            nodes = set()
            for a in chosen:
                nodes |= {by_addr[a], *nx.descendants(graph, by_addr[a])}
        else:
            nodes = set(graph.nodes)
        sub = graph.subgraph(nodes)
        # dependencies first; ties by address so the plan is stable
        ordered = list(nx.lexicographical_topological_sort(sub.reverse(copy=True), key=lambda s: addr[s]))
        runnable = [s for s in ordered if getattr(s, "cmd", None) and not s.frozen]
        run_set = set(runnable)
        deps = {addr[s]: sorted(addr[d] for d in graph.successors(s) if d in run_set) for s in runnable}
        todo: list[str] = []
        why: dict[str, str] = {}
        how = ""
        specs, writer, paths = {}, None, {}
        from dvc.lock import LockError

        for attempt in range(LOCK_TRIES):
            try:
                with repo.lock:
                    todo, (why, how) = [], _reasons(repo, runnable, addr, deps)
                    for s in runnable:  # an upstream stage that runs makes everything downstream of it run
                        if any(d in todo for d in deps[addr[s]]) or why[addr[s]] != UP_TO_DATE:
                            todo.append(addr[s])
                    if runner == "direct" and todo:
                        specs, writer = _direct(repo, root, [by_addr[a] for a in todo])
                    if remote and todo:
                        paths = _travelling(root, [by_addr[a] for a in todo], specs)
                break
            except LockError as e:  # another dvc process holds the repository or a stage's outputs (or has
                # just been killed and is not yet reaped: DVC drops its entries once the process is gone)
                if attempt == LOCK_TRIES - 1:
                    raise RlsacError(f"{repo_dir}: {' '.join(str(e).split())[:300]}") from None
                time.sleep(1.0)
    finally:
        repo.close()
    return {"root": root, "order": [addr[s] for s in runnable], "deps": deps, "todo": todo, "why": why, "how": how,
            "selected": sorted(addr[s] for s in ordered), "specs": specs, "writer": writer, "paths": paths}


def _direct(repo, root: Path, stages: list) -> tuple[dict, Any]:
    """The direct runner's part of the plan: each stage's spec and the lock files' writer."""
    from rlsac.runners.dvc_stage import LockWriter, stage_spec

    files: dict = {}
    for s in stages:  # one dvc.yaml object per file: each stage's own would parse its lock file again (3 s each)
        s.dvcfile = files.setdefault(s.path, s.dvcfile)
    specs = {_address(s, root): stage_spec(s, root) for s in stages}
    return {a: sp for a, sp in specs.items() if sp is not None}, LockWriter(repo, stages)


def _travelling(root: Path, stages: list, specs: dict) -> dict[str, list[str]]:
    """--remote's part of the plan: each stage's dependencies that go through the bucket (paths from the top of the
    git working tree: a nested DVC project's stages read files of the repository around it)."""
    from rlsac.runners.transfer import stage_paths, tree_root

    top, _ = tree_root(root)
    out = {}
    for s in stages:
        a = _address(s, root)
        if a not in specs:
            raise RlsacError(f"--remote: {a} is a .dvc file's stage (`dvc repro -s` runs it, in a shared folder only)")
        out[a] = stage_paths(s, top)
    return out


# Why a stage is out of date (the dry run's plan): its own change; an upstream stage's change; only its outputs are
# missing (git-ignored data a clean clone lacks: re-made from unchanged inputs, they are what dvc.lock recorded); only
# inputs that such a stage re-makes are missing (up to date once they are back); nothing.
CHANGED, UPSTREAM, REGENERATE, AFTER_DATA, UP_TO_DATE = ("changed", "upstream changed", "outputs missing",
                                                        "inputs missing", "up to date")


def _reasons(repo, runnable: list, addr: dict, deps: dict) -> tuple[dict[str, str], str]:
    """({address: one of the reasons above}, how the files were checked), in dependency order, by DVC's rules on
    dvc.lock and the files' md5s (rlsac.runners.stage_status: each file hashed once, kept by size and time across
    plans). A missing input counts as a change unless a stage that only re-makes missing outputs makes it: it is one of
    their outputs or lies inside one (``fold_data`` records the folder data/folds/<regime>/<fold>, later stages read
    files in it)."""
    from rlsac.runners.stage_status import Status

    status = Status(repo)
    why: dict[str, str] = {}
    remade: list[str] = []  # output paths of the stages that only re-make missing outputs

    def remade_by_data(d) -> bool:
        path = str(d.fs_path)
        return status.missing(d) and any(path == o or path.startswith(o.rstrip(os.sep) + os.sep) for o in remade)

    for s in runnable:
        a = addr[s]
        changed = [d for d in s.deps if status.changed(d)]
        own = (s.changed_stage() or s.always_changed or s.is_callback
               or any(not remade_by_data(d) for d in changed))
        if own:
            why[a] = CHANGED
        elif any(why[u] in (CHANGED, UPSTREAM) for u in deps[a]):
            why[a] = UPSTREAM
        elif status.changed_outs(s):
            why[a] = REGENERATE
            remade.extend(str(o.fs_path) for o in s.outs)
        else:
            why[a] = AFTER_DATA if changed else UP_TO_DATE
    status.hashes.save()
    return why, status.hashes.summary()


def _groups(addresses: list[str]) -> dict[str, int]:
    """Stage group (the name before ``@``) -> how many of ``addresses`` it holds, in first-seen order."""
    out: dict[str, int] = {}
    for a in addresses:
        g = a.split("@", 1)[0]
        out[g] = out.get(g, 0) + 1
    return out


# ------------------------------------------------------------------------------------- which ready stage first


def bottom_levels(deps: dict[str, list[str]], seconds: dict[str, float]) -> dict[str, float]:
    """{address: its bottom level}: the expected seconds of the longest chain from the stage (itself included) to
    the end of the plan. ``deps``: {address: the addresses it needs} (those outside ``deps`` are ignored);
    ``seconds``: each stage's expected time (a stage absent from it counts 1). Starting the ready stage with the
    highest bottom level first is list scheduling's critical-path rule: a long chain is not left waiting behind
    many short independent stages (issue #50, item 4)."""
    dependents: dict[str, list[str]] = {a: [] for a in deps}
    for a, ds in deps.items():
        for d in ds:
            if d in dependents:
                dependents[d].append(a)
    level: dict[str, float] = {}
    for a in reversed(_dependencies_first(deps)):
        level[a] = seconds.get(a, 1.0) + max((level[b] for b in dependents[a]), default=0.0)
    return level


def _dependencies_first(deps: dict[str, list[str]]) -> list[str]:
    """The addresses of ``deps``, each after those it needs (iterative: a chain of thousands of stages)."""
    done: set[str] = set()
    out: list[str] = []
    for start in sorted(deps):
        stack = [(start, iter(sorted(deps[start])))]
        while stack:
            a, needs = stack[-1]
            d = next((d for d in needs if d in deps and d not in done), None)
            if d is not None:
                if any(d == s for s, _ in stack):
                    raise RlsacError(f"the pipeline has a cycle through {d}")
                stack.append((d, iter(sorted(deps[d]))))
                continue
            stack.pop()
            if a not in done:
                done.add(a)
                out.append(a)
    return out


def expected_seconds(addresses: list[str], measured: dict[str, float]) -> dict[str, float]:
    """Each stage's expected seconds: its measured time (an earlier run's, ``logged_stage_times``), else its
    group's mean (a new seed of a group that ran before costs about what its siblings did), else 1."""
    groups: dict[str, list[float]] = {}
    for a, t in measured.items():
        groups.setdefault(a.split("@", 1)[0], []).append(t)
    mean = {g: sum(ts) / len(ts) for g, ts in groups.items()}
    return {a: measured.get(a, mean.get(a.split("@", 1)[0], 1.0)) for a in addresses}


def logged_stage_times(uri: str, addresses: list[str], repo: str | os.PathLike | None = None) -> dict[str, float]:
    """{address: seconds} of the stages of ``addresses`` that a pipeline run of the MLflow store ``uri`` timed
    (its metric ``stage_s/<address>``, logged as the stage ended); of several runs, the latest's; {} when the store
    has no pipeline run. ``repo``: only the runs of that DVC repository (their param ``repo``; the quick profile's
    stages have the same names)."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("pipeline")
    if exp is None:
        return {}
    names = {stage_metric(a): a for a in addresses}
    out: dict[str, float] = {}
    runs = client.search_runs([exp.experiment_id], order_by=["attributes.start_time ASC"], max_results=50000)
    root = None if repo is None else str(Path(repo).resolve())
    for run in runs:  # oldest first: a later run's time of a stage replaces an earlier one's
        if root is not None and run.data.params.get("repo") != root:
            continue
        out.update({names[k]: float(v) for k, v in run.data.metrics.items() if k in names})
    return out


# ------------------------------------------------------------------------------------------- one stage (task)


_GUARD = """
import os, signal, sys, time
import psutil
pgid, worker, grace = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
if os.fork():  # detach: Ray kills a dead worker's direct children, which would take this guard with them
    os._exit(0)
os.setsid()

def alive(pid):
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False

def group():
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False

while alive(worker):
    if not group():  # the stage ended: nothing to guard
        sys.exit(0)
    time.sleep(0.5)
for sig in (signal.SIGTERM, signal.SIGKILL):
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        sys.exit(0)
    end = time.monotonic() + (grace if sig == signal.SIGTERM else 0)
    while group() and time.monotonic() < end:
        time.sleep(0.2)
"""


def first_error_line(text: str) -> str:
    """The first line that reads as an error (``error: ...`` of an rlsac command, the ``XxxError: ...`` line that
    ends a traceback, DVC's ``ERROR: ...``), else the last non-empty line."""
    lines = [ln.rstrip() for ln in text.splitlines() if ln.strip()]
    for ln in lines:
        if _ERROR_LINE.match(ln):
            return ln.strip()
    return lines[-1].strip() if lines else "(no output)"


def start_guarded(argv: list[str], **kwargs) -> subprocess.Popen:
    """``subprocess.Popen(argv, **kwargs)`` in a process group of its own, stdin /dev/null, watched by the guard: it
    ends the group if this worker dies, and itself once the group is gone. The command starts once the guard
    watches (a shell reads a line from a pipe on its stdin, then execs it): a stage that ended its worker at once
    outlived it otherwise; if this worker dies first, the pipe closes and the command never starts."""
    kwargs.pop("stdin", None)
    ready, go = os.pipe()
    try:
        proc = subprocess.Popen(["/bin/sh", "-c", 'read _ || exit 111; exec "$@" </dev/null', "sh", *argv],
                                stdin=ready, start_new_session=True, **kwargs)
        guard(proc.pid)
        os.write(go, b"\n")
    finally:
        os.close(ready)
        os.close(go)
    return proc


def guard(pgid: int) -> None:
    """Start the guard of process group ``pgid`` (a stage command's session): it ends the group if this worker
    dies, and itself once the group is gone; it watches when this returns."""
    subprocess.run([sys.executable, "-c", _GUARD, str(pgid), str(os.getpid()), str(KILL_GRACE_S)],
                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def start_stage_command(argv: list[str], **kwargs):
    """How the direct runner starts a stage's command line: warm where it is a plain ``rlsac ...`` call
    (rlsac.runners.warm: the imports done once per worker), else start_guarded; guarded either way."""
    from rlsac.runners import warm

    return warm.start(argv, guard, start_guarded, **kwargs)


def _error(rc: int | None, log: str) -> str:
    return _error_text(rc, Path(log).read_text(errors="replace"))


def run_stage(root: str, address: str, env: dict[str, str], log: str) -> dict:
    """Run ``dvc --wait-for-lock repro -s <address>`` in ``root`` (the dvc runner: a Ray task's body; plain Python
    too). -> {stage, status (done / skipped / failed), seconds, rc, error, log, node}."""
    import socket

    from rlsac.runners.dvc_stage import python_bin_env

    Path(log).parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with open(log, "wb") as f:
        proc = start_guarded([sys.executable, "-m", "dvc", "--wait-for-lock", "repro", "-s", address], cwd=root,
                             env=python_bin_env(env), stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        rc = proc.wait()
    seconds = time.time() - t0
    status = "failed" if rc else "skipped" if _SKIPPED.search(Path(log).read_text(errors="replace")) else "done"
    return {"stage": address, "status": status, "seconds": seconds, "rc": rc, "error": _error(rc, log) if rc else None,
            "log": log, "node": socket.gethostname()}


def run_direct(root: str, address: str, spec: dict, env: dict[str, str], log: str) -> dict:
    """Run the stage's own command in ``root`` and compute its lock entry (the direct runner,
    rlsac.runners.dvc_stage.run: a
    Ray task's body; plain Python too). -> run_stage's result with "entry" and "ignore" for the driver's writer."""
    from rlsac.runners.dvc_stage import python_bin_env
    from rlsac.runners.dvc_stage import run as run_direct_stage

    r = run_direct_stage(root, spec, python_bin_env(env), log, start=start_stage_command)
    r["stage"] = address
    if r["status"] == "failed":
        r["error"] = _error(r["rc"], log)
    return r


def run_remote(conf: dict, tree: str, address: str, spec: dict, deps: list[dict], env: dict[str, str],
               log: str, sub: str = ".") -> dict:
    """The direct runner on a node that shares no folder with the driver (``--remote``,
    rlsac.runners.transfer.run_on_node:
    a Ray task's body). ``log``: its path from the repository root. -> run_direct's result with "outs" (what the
    driver brings back), "log_text" and "ignore" as paths from the root, "out_bytes", "node_id" (Ray's), and
    "downloads" and "cache_hits" (rlsac.runners.transfer.NodeCache)."""
    from rlsac.runners.dvc_stage import python_bin_env
    from rlsac.runners.dvc_stage import run as run_direct_stage
    from rlsac.runners.transfer import run_on_node

    def run(root: str, spec: dict, env: dict[str, str], log: str) -> dict:
        return run_direct_stage(root, spec, python_bin_env(env), log, start=start_stage_command)

    r = run_on_node(conf, tree, spec, deps, env, log, run, sub)
    r["stage"] = address
    with contextlib.suppress(Exception):  # the node its dependents prefer (its cache holds the outputs): a Ray task
        import ray

        r["node_id"] = ray.get_runtime_context().get_node_id()
    if r["status"] == "failed":
        r["error"] = _error_text(r["rc"], r["log_text"])
    return r


def _error_text(rc: int | None, text: str) -> str:
    line = first_error_line(text)
    return f"killed by {signal.Signals(-rc).name}: {line}" if rc and rc < 0 else line


# ------------------------------------------------------------------------------------------------- scheduling


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


def _check_tracking_server() -> None:
    """Stages on other machines log where MLFLOW_TRACKING_URI points: a sqlite file (the default) would be one store
    per node and the driver's a third, with no warning (issue #50, item 3), so a cluster needs an http(s) server."""
    from urllib.parse import urlsplit

    from rlsac.tracking import DEFAULT_URI

    uri = os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI
    if urlsplit(uri).scheme.lower() not in ("http", "https"):
        raise RlsacError(f"--address runs stages on other machines: MLFLOW_TRACKING_URI must be an http(s) MLflow "
                         f"server every node reaches, not {uri} (one store per node; docs/reproducing.md shows the "
                         "server command)")


def _auto_address() -> tuple[str, str]:
    """The address Ray's ``auto`` joins, found as ``ray.init`` finds it: RAY_ADDRESS, else the address file the last
    ``ray start`` (or a local cluster) wrote in Ray's temporary folder (ray_current_cluster; a killed cluster leaves it
    behind), else a Ray cluster process of this machine. -> (the address, where it was found)."""
    if os.environ.get("RAY_ADDRESS"):
        return os.environ["RAY_ADDRESS"], "from RAY_ADDRESS"
    from ray._common.utils import get_ray_address_file
    from ray._private.services import canonicalize_bootstrap_address

    try:
        address = canonicalize_bootstrap_address("auto")
    except Exception as e:  # noqa: BLE001 (Ray's ConnectionError when there is none; a bad file's ValueError)
        raise RlsacError(f"--address auto: no Ray cluster to join ({' '.join(str(e).split())[:160]})") from None
    file = get_ray_address_file(None)
    return address, f"from {file}" if Path(file).is_file() else "a Ray process of this machine"


def _check_address(address: str, shown: str | None = None) -> None:
    """A TCP connection to ``address`` (host:port, or ray://host:port) within ``ADDRESS_TIMEOUT_S``, retried while
    refused (a head started just before): Ray's own connection retried for over 400 s, with the MLflow run open.
    ``shown``: the option's value in the error, when not ``address`` (``auto`` and what it stood for)."""
    import socket
    from urllib.parse import urlsplit

    shown = shown or address
    where = urlsplit(address if "://" in address else f"ray://{address}")
    try:
        host, port = where.hostname, where.port
    except ValueError:  # a port that is not a number
        host, port = None, None
    if not host or not port:
        raise RlsacError(f"--address {shown}: not host:port (`ray start --head` prints the address), nor 'auto'")
    end = time.monotonic() + ADDRESS_TIMEOUT_S
    while True:
        try:
            socket.create_connection((host, port), timeout=max(0.1, end - time.monotonic())).close()
            return
        except OSError as e:
            if time.monotonic() + 0.5 >= end:
                raise RlsacError(f"--address {shown}: no Ray cluster answers there within {ADDRESS_TIMEOUT_S:g} s "
                                 f"({e.__class__.__name__}: {' '.join(str(e).split())[:120]})") from None
            time.sleep(0.5)


def _check_resources(o: dict, plan: dict, resources: dict) -> None:
    """What the stages ask Ray for must exist in the cluster, else a task waits for ever."""
    gpu_stages = [a for a in plan["todo"] if o["gpus_per_train"] > 0 and _is_gpu_stage(a, o["gpu_stages"])]
    if gpu_stages and resources.get("GPU", 0) < o["gpus_per_train"]:
        raise RlsacError(f"--gpus-per-train {o['gpus_per_train']:g}: the Ray cluster has "
                         f"{resources.get('GPU', 0):g} GPUs ({gpu_stages[0]} would never start)")


def _start_ray(o: dict) -> tuple[Any, bool]:
    """-> (ray, started): joins ``address``, or starts a local cluster of ``workers`` CPUs; an already
    initialised Ray (a test, a notebook) is used as it is and left running."""
    import logging

    if o["address"] and o["address"] != "auto" and "RAY_AUTH_MODE" not in os.environ and (
            os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
            or (Path.home() / ".ray" / "auth_token").is_file()):
        # Ray uses the cluster token (RAY_AUTH_TOKEN, ~/.ray/auth_token) by itself for `auto` only; for an explicit
        # address it must be asked for, before Ray is imported (its configuration is read then)
        os.environ["RAY_AUTH_MODE"] = "token"
    import ray

    if ray.is_initialized():
        return ray, False
    kwargs = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
    try:
        if o["address"]:
            ray.init(address=o["address"], **kwargs)
        else:  # a local cluster: token authentication stays on, its notice is noise on this screen
            auth_log = logging.getLogger("ray._private.authentication.authentication_token_setup")
            level = auth_log.level
            auth_log.setLevel(logging.ERROR)
            try:
                # address="local": a new cluster even where `ray start` left one running (or its address file)
                ray.init(address="local", num_cpus=o["workers"] or os.cpu_count() or 1, **kwargs)
            finally:
                auth_log.setLevel(level)
    except Exception as e:
        raise RlsacError(f"cannot start Ray{' at ' + o['address'] if o['address'] else ''} "
                         f"({e.__class__.__name__}: {' '.join(str(e).split())[:200]})") from None
    return ray, True


def _is_gpu_stage(address: str, patterns: str) -> bool:
    return any(fnmatch.fnmatchcase(address, p.strip()) for p in patterns.split(",") if p.strip())


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


# --------------------------------------------------------------------------------------------------- command


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


DRIVERS = Path(".dvc") / "tmp" / "rlsac-drivers"  # under the repository's root: <pid>.json of each running driver


def _note_driver(root: Path, ray) -> Path | None:
    """The local Ray cluster this driver started, by its session's name (in the command line of each of its
    processes), in ``DRIVERS``: if the driver is SIGKILLed, ``recover`` ends what of the cluster outlived it (Ray's
    agents did). -> the note's path, removed when the driver ends; None when Ray does not say its session."""
    from rlsac.runners.dvc_stage import _owner, write_atomic

    try:
        session = Path(ray._private.worker._global_node.get_session_dir_path()).name
    except Exception:  # noqa: BLE001 (Ray's internals moved: nothing to note, nothing ended later)
        return None
    path = root / DRIVERS / f"{os.getpid()}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, json.dumps({"owner": _owner(), "session": session}))
    return path


def _end_session(session: str) -> int:
    """End (SIGTERM, then SIGKILL after 5 s) this user's processes whose command line names the Ray session
    ``session``. -> how many there were."""
    import psutil

    me, user = os.getpid(), psutil.Process().username()
    procs = []
    for p in psutil.process_iter(["cmdline", "username"]):
        with contextlib.suppress(psutil.Error):
            if p.pid != me and p.info["username"] == user and session in " ".join(p.info["cmdline"] or []):
                p.terminate()
                procs.append(p)
    _, left = psutil.wait_procs(procs, timeout=5)
    for p in left:
        with contextlib.suppress(psutil.Error):
            p.kill()
    return len(procs)


def recover(repo: str | os.PathLike = ".", required: bool = False) -> dict:
    """What a SIGKILLed driver of this repository left, repaired: its local Ray cluster's processes that outlived it
    ended, then the outputs its stages had set aside put back (rlsac.runners.dvc_stage.recover). ``repo``: the
    repository or a folder in it (``required``: else an error; not: nothing to do). -> {"processes": how many were
    ended, "outputs": the paths restored, from the root}."""
    from rlsac.runners.dvc_stage import _alive
    from rlsac.runners.dvc_stage import recover as recover_outputs

    root = _dvc_root(repo)
    if root is None:
        if required:
            raise RlsacError(f"--repo {repo}: not in a DVC repository (no .dvc folder here or above)")
        return {"processes": 0, "outputs": []}
    ended = 0
    for note in sorted((root / DRIVERS).glob("*.json")) if (root / DRIVERS).is_dir() else []:
        try:
            driver = json.loads(note.read_text())
            if _alive(driver["owner"]):
                continue
            ended += _end_session(str(driver["session"]))
        except (OSError, ValueError, KeyError, TypeError):
            pass  # a note cut short or not ours: it goes
        note.unlink(missing_ok=True)
    # a dead worker's guard ends its stage's command within the grace: the outputs wait for that, no longer
    outputs = recover_outputs(root, wait_s=KILL_GRACE_S + 5.0)
    return {"processes": ended, "outputs": [os.path.relpath(p, root) for p in outputs]}


def _dvc_root(repo: str | os.PathLike) -> Path | None:
    """The DVC repository holding ``repo`` (the nearest folder with a .dvc folder, up from it), None outside one."""
    return next((d for d in (Path(repo).resolve(), *Path(repo).resolve().parents) if (d / ".dvc").is_dir()), None)


def format_recovery(r: dict) -> str | None:
    """One line of what ``recover`` did, None when there was nothing to do."""
    if not r["processes"] and not r["outputs"]:
        return None
    return (f"pipeline: a killed run's leftovers repaired: {len(r['outputs'])} set-aside outputs restored"
            + (f" ({_names(r['outputs'])})" if r["outputs"] else "")
            + f", {r['processes']} Ray processes of its cluster ended")


def _restore_interrupted(plan: dict, addresses) -> None:
    """The outputs of the stages an interruption stopped, as they were before them (rlsac.runners.dvc_stage.restore,
    once each stage's guard has ended its command): a cancelled worker cannot do it, and DVC's way (outputs deleted
    before the command) would leave committed files deleted. A --remote stage's outputs are on its node."""
    if plan.get("remote") is not None:
        return
    from rlsac.runners.dvc_stage import restore

    for a in addresses:
        if a in plan.get("specs", {}):
            restore(plan["root"], plan["specs"][a], wait_s=KILL_GRACE_S + 5.0)


def _priorities(plan: dict, track: bool) -> dict[str, float]:
    """Each stage to run -> its bottom level, from the stage times earlier pipeline runs of this repository logged
    to the tracking store (none with --no-tracking: then every stage counts 1, the longest chain of stages first)."""
    from rlsac.tracking import DEFAULT_URI

    measured = {}
    if track and plan["todo"]:
        try:  # an order, not a result: a store that cannot answer (busy, old schema) leaves every stage at 1
            measured = logged_stage_times(os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI), plan["todo"],
                                          plan["root"])
        except Exception as e:  # noqa: BLE001 (MLflow's and the HTTP client's errors alike)
            print(f"pipeline: no stage times from the tracking store ({type(e).__name__}); every stage counts 1")
    todo = set(plan["todo"])
    deps = {a: [d for d in plan["deps"][a] if d in todo] for a in plan["todo"]}
    return bottom_levels(deps, expected_seconds(plan["todo"], measured))


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


def _summary(plan: dict, base: dict, skipped: list[str], results: dict, wall: float, workers: int, run,
             track: bool) -> dict:
    """-> the command's result (see ``pipeline``), logged to the run; stages never reached are "not run"."""
    results = dict(results)
    for a in skipped:
        results[a] = {"stage": a, "status": "skipped", "seconds": None}
    for a in plan["todo"]:
        results.setdefault(a, {"stage": a, "status": "not run"})
    results = {a: results[a] for a in plan["order"] if a in results}
    counts = {s: sum(r["status"] == s for r in results.values()) for s in STATUSES}
    run.metrics({f"n_{k.replace(' ', '_')}": v for k, v in counts.items()})
    run.metrics({"wall_s": wall, "workers": workers})
    if track:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "pipeline.json"
            path.write_text(json.dumps({"deps": plan["deps"], "results": results}, indent=1) + "\n")
            run.artifact(path)
    return {**base, "dry_run": False, "results": results, "counts": counts, "wall_s": wall, "workers": workers,
            "run_id": run.run_id}


def stage_metric(stage: str) -> str:
    """The MLflow metric of a stage's wall time (stage wall times go to MLflow only, never into committed files):
    ``stage_s/<address>``, the characters MLflow refuses replaced by ``_``."""
    return "stage_s/" + re.sub(r"[^\w.\- /]", "_", stage)


def _names(items: list[str], width: int = 110) -> str:
    """Comma-separated names cut to about one line: ``a, b, c, ... and 40 more``."""
    out, n = "", 0
    for i, a in enumerate(items):
        piece = (", " if out else "") + a
        if len(out) + len(piece) > width and i < len(items) - 1:
            return out + f", ... and {len(items) - n} more"
        out += piece
        n += 1
    return out


def _shown(path: str) -> str:
    """A path relative to the current directory when it lies under it, else as it is."""
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def _plan_lines(s: dict, by: dict) -> list[str]:
    """The dry run: the count, the stages to run; where some only re-make missing outputs (a clean clone's data),
    what runs after them (one line per stage group when any does), and how the files were checked. A stage that
    waits only on re-made outputs counts as up to date: it is skipped when its turn comes if they match dvc.lock."""
    why = s.get("why") or {}
    waiting = [a for a in s["todo"] if why.get(a) in (AFTER_DATA, UP_TO_DATE)]  # in todo after a waiting stage
    run = [a for a in s["todo"] if a not in set(waiting)]
    lines = [f"pipeline (dry run): {len(run)} to run, {len(by['skipped']) + len(waiting)} up to date of "
             f"{s['n_selected']} stages" + (f" ({len(waiting)} of them once the re-made outputs match dvc.lock)"
                                             if waiting else "")]
    if run:
        lines.append(f"to run   {_names(run)}")
    remake = [a for a in run if why.get(a) == REGENERATE]
    if remake:
        after = [a for a in run if why.get(a) in (CHANGED, UPSTREAM)]
        lines.append(f"plan: {len(remake)} stages re-make missing outputs from unchanged inputs ({_names(remake)}); "
                     f"after them {len(after)} run" + (", by group:" if after else ""))
        if after:
            lines.append("  group                          run  up to date")
            run_g, all_g = _groups(after), _groups([a for a in s["why"] if a not in remake])
            for g, n in all_g.items():
                lines.append(f"  {g:<30} {run_g.get(g, 0):>3}  {n - run_g.get(g, 0):>10}")
    if s.get("how"):
        lines.append(s["how"])
    return lines


def format_summary(s: dict) -> str:
    """The one-screen summary: counts, then one line per status (names cut to a line), failed stages one per
    line with the error's first line and their log (the first 10)."""
    by = {k: [a for a, r in s["results"].items() if r["status"] == k] for k in STATUSES}
    if s["dry_run"]:
        return "\n".join(_plan_lines(s, by))
    head = ", ".join(f"{len(by[k])} {k}" for k in STATUSES if k != "interrupted" or by[k])
    lines = [f"pipeline: {head} of {s['n_selected']} stages in {s['wall_s']:.1f} s"
             + (f" ({s['workers']} CPUs)" if s["workers"] else "")]
    for k in ("done", "skipped"):
        if by[k]:
            lines.append(f"{k:<8} {_names(by[k])}")
    retried = [a for a, r in s["results"].items() if r.get("retried")]
    if retried:  # their worker or node died, then a new run of the stage ended as its status says
        lines.append(f"retried  {_names(retried)} (worker or node lost: {s['results'][retried[0]]['retried'][0]})")
    for a in by["failed"][:10]:
        r = s["results"][a]
        lines.append(f"failed   {a}: {r['error']}" + (f" (log {_shown(r['log'])})" if r.get("log") else ""))
    if len(by["failed"]) > 10:
        lines.append(f"failed   ... and {len(by['failed']) - 10} more")
    if by["not run"]:
        lines.append(f"not run  {_names(by['not run'])}")
    if by["interrupted"]:  # in flight at SIGINT / SIGTERM: their tasks cancelled, their runs ended KILLED
        lines.append(f"interrupted {_names(by['interrupted'])}")
    return "\n".join(lines)
