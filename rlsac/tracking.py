"""One MLflow helper for every command: experiment per task, flattened params, FAILED on error.

The tracking URI defaults to ``sqlite:///mlflow.db`` in the working directory; MLFLOW_TRACKING_URI
overrides it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import warnings
from pathlib import Path
from typing import Any, Iterator

from rlsac.config import flatten

DEFAULT_URI = "sqlite:///mlflow.db"


def _quiet() -> None:
    # MLflow's sqlite backend logs every alembic migration at INFO on first use.
    for name in ("alembic", "mlflow", "alembic.runtime.migration"):
        logging.getLogger(name).setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", module="mlflow")
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")


class Run:
    """Thin wrapper over an active MLflow run; every method is a no-op when tracking is off."""

    def __init__(self, mlflow_mod=None):
        self._mlflow = mlflow_mod
        self.run_id: str | None = None

    def params(self, params: dict[str, Any]) -> None:
        if self._mlflow is None:
            return
        flat = {k: (str(v)[:500] if v is not None else "None") for k, v in flatten(params).items()}
        items = list(flat.items())
        for i in range(0, len(items), 100):
            self._mlflow.log_params(dict(items[i : i + 100]))

    def metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        if self._mlflow is None:
            return
        clean = {k: float(v) for k, v in metrics.items() if v is not None}
        if clean:
            self._mlflow.log_metrics(clean, step=step)

    def artifact(self, path: str | Path, subdir: str | None = None) -> None:
        if self._mlflow is None or not Path(path).exists():
            return
        self._mlflow.log_artifact(str(path), artifact_path=subdir)

    def tags(self, tags: dict[str, str]) -> None:
        if self._mlflow is not None:
            self._mlflow.set_tags(tags)


def _store_lock(uri: str):
    """Serialise first use of a sqlite store across processes.

    Two commands started together on a fresh ``mlflow.db`` (e.g. two stages of ``rlsac pipeline``) both run
    MLflow's schema migrations and one fails with "table ... already exists"; creating the same
    experiment twice races the same way. A lock file next to the database orders them.
    """
    db = store_path(uri)
    if db is None:
        return contextlib.nullcontext()
    from filelock import FileLock

    return FileLock(str(db) + ".lock", timeout=600)


def client(uri: str | None = None):
    """An MLflow client of the store at ``uri`` (MLFLOW_TRACKING_URI, else DEFAULT_URI), made under the store lock:
    making one opens the store, which runs MLflow's schema migrations on a new file. Unlocked, a command that only
    reads the store (check_store's look-up of an experiment) raced another's migrations on a fresh ``mlflow.db``
    and left it unusable ("table _alembic_tmp_experiments already exists": every stage of a --workers 2 verify
    failed)."""
    _quiet()
    import mlflow

    uri = uri or os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    with _store_lock(uri):
        return mlflow.MlflowClient(uri)


def store_path(uri: str | None = None) -> Path | None:
    """The database file of a ``sqlite:///`` tracking URI (None for other stores)."""
    uri = uri or os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    prefix = "sqlite:///"
    return Path(uri[len(prefix):]) if uri.startswith(prefix) else None


def check_store(enabled: bool = True, experiment: str | None = None) -> None:
    """Fail early, with a one-line RlsacError, when the tracking store cannot be written (a read-only working
    directory, a path under a regular file): commands call it before their work. With ``experiment``, its
    artifact location too (issue #28, item 5: an unwritable artifact root failed after the work, at the first
    artifact, with a traceback and a FAILED run)."""
    if not enabled:
        return
    from rlsac.errors import RlsacError
    from rlsac.io import check_writable

    db = store_path()
    try:
        if db is not None:
            check_writable(db, "the MLflow store")
            check_writable(Path(str(db) + ".lock"), "the MLflow store lock")
        if experiment is not None:
            where = artifact_path(experiment)
            if where is not None:
                check_writable(where, "MLflow artifacts of experiment " + repr(experiment), folder=True)
    except RlsacError as e:
        raise RlsacError(f"{e}; use --no-tracking or set MLFLOW_TRACKING_URI") from None


def artifact_path(experiment: str) -> Path | None:
    """The local folder where the runs of ``experiment`` put their artifacts: the experiment's artifact location
    when the store has the experiment, else where MLflow puts a new experiment's (./mlruns/<id> of a sqlite store,
    so the root ./mlruns is what must be writable); None for a remote location (s3://, mlflow-artifacts:, ...)
    or a store other than sqlite, which this check does not reach. Reads the store only when its file exists."""
    db = store_path()
    if db is None:
        return None
    location = None
    if db.is_file():
        try:
            exp = client().get_experiment_by_name(experiment)
        except Exception:  # an unreadable store fails later with its own one-line error (start_run)
            exp = None
        location = exp.artifact_location if exp is not None else None
    if location is None:  # MLflow's default for a new experiment (mlflow.tracking._tracking_service.utils)
        location = os.environ.get("_MLFLOW_SERVER_ARTIFACT_ROOT", "./mlruns")
    from urllib.parse import unquote, urlparse

    url = urlparse(location)
    if url.scheme == "file":
        return Path(unquote(url.path))
    return Path(location) if url.scheme == "" else None


def command_name() -> str | None:
    """The ``rlsac`` subcommand being run (from click's context), None outside the CLI."""
    try:
        import click

        ctx = click.get_current_context(silent=True)
    except ImportError:  # pragma: no cover
        return None
    return ctx.info_name if ctx is not None and ctx.parent is not None else None


def run_status(run_id: str) -> str | None:
    """Status of run ``run_id`` in the current store (RUNNING, FINISHED, FAILED, KILLED), None if absent."""
    try:
        return client().get_run(run_id).info.status
    except Exception:  # deleted, or from another store
        return None


def _error_tags(e: BaseException) -> dict[str, str]:
    message = " ".join(str(e).split()) or e.__class__.__name__
    if isinstance(e, KeyboardInterrupt) and not str(e):
        message = "interrupted (KeyboardInterrupt)"
    return {"error": message[:5000], "error_type": e.__class__.__name__}


def _process_tags() -> dict[str, str]:
    """Which process holds a run: ``close_dead_runs`` ends the runs of processes that no longer exist."""
    import socket

    return {"host": socket.gethostname(), "pid": str(os.getpid())}


def _alive(pid: int, since_s: float) -> bool:
    """Whether process ``pid`` exists and started before ``since_s`` (epoch seconds): a newer process of the same
    pid is not the one that opened the run."""
    import psutil

    try:
        return psutil.Process(pid).create_time() <= since_s + 1.0
    except (psutil.NoSuchProcess, psutil.AccessDenied, ValueError):
        return False


def close_dead_runs(client=None) -> list[str]:
    """End KILLED every RUNNING run of this host whose process (tags ``host`` and ``pid``) is gone: a SIGKILL (or a
    lost machine) gives a process no chance to end its run, so the next command on the host does it (issue #49).
    -> the run ids closed. Runs of other hosts, and runs without the tags, are left alone."""
    import socket

    import mlflow

    client = client or mlflow.MlflowClient()
    host, closed = socket.gethostname(), []
    ids = [e.experiment_id for e in client.search_experiments()]
    if not ids:
        return closed
    for r in client.search_runs(ids, filter_string=f"attributes.status = 'RUNNING' and tags.host = '{host}'",
                                max_results=1000):
        pid = r.data.tags.get("pid", "")
        if not pid.isdigit() or _alive(int(pid), r.info.start_time / 1000.0):
            continue
        client.set_tag(r.info.run_id, "error", f"process {pid} on {host} ended while the run was RUNNING (killed, "
                       "e.g. by SIGKILL); closed by a later command")
        client.set_terminated(r.info.run_id, status="KILLED")
        closed.append(r.info.run_id)
    return closed


# MLflow 3's UI opens an experiment on its GenAI overview ("Traces: 0") unless the experiment says it is model
# training: with this tag it opens on the runs table (issue #47) where the UI's workflow switch is off; 3.17's is on
# and reads the page's workflowType instead (RUNS_PAGE below). The kind is the UI's, not a documented constant
EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")
# The runs table's columns: MLflow 3.17 shows no metric column until one is picked, and takes none from the URL; a
# shared view state (an experiment tag the UI reads for `?viewStateShareKey=rlsac`) brings the main metrics and the
# sort by mAA (metrics an experiment does not log are not shown). The key format is the UI's, not a documented API
VIEW_KEY = "rlsac"
VIEW_STATE = ("mlflow.sharedViewState." + VIEW_KEY, json.dumps({
    "selectedColumns": [f"metrics.`{m}`" for m in ("mAA", "mAA_R", "mAA_t", "median_R", "median_t")],
    "orderByKey": "metrics.`mAA`", "orderByAsc": False}))


@contextlib.contextmanager
def start_run(experiment: str, run_name: str, params: dict[str, Any] | None = None,
              tags: dict[str, str] | None = None, enabled: bool = True, run_id: str | None = None) -> Iterator[Run]:
    """Open an MLflow run in ``experiment``; the run ends FINISHED, FAILED if the block raises (the
    message in the ``error`` tag), KILLED on KeyboardInterrupt or an exception whose ``run_status``
    is "KILLED". The ``command`` tag defaults to the rlsac subcommand.

    ``run_id``: continue that run (``rlsac train --resume``) when the store still has it; params it
    already holds with another value are not re-logged but tagged ``changed_on_resume.<key>``.
    Every run is tagged with its ``host`` and ``pid``; runs of this host's dead processes are closed first
    (``close_dead_runs``).
    """
    if not enabled:
        yield Run(None)
        return
    check_store(True, experiment)
    _quiet()
    import mlflow

    from rlsac.errors import RlsacError

    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    tags = {**{k: str(v) for k, v in (tags or {}).items()}, **_process_tags()}
    if "command" not in tags and command_name():
        tags["command"] = command_name()
    try:
        mlflow.set_tracking_uri(uri)
        with _store_lock(uri):
            exp = mlflow.set_experiment(experiment)
            for tag in (EXPERIMENT_KIND, VIEW_STATE):  # an experiment of ours, new or from before the tag
                if (exp.tags or {}).get(tag[0]) != tag[1]:
                    mlflow.MlflowClient().set_experiment_tag(exp.experiment_id, *tag)
        with contextlib.suppress(Exception):  # a store that cannot be searched still records this run
            close_dead_runs()
        old = None
        if run_id is not None:
            try:
                old = mlflow.MlflowClient().get_run(run_id)
            except Exception:
                old = None
            if old is not None and old.info.experiment_id != mlflow.get_experiment_by_name(experiment).experiment_id:
                old = None
        if old is not None:
            active = mlflow.start_run(run_id=run_id)
        else:
            # in the experiment set_experiment returned: where two processes create it at once, MLflow's
            # set_experiment returns it without making it active, and start_run then took MLFLOW_EXPERIMENT_ID from
            # the environment (a pipeline stage's run landed in the driver's "pipeline" experiment)
            active = mlflow.start_run(run_name=run_name, experiment_id=exp.experiment_id)
    except RlsacError:
        raise
    except Exception as e:  # an unusable store: one line, not MLflow's traceback
        raise RlsacError(f"MLflow tracking at {uri} failed ({e.__class__.__name__}: {' '.join(str(e).split())[:200]}); "
                         "use --no-tracking or set MLFLOW_TRACKING_URI") from None
    run = Run(mlflow)
    run.run_id = active.info.run_id
    status = "FAILED"
    if old is not None:  # the earlier attempt's end, kept as "interrupted"; the error tags are for this one
        was = old.data.tags.get("error") or (f"process ended while {old.info.status} (killed)"
                                             if old.info.status == "RUNNING" else old.info.status)
        with contextlib.suppress(Exception):
            run.tags({"interrupted": was[:5000]})
            for key in ("error", "error_type"):
                if key in old.data.tags:
                    mlflow.delete_tag(key)
    try:
        if params:
            if old is not None:
                have = old.data.params
                flat = {k: (str(v)[:500] if v is not None else "None") for k, v in flatten(params).items()}
                changed = {k: v for k, v in flat.items() if k in have and have[k] != v}
                run.params({k: v for k, v in flat.items() if k not in have})
                if changed:
                    run.tags({f"changed_on_resume.{k}": f"{have[k]} -> {v}"[:5000] for k, v in changed.items()})
            else:
                run.params(params)
        if tags:
            run.tags(tags)
        yield run
        status = "FINISHED"
    except BaseException as e:
        from rlsac.signals import interrupted_in

        signalled = interrupted_in(e)  # a signal raised inside a store write arrives wrapped by MLflow
        if isinstance(e, KeyboardInterrupt) or signalled is not None:
            status = "KILLED"
        with contextlib.suppress(Exception):
            run.tags(_error_tags(signalled or e))
        if signalled is not None and signalled is not e:
            raise signalled from None
        raise
    finally:
        _end_run(status)


def _end_run(status: str) -> None:
    """``mlflow.end_run``; a signal landing in its write (an MlflowException around ``Interrupted``) ends the run
    KILLED on a second try and raises the interruption itself."""
    import mlflow

    from rlsac.signals import interrupted_in

    try:
        mlflow.end_run(status=status)
    except Exception as e:
        signalled = interrupted_in(e)
        if signalled is None:
            raise
        with contextlib.suppress(Exception):
            mlflow.end_run(status="KILLED")
        raise signalled from None


def data_label(path: str | os.PathLike) -> str:
    """A data file as run names show it: its path without ``data/`` and the extension (``folds/hard/entry/test``):
    the fold and regime are in the name, so that one command on two folds gives two names (issue #63 item 5)."""
    p = Path(path)
    if p.is_absolute():
        with contextlib.suppress(ValueError):
            p = p.relative_to(Path.cwd())
    parts = p.with_suffix("").parts
    return "/".join(parts[1:] if parts[:1] == ("data",) and len(parts) > 1 else parts)


# The UI's "workflow" (GenAI or machine learning) decides whether an experiment opens on its traces or its runs. MLflow
# 3.17 takes it from the page's `workflowType` parameter, else from what the browser last picked (GenAI at first): it
# no longer reads the experiment's `mlflow.experimentKind` tag (rlsac still sets it, for the versions that do). So
# `rlsac ui` prints, per experiment, the link that opens its runs table with the mAA columns (VIEW_STATE).
RUNS_PAGE = "/#/experiments/{id}/runs?workflowType=machine_learning&viewStateShareKey=" + VIEW_KEY


def runs_links(uri: str, base: str) -> list[dict[str, Any]]:
    """[{"name", "id", "runs", "url"}] of every experiment of the store at ``uri`` that holds runs, ``url`` its runs
    table on the UI served at ``base`` (``http://host:port``)."""
    store = client(uri)
    out = []
    for e in store.search_experiments():
        n = len(store.search_runs([e.experiment_id], max_results=1000))
        if n:
            out.append({"name": e.name, "id": e.experiment_id, "runs": n,
                        "url": base + RUNS_PAGE.format(id=e.experiment_id)})
    return out


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def mlflow_server(store_uri: str, work: str | os.PathLike, extra: tuple[str, ...] = (), port: int | None = None,
                  timeout_s: float = 120.0) -> Iterator[str]:
    """``mlflow server`` (this interpreter's) on ``store_uri``, artifacts and its log in ``work``, on 127.0.0.1;
    yields its http URI once /health answers, and stops it and the workers it spawned on exit. RuntimeError with
    the end of its log where it exits or does not answer within ``timeout_s``. For the tests and benchmarks that
    need a tracking server (docs/reproducing.md starts one by hand for a cluster)."""
    import shutil
    import signal
    import subprocess
    import sys
    import time
    import urllib.request

    exe = Path(sys.executable).parent / "mlflow"
    exe = str(exe) if exe.is_file() else shutil.which("mlflow")
    if exe is None:
        raise RuntimeError("no mlflow executable beside this interpreter or on PATH")
    work = Path(work)
    port = port or free_port()
    base, log = f"http://127.0.0.1:{port}", work / "mlflow-server.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([exe, "server", "--backend-store-uri", store_uri, "--artifacts-destination",
                                 str(work / "mlflow-artifacts"), "--host", "127.0.0.1", "--port", str(port),
                                 "--workers", "1", *extra],
                                stdout=out, stderr=subprocess.STDOUT, cwd=work, start_new_session=True)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            if proc.poll() is not None or time.monotonic() > deadline:
                why = f"exited with {proc.returncode}" if proc.returncode is not None else f"no answer in {timeout_s} s"
                raise RuntimeError(f"mlflow server {why}:\n{log.read_text()[-3000:]}")
            with contextlib.suppress(OSError):
                with urllib.request.urlopen(base + "/health", timeout=2) as r:
                    if r.status == 200:
                        break
            time.sleep(0.3)
        yield base
    finally:
        for sig in (signal.SIGTERM, signal.SIGKILL):  # the server and the workers it spawned (its own session)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=10)
                break
