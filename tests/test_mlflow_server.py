"""The MLflow UI/server sees what the commands log: experiments, params, metrics, tags and artefacts.

A tiny pipeline (synth-lines, evaluate --method ransac with ablation-style tags) logs into a sqlite
store in a tmp dir; ``mlflow server`` is started on that store on a free local port and queried
through its REST API. The server is always stopped (its whole process group) at the end.
"""

from __future__ import annotations

import json
import os
import urllib.request

import pytest

from rlsac import commands
from rlsac.evaluation.evaluate import evaluate
from rlsac.tracking import mlflow_server


def _get(base: str, path: str) -> dict:
    with urllib.request.urlopen(base + path, timeout=10) as r:
        return json.loads(r.read().decode())


def _post(base: str, path: str, body: dict) -> dict:
    req = urllib.request.Request(base + path, data=json.dumps(body).encode(), method="POST",
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.loads(r.read().decode())


def test_server_shows_logged_runs(workdir):
    s = commands.synth_lines({"outlier_rate": 0.5, "n_instances": 16, "seed": 3, "out": "data/t.h5"}, track=True,
                             params_path=None)
    e = evaluate({"task": "line", "method": "ransac", "data": s["path"], "iterations": 20, "device": "cpu",
                  "out_dir": "reports/eval/t", "tags": {"ablation": "smoke", "variant": "ransac"}}, track=True)

    with mlflow_server(os.environ["MLFLOW_TRACKING_URI"], workdir) as base:  # stopped (its process group) on exit
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
    with pytest.raises(OSError):  # stopped: nothing answers on its port
        urllib.request.urlopen(base + "/health", timeout=2)
