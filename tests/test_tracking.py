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


def test_run_names_carry_the_data_folders_and_rlsac_ui_links_each_runs_table(workdir):
    """Issue #63 item 5: the same command on two folds gave two runs of one name (`evaluate
    fundamental_rlsac_rlsac_test_i1000_s0`, `prepare-test`): names carry the data file's folders (fold, regime).
    MLflow 3.17's UI picks its GenAI or runs page by the page's `workflowType` (no longer by the experiment's tag):
    `rlsac ui` prints each experiment's runs-table link."""
    import mlflow
    from click.testing import CliRunner

    from rlsac.cli import cli

    run = CliRunner().invoke
    for fold in ("castle", "entry"):
        out = f"data/folds/hard/{fold}/test.h5"
        assert run(cli, ["synth-lines", "--n-instances", "3", "--out", out, "--params", ""]).exit_code == 0
        r = run(cli, ["evaluate", "--task", "line", "--method", "ransac", "--data", out, "--iterations", "5",
                      "--out-dir", f"ev/{fold}", "--params", ""])
        assert r.exit_code == 0, r.output
    client = mlflow.MlflowClient(f"sqlite:///{workdir / 'mlflow.db'}")
    lines = client.get_experiment_by_name("lines")
    names = sorted(r.info.run_name for r in client.search_runs([lines.experiment_id]))
    assert [n for n in names if n.startswith("evaluate")] == ["evaluate ransac folds/hard/castle/test i5 s0",
                                                              "evaluate ransac folds/hard/entry/test i5 s0"], names
    assert [n for n in names if n.startswith("synth")] == ["synth-lines folds/hard/castle/test o0.5 s0",
                                                           "synth-lines folds/hard/entry/test o0.5 s0"], names

    r = run(cli, ["ui", "--port", "5055", "--links-only"])
    assert r.exit_code == 0, r.output
    assert r.output.split() == ["lines", "4", "runs", f"http://127.0.0.1:5055/#/experiments/{lines.experiment_id}"
                                "/runs?workflowType=machine_learning&viewStateShareKey=rlsac"], r.output
    (workdir / "mlflow.db").unlink()
    gone = run(cli, ["ui", "--links-only"])
    assert gone.exit_code == 2 and gone.output.startswith("error: ") and "no tracking store here" in gone.output


def test_a_run_lands_in_its_experiment_when_another_process_created_it_at_once(tmp_path, monkeypatch):
    """Two stages creating one experiment at once: MLflow's set_experiment then returns it without making it active
    (its RESOURCE_ALREADY_EXISTS branch), and the run went to MLFLOW_EXPERIMENT_ID of the environment (the pipeline
    driver's experiment, inherited by its stages)."""
    import mlflow

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    client = mlflow.MlflowClient(uri)
    driver = client.create_experiment("pipeline")
    client.create_experiment("lines")  # made by the other stage a moment before
    monkeypatch.setenv("MLFLOW_EXPERIMENT_ID", driver)
    monkeypatch.setattr(mlflow.tracking.fluent, "_active_experiment_id", None)
    monkeypatch.setattr(mlflow, "set_experiment", lambda name: client.get_experiment_by_name(name))  # the race's
    with start_run("lines", "stage") as run:
        pass
    assert client.get_run(run.run_id).info.experiment_id == client.get_experiment_by_name("lines").experiment_id


def test_reading_a_store_waits_for_the_lock_another_process_migrates_under(tmp_path, monkeypatch):
    """A fresh mlflow.db exists from the moment a first process starts MLflow's migrations (under the store lock);
    a second command's check_store read it at once, unlocked, and ran the migrations alongside: the store was
    left with "_alembic_tmp_experiments already exists" (every stage of a two-worker verify failed)."""
    import threading

    from filelock import FileLock

    from rlsac.tracking import check_store

    db = tmp_path / "fresh.db"
    db.touch()  # what the first process's migrations have made so far
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{db}")
    monkeypatch.chdir(tmp_path)
    holder = FileLock(str(db) + ".lock")
    holder.acquire()
    reader = threading.Thread(target=check_store, args=(True, "lines"), daemon=True)
    reader.start()
    reader.join(timeout=3)
    waited = reader.is_alive()
    read_meanwhile = db.stat().st_size
    holder.release()
    reader.join(timeout=120)
    assert waited and read_meanwhile == 0, "check_store opened the store while another process held its lock"
    assert not reader.is_alive()
