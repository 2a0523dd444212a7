"""The MLflow UI/server sees what the commands log: experiments, params, metrics, tags and artefacts.

A tiny pipeline (synth-lines, evaluate --method ransac with ablation-style tags) logs into a sqlite
store in a tmp dir; ``mlflow server`` is started on that store on a free local port and queried
through its REST API. The server is always stopped (its whole process group) at the end.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from rlsac import commands
from rlsac.evaluate import evaluate

START_TIMEOUT_S = 60


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _mlflow_exe() -> str | None:
    here = Path(sys.executable).parent / "mlflow"
    return str(here) if here.is_file() else shutil.which("mlflow")


def _get(base: str, path: str) -> dict:
    with urllib.request.urlopen(base + path, timeout=10) as r:
        return json.loads(r.read().decode())


def _post(base: str, path: str, body: dict) -> dict:
    req = urllib.request.Request(base + path, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read().decode())


def _wait_up(base: str, proc: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"mlflow server exited with {proc.returncode}:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(base + "/health", timeout=2) as r:
                if r.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        time.sleep(0.3)
    pytest.fail(f"mlflow server not up after {START_TIMEOUT_S} s:\n{log.read_text()[-3000:]}")


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)  # the server and the workers it spawned (own session)
        proc.wait(timeout=10)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=10)


def test_server_shows_logged_runs(workdir):
    exe = _mlflow_exe()
    if exe is None:
        pytest.skip("mlflow executable not found")
    s = commands.synth_lines({"outlier_rate": 0.5, "n_instances": 16, "seed": 3, "out": "data/t.h5"}, track=True,
                             params_path=None)
    e = evaluate({"task": "line", "method": "ransac", "data": s["path"], "iterations": 20, "device": "cpu",
                  "out_dir": "reports/eval/t", "tags": {"ablation": "smoke", "variant": "ransac"}}, track=True)

    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    log = workdir / "server.log"
    db = os.environ["MLFLOW_TRACKING_URI"]
    with open(log, "w") as out:
        proc = subprocess.Popen(
            [exe, "server", "--backend-store-uri", db, "--artifacts-destination", str(workdir / "art"),
             "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
            stdout=out, stderr=subprocess.STDOUT, cwd=workdir, start_new_session=True)
    try:
        _wait_up(base, proc, log)
        exps = _post(base, "/api/2.0/mlflow/experiments/search", {"max_results": 100})["experiments"]
        by_name = {x["name"]: x["experiment_id"] for x in exps}
        assert "lines" in by_name, by_name

        runs = _post(base, "/api/2.0/mlflow/runs/search",
                     {"experiment_ids": [by_name["lines"]], "max_results": 100})["runs"]
        assert len(runs) == 2
        ev = [r for r in runs if r["info"]["run_id"] == e["run_id"]]
        assert len(ev) == 1
        run = ev[0]
        assert run["info"]["status"] == "FINISHED"
        params = {p["key"]: p["value"] for p in run["data"]["params"]}
        assert params["method"] == "ransac" and params["iterations"] == "20" and params["task"] == "line"
        metrics = {m["key"]: m["value"] for m in run["data"]["metrics"]}
        assert metrics["mAA"] == pytest.approx(e["mAA"])
        assert "median_deg" in metrics
        tags = {t["key"]: t["value"] for t in run["data"]["tags"]}
        assert tags["command"] == "evaluate" and tags["ablation"] == "smoke" and tags["variant"] == "ransac"

        # the same run found by a tag filter, as the UI's search box does
        hits = _post(base, "/api/2.0/mlflow/runs/search",
                     {"experiment_ids": [by_name["lines"]], "filter": "tags.ablation = 'smoke'"})["runs"]
        assert [r["info"]["run_id"] for r in hits] == [e["run_id"]]

        files = _get(base, f"/api/2.0/mlflow/artifacts/list?run_id={e['run_id']}").get("files", [])
        names = {f["path"] for f in files}
        assert {"errors.csv", "summary.json"} <= names, names

        synth = [r for r in runs if r["info"]["run_id"] == s["run_id"]][0]
        sp = {p["key"]: p["value"] for p in synth["data"]["params"]}
        assert sp["n_instances"] == "16" and sp["seed"] == "3"
    finally:
        _stop(proc)
    assert proc.poll() is not None
