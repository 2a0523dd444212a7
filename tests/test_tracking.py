"""The MLflow helper: run status, and several processes opening one fresh sqlite store at once."""

import json
import multiprocessing as mp

import pytest

from rlsac.tracking import start_run


def _log_one(uri: str, i: int, barrier) -> None:
    import os

    import mlflow  # noqa: F401  (imported before the barrier so that the workers start together)

    os.environ["MLFLOW_TRACKING_URI"] = uri
    barrier.wait()
    with start_run("lines", f"worker {i}", params={"i": i}) as run:
        run.metrics({"value": float(i)})


def _runs(uri: str):
    import mlflow

    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name("lines")
    return client.search_runs([exp.experiment_id])


def test_failed_block_marks_run_failed(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'm.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    with pytest.raises(RuntimeError):
        with start_run("lines", "boom"):
            raise RuntimeError("x")
    with start_run("lines", "ok", params={"a": {"b": 1}}):
        pass
    runs = {r.info.run_name: r for r in _runs(uri)}
    assert {k: r.info.status for k, r in runs.items()} == {"boom": "FAILED", "ok": "FINISHED"}
    assert runs["ok"].data.params == {"a.b": "1"}


def test_parallel_processes_on_a_fresh_store(tmp_path):
    # Without the lock, concurrent schema migrations fail with "table ... already exists".
    uri = f"sqlite:///{tmp_path / 'fresh.db'}"
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(3)
    procs = [ctx.Process(target=_log_one, args=(uri, i, barrier)) for i in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=300)
    assert [p.exitcode for p in procs] == [0, 0, 0]
    runs = _runs(uri)
    assert sorted(r.data.metrics["value"] for r in runs) == [0.0, 1.0, 2.0]
    assert all(r.info.status == "FINISHED" for r in runs)


def test_experiments_open_on_the_runs_table(tmp_path, monkeypatch):
    """Issue #47: MLflow 3 opens an untagged experiment on its GenAI overview; ours are tagged as model training
    (the UI's experiment kind), new ones and ones made before the tag alike, and the tag is set once."""
    import mlflow

    from rlsac.tracking import EXPERIMENT_KIND

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.chdir(tmp_path)
    client = mlflow.MlflowClient(uri)
    old = client.create_experiment("lines")  # an experiment from before the tag
    with start_run("lines", "r1") as run:
        run.metrics({"mAA": 0.5})
    with start_run("fundamental", "r2"):
        pass
    for name in ("lines", "fundamental"):
        tags = client.get_experiment_by_name(name).tags
        assert tags.get(EXPERIMENT_KIND[0]) == "custom_model_development"
        # the runs table's shared view (?viewStateShareKey=rlsac): the main metrics as columns, sorted by mAA
        view = json.loads(tags["mlflow.sharedViewState.rlsac"])
        assert view["selectedColumns"][:3] == ["metrics.`mAA`", "metrics.`mAA_R`", "metrics.`mAA_t`"]
        assert view["orderByKey"] == "metrics.`mAA`" and view["orderByAsc"] is False
    assert client.get_experiment_by_name("lines").experiment_id == old
