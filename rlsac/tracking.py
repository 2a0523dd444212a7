"""One MLflow helper for every command: experiment per task, flattened params, FAILED on error.

The tracking URI defaults to ``sqlite:///mlflow.db`` in the working directory; MLFLOW_TRACKING_URI
overrides it.
"""

from __future__ import annotations

import contextlib
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

    Two commands started together on a fresh ``mlflow.db`` (e.g. two ``dvc repro`` lanes) both run
    MLflow's schema migrations and one fails with "table ... already exists"; creating the same
    experiment twice races the same way. A lock file next to the database orders them.
    """
    prefix = "sqlite:///"
    if not uri.startswith(prefix):
        return contextlib.nullcontext()
    from filelock import FileLock

    return FileLock(uri[len(prefix):] + ".lock", timeout=600)


@contextlib.contextmanager
def start_run(experiment: str, run_name: str, params: dict[str, Any] | None = None,
              tags: dict[str, str] | None = None, enabled: bool = True) -> Iterator[Run]:
    """Open an MLflow run in ``experiment``; the run ends FINISHED, or FAILED if the block raises."""
    if not enabled:
        yield Run(None)
        return
    _quiet()
    import mlflow

    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    mlflow.set_tracking_uri(uri)
    with _store_lock(uri):
        mlflow.set_experiment(experiment)
    active = mlflow.start_run(run_name=run_name)
    run = Run(mlflow)
    run.run_id = active.info.run_id
    status = "FAILED"
    try:
        if params:
            run.params(params)
        if tags:
            run.tags(tags)
        yield run
        status = "FINISHED"
    finally:
        mlflow.end_run(status=status)
