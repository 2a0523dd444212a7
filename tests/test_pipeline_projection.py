"""benchmarks/pipeline_projection.py (issue #30, item 4) on a toy DAG whose answers are known by hand."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("pipeline_projection", ROOT / "benchmarks" / "pipeline_projection.py")
proj = importlib.util.module_from_spec(spec)
spec.loader.exec_module(proj)

# a (3 s) -> b (2 s), a -> c (1 s), d (5 s) on its own, e (1 s) after b and c
DEPS = {"a": [], "b": ["a"], "c": ["a"], "d": [], "e": ["b", "c"]}
TIMES = {"a": 3.0, "b": 2.0, "c": 1.0, "d": 5.0, "e": 1.0}


def test_total_critical_path_and_list_schedule():
    p = proj.projection(DEPS, TIMES, [1, 2, 3, 8])
    assert p["total_s"] == 12.0
    assert p["critical_path_s"] == 6.0 and p["critical_path"] == ["a", "b", "e"]
    # 2 workers, longest path to the end first: a, d at 0; b at 3 (a done); c at 5 (b, d done); e at 6 -> 7.
    # 3 workers: a, d at 0; b, c at 3; e at 5 (b done) -> 6 = the critical path
    assert p["wall_s"] == {1: 12.0, 2: 7.0, 3: 6.0, 8: 6.0}


def test_times_by_pattern_and_from_a_pipeline_artifact(tmp_path, capsys):
    assert proj.stage_times({"x@1": [], "x@2": [], "y": []}, {"x@2": 5, "x@*": 2, "*": 1}) == \
        {"x@1": 2.0, "x@2": 5.0, "y": 1.0}
    with pytest.raises(SystemExit, match="no time for 1 stage"):
        proj.stage_times({"z": []}, {"x@*": 2})
    artifact = tmp_path / "pipeline.json"  # what `rlsac pipeline` logs: skipped stages have no time
    artifact.write_text(json.dumps({"deps": DEPS, "results": {
        **{a: {"status": "done", "seconds": t} for a, t in TIMES.items()}, "f": {"status": "skipped",
                                                                             "seconds": None}}}))
    proj.main(["--times", str(artifact), "--workers", "2", "--json", "--overhead", "0"])
    out = json.loads(capsys.readouterr().out)
    assert out["n_stages"] == 5 and out["wall_s"] == {"2": 7.0} and out["critical_path_s"] == 6.0


def test_per_stage_overhead_and_runner_work_taken_off(tmp_path, capsys):
    """--overhead adds the runner's own seconds to every stage (by default the measured DIRECT_OVERHEAD_S); --less
    takes off the runner work the times already hold, floored at 0."""
    times = tmp_path / "times.json"
    times.write_text(json.dumps(TIMES))

    def walls(*flags):
        proj.main(["--repo", str(tmp_path), "--times", str(times), "--workers", "1,2", "--json", *flags])
        return json.loads(capsys.readouterr().out)

    import unittest.mock as mock

    with mock.patch.object(proj, "load_dag", return_value=DEPS):
        # +1 s a stage: a 4, b 3, c 2, d 6, e 2; 2 workers: a, d at 0; b at 4; c at 6; e at 8 -> 10
        assert walls("--overhead", "1")["wall_s"] == {"1": 17.0, "2": 10.0}
        # -1 s a stage: a 2, b 1, c 0, d 4, e 0; 2 workers: a, d at 0; b at 2, c and e at 3; d ends at 4
        assert walls("--overhead", "0", "--less", "1")["wall_s"] == {"1": 7.0, "2": 4.0}
        default = walls()
        assert default["overhead_s"] == proj.DIRECT_OVERHEAD_S
        assert default["wall_s"]["1"] == pytest.approx(12.0 + 5 * proj.DIRECT_OVERHEAD_S)
        for bad, why in ((["--overhead", "x"], "neither a number"), (["--overhead", "-1"], "at least 0"),
                         (["--less", "-1"], "at least 0")):
            with pytest.raises(SystemExit, match=why):
                walls(*bad)


def test_only_timed_leaves_out_stages_without_a_time():
    deps, left = proj.timed_only({"x@1": [], "x@2": ["x@1", "new@1"], "new@1": [], "new@2": ["x@1"]}, {"x@*": 2})
    assert deps == {"x@1": [], "x@2": ["x@1"]} and left == {"new": 2}


def test_longest_path_first():
    """The ready stage with the longest path to the end starts first, at the start and when a stage finishes."""
    at_start = {"x": [], "y": [], "z": [], "w": ["z"]}  # 2 workers: z, x at 0; y, w at 1 -> 4 (x, y first: 5)
    assert proj.list_schedule(at_start, {"x": 1, "y": 1, "z": 1, "w": 3}, 2) == 4.0
    later = {"a": [], "p": ["a"], "p2": ["a"], "q": ["a"], "r": ["q"]}  # q, p at 1; r, p2 at 2 -> 5 (p, p2 first: 6)
    assert proj.list_schedule(later, {"a": 1, "p": 1, "p2": 1, "q": 1, "r": 3}, 2) == 5.0


def test_times_from_the_pipeline_runs_of_an_mlflow_store(tmp_path, monkeypatch, capsys):
    """--from-mlflow: each stage's time as the pipeline runs logged it (stage_s/<address>, the latest run's wins, an
    interrupted run's count), the unmeasured stages at their group's mean, and the cost table per group."""
    import mlflow

    uri = f"sqlite:///{tmp_path / 'm.db'}"
    deps = {"t@1": [], "t@2": [], "t@3": [], "e@1": ["t@1"], "e@2": ["t@2"], "e@3": ["t@3"], "tables": ["e@1"]}
    client = mlflow.MlflowClient(uri)
    exp = client.create_experiment("pipeline", artifact_location=str(tmp_path / "art"))
    first = {"stage_s/t_1": 10.0, "stage_s/e_1": 3.0}  # then a later run times t@1 again
    later = {"stage_s/t_1": 12.0, "stage_s/t_2": 14.0, "stage_s/e_2": 5.0, "stage_s/tables": 1.0}
    other = {"stage_s/t_1": 99.0}  # a run of another repository (the quick profile's stages have the same names)
    for start, metrics, repo in ((1000, first, tmp_path), (2000, later, tmp_path), (3000, other, tmp_path / "q")):
        run = client.create_run(exp, start_time=start)
        client.log_param(run.info.run_id, "repo", str(repo))
        for k, v in metrics.items():
            client.log_metric(run.info.run_id, k, v)
        client.set_terminated(run.info.run_id, "KILLED")
    measured = proj.mlflow_times(uri, deps, tmp_path)
    assert proj.mlflow_times(uri, deps)["t@1"] == 99.0  # without a repository: every run, the latest wins
    assert measured == {"t@1": 12.0, "t@2": 14.0, "e@1": 3.0, "e@2": 5.0, "tables": 1.0}
    full = proj.fill_by_group(deps, measured)
    assert full["t@3"] == 13.0 and full["e@3"] == 4.0
    with pytest.raises(SystemExit, match="no measured stage in 1 group"):
        proj.fill_by_group({**deps, "x@1": []}, measured)
    assert proj.fill_by_group({**deps, "x@1": []}, measured, {"x@*": 7.0})["x@1"] == 7.0  # a group run earlier
    table = proj.group_table(deps, measured)
    assert "| `t` | 3 | 2 | 26 | 13.0 | 12.0-14.0 |" in table and "| `tables` | 1 | 1 | 1 | 1.0 | 1.0-1.0 |" in table
    monkeypatch.setattr(proj, "load_dag", lambda repo: deps)
    proj.main(["--from-mlflow", uri, "--workers", "1", "--groups", "--repo", str(tmp_path)])
    out = capsys.readouterr().out
    assert "measured 5 of 7 stages" in out and "total stage time 52 s" in out and "| `e` | 3 | 2 | 8 |" in out


def test_times_from_stage_logs(tmp_path, monkeypatch, capsys):
    """--from-logs: a stage without an MLflow time takes its log's span (birth to last write); a span far above its
    group's (a log a later run rewrote) is left out; MLflow's time wins where both exist."""
    import os
    import subprocess

    spans = {"t@1": 10, "t@2": 12, "t@3": 200, "e@1": 4}  # t@3: over LOG_OUTLIER x the median 12
    for a, span in spans.items():
        f = tmp_path / f"{a}.log"
        f.write_text("dvc output\n")
        born = int(subprocess.run(["stat", "-c", "%W", str(f)], capture_output=True, text=True).stdout)
        if born <= 0:
            pytest.skip("this file system reports no birth time")
        os.utime(f, (born + span, born + span))
    deps = {"t@1": [], "t@2": [], "t@3": [], "e@1": ["t@1"], "x": []}
    assert proj.log_times(tmp_path, deps) == {"t@1": 10.0, "t@2": 12.0, "e@1": 4.0}
    monkeypatch.setattr(proj, "load_dag", lambda repo: deps)
    monkeypatch.setattr(proj, "mlflow_times", lambda uri, d, repo: {"t@2": 13.0, "x": 1.0})
    proj.main(["--from-mlflow", "u", "--from-logs", str(tmp_path), "--workers", "1", "--groups"])
    out = capsys.readouterr().out
    assert "measured 4 of 5 stages" in out and "| `t` | 3 | 2 | 23 | 11.5 |" in out  # t@3 at the group mean
    with pytest.raises(SystemExit, match="give both"):
        proj.main(["--from-logs", str(tmp_path)])
