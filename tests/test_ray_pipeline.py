"""``rlsac pipeline`` (issue #30): a toy DVC pipeline in a temporary git + DVC repository, run as Ray tasks on a
local 2-CPU Ray cluster (one ``ray.init`` for the module, shut down at the end).

The toy pipeline: ``a`` -> ``b``, ``a`` -> ``c``, and ``d`` on its own; each command is a tiny ``python -c`` write.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import ray
import yaml
from click.testing import CliRunner

from rlsac.cli import cli

PY = "python"  # the stages' interpreter: the pipeline puts this one's bin folder first on PATH


def _write(name: str, text: str, needs: tuple[str, ...] = ()) -> str:
    reads = "".join(f"+open('{n}').read()" for n in needs)
    return f"{PY} -c \"open('{name}','w').write('{text}'{reads})\""


TOY = {  # a takes a second, so a dependent started too early would find a.txt missing
    "a": {"cmd": _write("a.txt", "a").replace("-c \"", "-c \"import time; time.sleep(1); "), "outs": ["a.txt"]},
    "b": {"cmd": _write("b.txt", "b", ("a.txt",)), "deps": ["a.txt"], "outs": ["b.txt"]},
    "c": {"cmd": _write("c.txt", "c", ("a.txt",)), "deps": ["a.txt"], "outs": ["c.txt"]},
    "d": {"cmd": _write("d.txt", "d"), "outs": ["d.txt"]},
}


def _env() -> dict:
    bindir = str(Path(sys.executable).parent)
    return {**os.environ, "PATH": bindir + os.pathsep + os.environ.get("PATH", ""), "OMP_NUM_THREADS": "1"}


def make_repo(path: Path, stages: dict, files: dict[str, str] | None = None) -> Path:
    path.mkdir(parents=True)
    subprocess.run(["git", "init", "-q"], cwd=path, check=True)
    subprocess.run([sys.executable, "-m", "dvc", "init", "-q"], cwd=path, check=True, env=_env())
    (path / "dvc.yaml").write_text(yaml.safe_dump({"stages": stages}, sort_keys=False))
    for name, text in (files or {}).items():
        (path / name).write_text(text)
    return path


def dvc(path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvc", *args], cwd=path, env=_env(), capture_output=True,
                          text=True)


def run_pipeline(*args: str):
    return CliRunner().invoke(cli, ["pipeline", *args], catch_exceptions=False)


def summary(output: str) -> list[str]:
    """The summary's lines (Ray may print its own report of a dead worker before it)."""
    lines = output.splitlines()
    starts = [i for i, ln in enumerate(lines) if ln.startswith("pipeline")]
    assert starts, output
    return lines[starts[-1]:]


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    """One local Ray cluster of 2 CPUs for the module: the pipeline uses an initialised Ray as it is."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_two_workers_match_sequential_dvc_repro(tmp_path):
    par = make_repo(tmp_path / "par", TOY)
    seq = make_repo(tmp_path / "seq", TOY)
    assert dvc(seq, "repro").returncode == 0

    r = run_pipeline("--repo", str(par), "--workers", "2", "--no-tracking")
    assert r.exit_code == 0, r.output
    assert summary(r.output)[0].startswith("pipeline: 4 done, 0 skipped, 0 failed, 0 not run of 4 stages"), r.output
    for name in ("a.txt", "b.txt", "c.txt", "d.txt"):
        assert (par / name).read_bytes() == (seq / name).read_bytes(), name
    # the same record; a stage new to dvc.lock is appended when it finishes, so compare entries, not line order
    assert yaml.safe_load((par / "dvc.lock").read_text()) == yaml.safe_load((seq / "dvc.lock").read_text())
    assert json.loads(dvc(par, "status", "--json").stdout) == {}

    again = run_pipeline("--repo", str(par), "--no-tracking")  # nothing out of date: nothing runs
    assert again.exit_code == 0, again.output
    assert summary(again.output)[0].startswith("pipeline: 0 done, 4 skipped"), again.output

    # a changed upstream output re-runs it and everything downstream of it, not its independent sibling
    (par / "dvc.yaml").write_text((par / "dvc.yaml").read_text().replace("'a'", "'A'"))
    plan = run_pipeline("--repo", str(par), "--dry-run", "--no-tracking")
    assert plan.exit_code == 0 and "to run   a, b, c" in plan.output, plan.output
    named = run_pipeline("b", "--repo", str(par), "--no-tracking")  # b and what it needs: a, not c
    assert named.exit_code == 0, named.output
    assert "done     a, b" in named.output and (par / "b.txt").read_text() == "bA"
    assert (par / "c.txt").read_text() == "ca"


def test_the_dry_run_plans_after_the_missing_data(tmp_path):
    """A clean clone lacks the git-ignored outputs of its data stages: the dry run says they only re-make missing
    outputs, that what needs only them is up to date once they are back, and what changed runs, per stage group."""
    repo = make_repo(tmp_path / "repo", TOY)
    assert dvc(repo, "repro").returncode == 0
    (repo / "a.txt").unlink()  # a's output, as a clean clone lacks it
    (repo / "dvc.yaml").write_text((repo / "dvc.yaml").read_text().replace("'d'", "'D'"))  # d changed
    r = run_pipeline("--repo", str(repo), "--dry-run", "--no-tracking")
    assert r.exit_code == 0, r.output
    lines = summary(r.output)
    assert lines[0] == ("pipeline (dry run): 2 to run, 2 up to date of 4 stages (2 of them once the re-made outputs "
                        "match dvc.lock)"), r.output
    assert lines[1] == "to run   a, d", r.output
    assert lines[2] == ("plan: 1 stages re-make missing outputs from unchanged inputs (a); after them 1 run, "
                        "by group:"), r.output
    assert [ln.split() for ln in lines[4:7]] == [["b", "0", "1"], ["c", "0", "1"], ["d", "1", "0"]], r.output
    assert lines[7].startswith("checked against dvc.lock by md5: "), r.output


def test_failed_stage_stops_dependents_only(tmp_path):
    stages = {**TOY,
              "c": {"cmd": f"{PY} -c \"import sys; print('working'); sys.exit('error: c broke here')\"",
                    "deps": ["a.txt"], "outs": ["c.txt"]},
              "e": {"cmd": _write("e.txt", "e", ("c.txt",)), "deps": ["c.txt"], "outs": ["e.txt"]}}
    repo = make_repo(tmp_path / "repo", stages)
    r = run_pipeline("--repo", str(repo), "--workers", "2", "--no-tracking")
    assert r.exit_code == 1, r.output
    lines = summary(r.output)
    assert lines[0].startswith("pipeline: 3 done, 0 skipped, 1 failed, 1 not run of 5 stages"), r.output
    assert "done     a, b, d" in lines
    assert any(ln.startswith("failed   c: error: c broke here (log ") for ln in lines), r.output
    assert "not run  e" in lines
    assert not any(ln.startswith("retried") for ln in lines), r.output  # a command's failure is not a lost worker
    assert (repo / "b.txt").exists() and (repo / "d.txt").exists() and not (repo / "e.txt").exists()


KILLER = """
import os, signal, sys, time
flag, pidfile = sys.argv[1], sys.argv[2]
if os.path.exists(flag):  # the second run: the stage works
    open('k.txt', 'w').write('k')
    sys.exit(0)
open(flag, 'w').close()
pids, pid = [os.getpid()], os.getppid()
while pid > 1:  # up to the Ray worker that runs this stage (its title starts with ray::): the shell, dvc
    cmdline = open(f'/proc/{pid}/cmdline', 'rb').read().split(b'\\0')[0].decode()
    if cmdline.startswith('ray::'):
        open(pidfile, 'w').write(' '.join(map(str, pids)))
        os.kill(pid, signal.SIGKILL)
        break
    pids.append(pid)
    pid = int(open(f'/proc/{pid}/stat').read().rsplit(')', 1)[1].split()[1])
time.sleep(120)  # mid-stage: the guard of the dead worker ends this process
open('k.txt', 'w').write('too late')
"""


def _exists(pid: int) -> bool:
    """As DVC's lock check sees it: a zombie not yet reaped still holds its lock entries."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_killed_worker_is_reported_and_a_second_run_completes(tmp_path):
    script = tmp_path / "killer.py"
    script.write_text(KILLER)
    flag, pidfile = tmp_path / "killed.flag", tmp_path / "stage.pid"
    stages = {"k": {"cmd": f"{PY} {script} {flag} {pidfile}", "outs": ["k.txt"]}, "d": TOY["d"]}
    repo = make_repo(tmp_path / "repo", stages)

    r = run_pipeline("--repo", str(repo), "--no-tracking", "--retries", "0")
    assert r.exit_code == 1, r.output
    assert "1 done, 0 skipped, 1 failed" in summary(r.output)[0], r.output
    failed = [ln for ln in summary(r.output) if ln.startswith("failed   k: ")]
    assert failed and "worker" in failed[0].lower(), r.output
    # the orphaned stage and its dvc process do not outlive their worker (the guard ends them)
    pids = [int(p) for p in pidfile.read_text().split()]
    assert pids  # the stage's command (and the shell, where it does not exec a lone command; dvc with --runner dvc)
    deadline = time.monotonic() + 60
    while any(map(_exists, pids)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(map(_exists, pids))
    assert not (repo / "k.txt").exists()

    again = run_pipeline("--repo", str(repo), "--no-tracking")
    assert again.exit_code == 0, again.output
    assert summary(again.output)[0].startswith("pipeline: 1 done, 1 skipped, 0 failed, 0 not run"), again.output
    assert (repo / "k.txt").read_text() == "k"
    assert json.loads(dvc(repo, "status", "--json").stdout) == {}


def test_a_killed_workers_stage_is_run_again_and_recorded_once(tmp_path, monkeypatch):
    """A stage whose Ray worker died is run again (--retries, default 2): the run completes, the summary says the
    stage was retried, its lock entry is written once and the lock is a serial `dvc repro`'s, byte for byte."""
    from rlsac.runners.dvc_stage import LockWriter

    script = tmp_path / "killer.py"
    script.write_text(KILLER)
    flag, pidfile = tmp_path / "killed.flag", tmp_path / "stage.pid"
    stages = {"k": {"cmd": f"{PY} {script} {flag} {pidfile}", "outs": ["k.txt"]}, "d": TOY["d"]}
    repo = make_repo(tmp_path / "repo", stages)
    recorded = []
    record = LockWriter.record
    monkeypatch.setattr(LockWriter, "record", lambda self, spec, result, *a, **k: (
        recorded.append(spec["name"]), record(self, spec, result, *a, **k))[1])

    r = run_pipeline("--repo", str(repo), "--no-tracking")
    assert r.exit_code == 0, r.output
    lines = summary(r.output)
    assert lines[0].startswith("pipeline: 2 done, 0 skipped, 0 failed, 0 not run of 2 stages"), r.output
    assert any(ln.startswith("retried  k (worker or node lost: ") for ln in lines), r.output
    assert sorted(recorded) == ["d", "k"]
    assert (repo / "k.txt").read_text() == "k"
    # the first attempt's orphaned command is ended by its guard, not left to write k.txt later
    pids = [int(p) for p in pidfile.read_text().split()]
    deadline = time.monotonic() + 60
    while any(map(_exists, pids)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not any(map(_exists, pids)) and (repo / "k.txt").read_text() == "k"
    seq = make_repo(tmp_path / "seq", stages)  # the flag is there: the stage works at once
    assert dvc(seq, "repro").returncode == 0
    assert (repo / "dvc.lock").read_bytes() == (seq / "dvc.lock").read_bytes()
    assert json.loads(dvc(repo, "status", "--json").stdout) == {}


class FakeRay:
    """Ray as ``schedule`` uses it, on ``cpus`` CPUs: tasks end in the order they started; ``get`` raises what
    ``fail`` holds for a stage (one exception per attempt), else returns the stage done. ``started``: the stages in
    the order their tasks were submitted; ``most``: the most tasks in flight at once."""

    def __init__(self, cpus: int, fail: dict | None = None):
        self.cpus, self.fail, self.started, self.flight, self.most = cpus, fail or {}, [], [], 0

    def cluster_resources(self) -> dict:
        return {"CPU": float(self.cpus)}

    def remote(self, fn):
        fake = self

        class Task:
            def options(self, **opts):
                return self

            def remote(self, root, address, *args):
                ref = (address, len(fake.started))
                fake.started.append(address)
                fake.flight.append(ref)
                fake.most = max(fake.most, len(fake.flight))
                return ref

        return Task()

    def wait(self, refs, num_returns, timeout):
        first = next(r for r in self.flight if r in refs)
        self.flight.remove(first)
        return [first], [r for r in refs if r != first]

    def get(self, ref):
        errors = self.fail.get(ref[0]) or []
        if errors:
            raise errors.pop(0)
        return {"stage": ref[0], "status": "done", "seconds": 0.0}


def _fake_plan(tmp_path, deps: dict[str, list[str]], seconds: dict[str, float] | None = None) -> dict:
    from rlsac.runners.priority import bottom_levels

    return {"root": tmp_path, "todo": sorted(deps), "deps": deps, "priority": bottom_levels(deps, seconds or {})}


OPTIONS = {"gpus_per_train": 0.0, "gpu_stages": "*train*", "retries": 2}


def test_the_ready_stage_with_the_longest_path_ahead_starts_first(tmp_path):
    from rlsac.runners.priority import bottom_levels
    from rlsac.runners.schedule import schedule

    # a chain z1 -> z2 -> z3 and five short stages on their own: their names come first, their paths are shorter
    deps = {"z1": [], "z2": ["z1"], "z3": ["z2"], **{f"a{i}": [] for i in range(5)}}
    assert bottom_levels(deps, {}) == {"z1": 3.0, "z2": 2.0, "z3": 1.0, **{f"a{i}": 1.0 for i in range(5)}}
    # expected seconds where known: one long stage outweighs the chain of three
    assert bottom_levels(deps, {"a3": 10.0})["a3"] == 10.0 and bottom_levels(deps, {"z2": 5.0})["z1"] == 7.0
    ray1 = FakeRay(cpus=1)
    schedule(_fake_plan(tmp_path, deps), OPTIONS, ray1)
    # (z3's path is as short as the others': ties go by address)
    assert ray1.started == ["z1", "z2", "a0", "a1", "a2", "a3", "a4", "z3"] and ray1.most == 1
    # two CPUs: the chain's head and one short stage; the chain goes on as soon as its stage ends
    ray2 = FakeRay(cpus=2)
    schedule(_fake_plan(tmp_path, deps, {"a3": 10.0}), OPTIONS, ray2)
    assert ray2.started[:2] == ["a3", "z1"] and ray2.most == 2


def test_expected_seconds_are_measured_else_the_groups_mean_else_one():
    from rlsac.runners.priority import expected_seconds

    measured = {"train@1": 100.0, "train@2": 300.0, "plot": 5.0}
    assert expected_seconds(["train@1", "train@3", "plot", "tables"], measured) == {
        "train@1": 100.0, "train@3": 200.0, "plot": 5.0, "tables": 1.0}


def test_the_order_takes_the_stage_times_earlier_runs_of_the_repository_logged(tmp_path, monkeypatch):
    """The bottom levels come from the `stage_s/<stage>` metrics of earlier pipeline runs of the same repository
    (another repository's runs are left out); with tracking off every stage counts 1."""
    import mlflow

    from rlsac.runners.priority import _priorities, stage_metric

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    client = mlflow.MlflowClient(uri)
    exp = client.create_experiment("pipeline")
    for repo, seconds in ((tmp_path / "repo", 50.0), (tmp_path / "other", 900.0)):
        run = client.create_run(exp)
        client.log_param(run.info.run_id, "repo", str(repo))
        client.log_metric(run.info.run_id, stage_metric("short@1"), seconds)
        client.set_terminated(run.info.run_id)
    plan = {"root": tmp_path / "repo", "todo": ["chain_1", "chain_2", "short@1", "short@2"],
            "deps": {"chain_1": [], "chain_2": ["chain_1"], "short@1": [], "short@2": []}}
    # short@2: its group's mean
    assert _priorities(plan, track=True) == {"chain_1": 2.0, "chain_2": 1.0, "short@1": 50.0, "short@2": 50.0}
    assert _priorities(plan, track=False) == {"chain_1": 2.0, "chain_2": 1.0, "short@1": 1.0, "short@2": 1.0}


def test_a_stage_prefers_the_node_of_its_parent_with_the_most_output_bytes():
    from rlsac.runners.schedule import _main_parent

    plan = {"deps": {"c": ["a", "b", "x"], "d": ["x"]}}
    placed = {"a": ("node-1", 10), "b": ("node-2", 500)}  # x ran in an earlier run (or not on a node): no preference
    assert _main_parent("c", plan, placed) == "node-2" and _main_parent("d", plan, placed) is None


class WorkerCrashedError(Exception):  # as Ray names a dead worker's error
    pass


def test_only_a_lost_worker_is_retried_not_a_failed_task(tmp_path):
    from rlsac.runners.schedule import schedule

    deps = {"k": [], "f": [], "after_k": ["k"]}
    fake = FakeRay(cpus=1, fail={"k": [WorkerCrashedError("died"), WorkerCrashedError("died")],
                                 "f": [RuntimeError("the task's body raised")]})
    results = schedule(_fake_plan(tmp_path, deps), OPTIONS, fake)
    assert fake.started.count("k") == 3 and fake.started.count("f") == 1
    assert results["k"]["status"] == "done" and len(results["k"]["retried"]) == 2
    assert results["after_k"]["status"] == "done"
    assert results["f"]["status"] == "failed" and "retried" not in results["f"]

    fake = FakeRay(cpus=1, fail={"k": [WorkerCrashedError("died"), WorkerCrashedError("died")]})
    results = schedule(_fake_plan(tmp_path, deps), {**OPTIONS, "retries": 1}, fake)
    assert fake.started.count("k") == 2 and results["k"]["status"] == "failed"
    assert results["k"]["error"] == "WorkerCrashedError: died (tried 2 times)"
    assert results["after_k"]["status"] == "not run"


def test_bad_input_is_one_error_line_before_any_work(tmp_path):
    repo = make_repo(tmp_path / "repo", TOY)
    (repo / "sub").mkdir()
    for args, message in ((["nosuch"], "no stage matches 'nosuch'"), (["--workers", "0"], "--workers"),
                          (["--repo", str(tmp_path)], "cannot read the DVC pipeline"),
                          (["--repo", str(repo / "sub")], "not a DVC repository's root"),
                          (["--gpus-per-train", "nan"], "must be a finite number >= 0"),
                          (["--retries", "-1"], "--retries"),
                          (["--gpus-per-train", "1", "--gpu-stages", "b"], "the Ray cluster has 0 GPUs (b would")):
        r = CliRunner().invoke(cli, ["pipeline", "--repo", str(repo), *args, "--no-tracking"])
        assert r.exit_code == 2, (args, r.output)
        assert r.output.startswith("error: ") and message in r.output and len(r.output.splitlines()) == 1, r.output
    assert not (repo / "a.txt").exists() and not (repo / "dvc.lock").exists()


# ------------------------------------------------------------------------------------- one MLflow server


def _host_status(base: str, host: str) -> int:
    """The HTTP status of an experiments search sent to ``base`` as if to ``host`` (its Host header)."""
    import urllib.error
    import urllib.request

    req = urllib.request.Request(base + "/api/2.0/mlflow/experiments/search", data=b'{"max_results": 1}',
                                 method="POST", headers={"Content-Type": "application/json", "Host": host})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code


def test_stages_log_to_one_mlflow_server(tmp_path, monkeypatch):
    from test_mlflow_server import _post

    from rlsac.tracking import free_port, mlflow_server

    port = free_port()
    allowed = ("--allowed-hosts", f"head-node:{port},127.0.0.1:*")  # docs/reproducing.md's
    with mlflow_server(f"sqlite:///{tmp_path / 'server.db'}", tmp_path, allowed, port=port) as base:
        # MLflow 3 answers only the Host headers it allows: the cluster's name for the server, not another one
        assert [_host_status(base, f"{name}:{port}") for name in ("head-node", "other-node")] == [200, 403]
        seeds = range(4)
        stages = {f"s{i}": {"cmd": f"rlsac synth-lines --n-instances 8 --seed {i} --out s{i}.h5",
                            "outs": [f"s{i}.h5"]} for i in seeds}
        repo = make_repo(tmp_path / "repo", stages)
        monkeypatch.setenv("MLFLOW_TRACKING_URI", base)  # the driver passes it on to every stage
        r = run_pipeline("--repo", str(repo))
        assert r.exit_code == 0, r.output
        assert summary(r.output)[0].startswith("pipeline: 4 done"), r.output

        exps = {x["name"]: x["experiment_id"]
                for x in _post(base, "/api/2.0/mlflow/experiments/search", {"max_results": 100})["experiments"]}
        runs = _post(base, "/api/2.0/mlflow/runs/search",
                     {"experiment_ids": list(exps.values()), "max_results": 100})["runs"]
        status = {r["info"]["run_name"]: r["info"]["status"] for r in runs}
        assert len(runs) == len(seeds) + 1, status  # every stage's run and the pipeline's
        assert set(status.values()) == {"FINISHED"}, status
        seeds_logged = sorted(int(p["value"]) for r in runs for p in r["data"].get("params", [])
                              if p["key"] == "seed")
        assert seeds_logged == list(seeds)
        pipe = [r for r in runs if r["info"]["experiment_id"] == exps["pipeline"]]
        where = {r["info"]["run_name"]: [k for k, v in exps.items() if v == r["info"]["experiment_id"]] for r in runs}
        assert len(pipe) == 1, where
        metrics = {m["key"]: m["value"] for m in pipe[0]["data"]["metrics"]}
        assert "n_done" in metrics, (where, sorted(metrics))
        assert metrics["n_done"] == len(seeds) and metrics["n_failed"] == 0
        assert {f"stage_s/s{i}" for i in seeds} <= set(metrics)
    shutil.rmtree(tmp_path / "mlflow-artifacts", ignore_errors=True)


def test_help_does_not_import_ray():
    """`rlsac --help` and `rlsac pipeline --help` stay fast: Ray and DVC are imported when the command runs."""
    code = ("import sys; from click.testing import CliRunner; from rlsac.cli import cli; "
            "r = [CliRunner().invoke(cli, a) for a in (['--help'], ['pipeline', '--help'])]; "
            "assert all(x.exit_code == 0 for x in r); "
            "print(sorted(m for m in ('ray', 'dvc.repo', 'mlflow') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def _wait_for_port(port: int, proc, timeout: float = 180.0) -> None:
    import socket

    end = time.monotonic() + timeout
    while time.monotonic() < end and proc.poll() is None:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return
        except OSError:
            time.sleep(0.5)
    raise AssertionError(f"ray head on port {port} did not come up")


def test_joins_a_ray_cluster_by_address(tmp_path):
    """`--address HOST:PORT` joins a cluster started with `ray start --head` (token authentication on: the
    module's local cluster made ~/.ray/auth_token) and runs the stages there."""
    from rlsac.tracking import free_port as _free_port

    port = _free_port()
    ray_exe = str(Path(sys.executable).parent / "ray")
    # as in a fresh shell: the module's ray.init set RAY_AUTH_MODE=token in this process's environment
    env = {k: v for k, v in _env().items() if k != "RAY_AUTH_MODE"}
    # a cluster needs a tracking server every node reaches (the stages here log nothing: none needs to answer)
    env["MLFLOW_TRACKING_URI"] = "http://127.0.0.1:9"
    log = open(tmp_path / "head.log", "w")
    head = subprocess.Popen([ray_exe, "start", "--head", "--port", str(port), "--num-cpus", "1",
                             "--include-dashboard", "false", "--block"], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True, env=env)
    try:
        repo = make_repo(tmp_path / "repo", {"a": TOY["a"], "b": TOY["b"]})
        _wait_for_port(port, head)  # the pipeline gives an address 10 s to answer (issue #49: no 400 s retries)
        r = subprocess.run([str(Path(sys.executable).parent / "rlsac"), "pipeline", "--repo", str(repo),
                            "--address", f"127.0.0.1:{port}", "--no-tracking"], capture_output=True, text=True,
                           env=env)
        assert r.returncode == 0, r.stdout + r.stderr[-3000:] + (tmp_path / "head.log").read_text()[-2000:]
        assert summary(r.stdout)[0].startswith("pipeline: 2 done, 0 skipped, 0 failed, 0 not run of 2 stages"), r.stdout
        assert "(1 CPUs)" in summary(r.stdout)[0]  # the cluster's size, not this machine's
        assert (repo / "b.txt").read_text() == "ba"
    finally:
        try:
            os.killpg(head.pid, signal.SIGTERM)
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()
        log.close()


def test_an_interrupted_run_keeps_the_times_of_the_stages_it_finished(tmp_path, monkeypatch):
    """Stage times go to MLflow as each stage ends (benchmarks/stage_times.py reads them): a pipeline interrupted
    after one stage (a long record stopped at the end of a sitting) still has that stage's time in its run."""
    import mlflow

    from rlsac.runners import pipeline as pipeline_module

    repo = make_repo(tmp_path / "repo", {"a": TOY["a"], "b": TOY["b"]})

    from rlsac.errors import Interrupted

    def interrupted(plan, o, ray_module, progress, results, running, stop):
        r = {"stage": plan["todo"][0], "status": "done", "seconds": 1.5}
        results[r["stage"]] = r
        progress(r)
        running["task-of-b"] = plan["todo"][1]  # in flight when the signal came (issue #49)
        raise Interrupted("interrupted by SIGTERM", 15)

    monkeypatch.setattr(pipeline_module, "schedule", interrupted)
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    r = CliRunner().invoke(cli, ["pipeline", "--repo", str(repo)])
    assert r.exit_code == 143, r.output  # the summary of what ran, then one error line, and the run KILLED
    assert summary(r.stdout)[0].startswith("pipeline: 1 done, 0 skipped, 0 failed, 0 not run, 1 interrupted"), r.stdout
    assert r.stderr.strip().splitlines()[-1] == "error: interrupted by SIGTERM", r.stderr
    runs = mlflow.MlflowClient(uri).search_runs(
        [mlflow.MlflowClient(uri).get_experiment_by_name("pipeline").experiment_id])
    assert len(runs) == 1 and runs[0].data.metrics.get("stage_s/a") == 1.5, runs[0].data.metrics
    assert runs[0].info.status == "KILLED" and runs[0].data.tags["error"] == "interrupted by SIGTERM"


# ------------------------------------------------------------------- the direct runner and its lock (issue #50)


TOOL = """
import json, os, sys
kind, args = sys.argv[1], sys.argv[2:]
if kind == "gen":  # seed n out
    seed, n, out = int(args[0]), int(args[1]), args[2]
    os.makedirs(os.path.dirname(out), exist_ok=True)
    open(out, "w").write("".join(f"{seed * i}\\n" for i in range(n)))
elif kind == "table":  # a directory out from the inputs
    os.makedirs("out/parts", exist_ok=True)
    for p in args:
        open(os.path.join("out/parts", os.path.basename(p)), "w").write(open(p).read()[::-1])
    open("out/index.txt", "w").write("\\n".join(sorted(args)) + "\\n")
elif kind == "grid":  # a b scale
    a, b, scale = args
    os.makedirs("reports", exist_ok=True)
    n = len(os.listdir("out/parts"))
    open(f"reports/grid_{a}-{b}.txt", "w").write(f"{a}{int(b) * int(scale) * n}\\n")
elif kind == "summary":
    os.makedirs("reports/summary", exist_ok=True)
    rows = sorted(p for p in os.listdir("reports") if p.startswith("grid_"))
    for r in rows:
        open(f"reports/summary/{r}", "w").write(open(f"reports/{r}").read())
    json.dump({"n": len(rows)}, open("reports/metrics.json", "w"))
    if not os.path.exists("model.bin"):  # a persistent output: made once, kept by every re-run
        open("model.bin", "w").write("m")
"""
GRID = ["reports/grid_x-1.txt", "reports/grid_x-2.txt", "reports/grid_y-1.txt", "reports/grid_y-2.txt"]
PIPE = {  # a foreach and a matrix group, params deps, cached file and directory outs, cache: false file, directory,
    # metric and persistent outs, in four levels
    "gen": {"foreach": "${gen.seeds}",
            "do": {"cmd": f"{PY} tool.py gen ${{item}} ${{gen.n}} data/gen_${{item}}.txt", "deps": ["tool.py"],
                   "params": ["gen.n"], "outs": ["data/gen_${item}.txt"]}},
    "table": {"cmd": f"{PY} tool.py table data/gen_1.txt data/gen_2.txt", "deps": ["data/gen_1.txt", "data/gen_2.txt"],
              "outs": ["out"]},
    "grid": {"matrix": {"a": ["x", "y"], "b": [1, 2]}, "cmd": f"{PY} tool.py grid ${{item.a}} ${{item.b}} ${{scale}}",
             "deps": ["out"], "params": ["scale"],
             "outs": [{"reports/grid_${item.a}-${item.b}.txt": {"cache": False}}]},
    "summary": {"cmd": f"{PY} tool.py summary", "deps": GRID,
                "outs": [{"reports/summary": {"cache": False}}, {"model.bin": {"cache": False, "persist": True}}],
                "metrics": [{"reports/metrics.json": {"cache": False}}]},
}
PARAMS = "gen:\n  n: 3\n  seeds: [1, 2]\nscale: 2\n"


def _tree(root: Path) -> dict[str, bytes]:
    """Every file of a repository but git's and DVC's own state and the pipeline's logs; .gitignore files as their
    sorted lines (the pipeline adds a stage's entries as it finishes, `dvc repro` in its order)."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_file() and not rel.startswith((".git/", ".dvc/tmp/", "logs/")):
            data = p.read_bytes()
            out[rel] = b"".join(sorted(data.splitlines(keepends=True))) if p.name == ".gitignore" else data
    return out


def test_the_direct_runner_writes_the_lock_a_serial_dvc_repro_writes(tmp_path):
    files = {"tool.py": TOOL, "params.yaml": PARAMS}
    seq, par = make_repo(tmp_path / "seq", PIPE, files), make_repo(tmp_path / "par", PIPE, files)
    assert dvc(seq, "repro").returncode == 0

    r = run_pipeline("--repo", str(par), "--workers", "2", "--no-tracking")
    assert r.exit_code == 0, r.output
    assert summary(r.output)[0].startswith("pipeline: 8 done, 0 skipped, 0 failed, 0 not run of 8 stages"), r.output
    assert (par / "dvc.lock").read_bytes() == (seq / "dvc.lock").read_bytes()
    assert json.loads(dvc(par, "status", "--json").stdout) == {}
    # the same outputs, .gitignore entries, DVC cache objects and run cache entries
    assert _tree(par) == _tree(seq)

    # a changed parameter: its stages and what follows re-run, the entries change in place
    for repo in (seq, par):
        (repo / "params.yaml").write_text(PARAMS.replace("scale: 2", "scale: 3"))
    assert dvc(seq, "repro").returncode == 0
    r = run_pipeline("--repo", str(par), "--workers", "2", "--no-tracking")
    assert r.exit_code == 0, r.output
    assert summary(r.output)[0].startswith("pipeline: 5 done, 3 skipped, 0 failed, 0 not run of 8 stages"), r.output
    assert (par / "dvc.lock").read_bytes() == (seq / "dvc.lock").read_bytes()
    assert json.loads(dvc(par, "status", "--json").stdout) == {}
    assert _tree(par) == _tree(seq)


def test_a_stage_whose_inputs_came_back_the_same_is_skipped_as_dvc_skips_it(tmp_path):
    """The plan says b runs (a runs first); a re-makes the same a.txt, so b is found unchanged when its turn
    comes, and is not run (its log says so), as `dvc repro` does."""
    repo = make_repo(tmp_path / "repo", {"a": TOY["a"], "b": TOY["b"]})
    assert run_pipeline("--repo", str(repo), "--no-tracking").exit_code == 0
    (repo / "a.txt").unlink()
    r = run_pipeline("--repo", str(repo), "--no-tracking")
    assert r.exit_code == 0, r.output
    lines = summary(r.output)
    assert lines[0].startswith("pipeline: 1 done, 1 skipped, 0 failed, 0 not run of 2 stages"), r.output
    assert lines[1:3] == ["done     a", "skipped  b"], r.output
    assert "didn't change, skipping" in (repo / "logs" / "pipeline" / "b.log").read_text()
    assert json.loads(dvc(repo, "status", "--json").stdout) == {}


def test_both_runners_record_the_same_entries(tmp_path):
    """`--runner dvc` (`dvc repro -s` a stage) records the same entries; it appends each as its stage ends, so only
    the direct runner has them in a serial `dvc repro`'s order."""
    files = {"tool.py": TOOL, "params.yaml": PARAMS}
    locks = []
    for runner in ("dvc", "direct"):
        repo = make_repo(tmp_path / runner, PIPE, files)
        r = run_pipeline("--repo", str(repo), "--workers", "1", "--runner", runner, "--no-tracking")
        assert r.exit_code == 0, r.output
        assert json.loads(dvc(repo, "status", "--json").stdout) == {}
        locks.append(yaml.safe_load((repo / "dvc.lock").read_text()))
    assert locks[0] == locks[1]


KILLED_WRITER = """
import sys
from rlsac.runners.dvc_stage import write_atomic
texts = [open(sys.argv[2]).read(), open(sys.argv[3]).read()]
i = 0
while True:  # the SIGKILL lands somewhere in here
    write_atomic(sys.argv[1], texts[i % 2])
    i += 1
    if i == 2:
        print("writing", flush=True)
"""


def _big_lock(k: int) -> str:
    return "schema: '2.0'\nstages:\n" + "".join(f"  s{i}:\n    cmd: run {k}\n" for i in range(40000))


def test_a_sigkill_of_the_writer_leaves_a_whole_lock(tmp_path):
    """The lock file is written to a temporary file and renamed over it: a SIGKILL at any instant leaves it whole
    (DVC's own write truncates it first: a kill there left it empty, issue #50)."""
    lock = tmp_path / "dvc.lock"
    texts = [_big_lock(0), _big_lock(1)]
    lock.write_text(texts[1])
    script = tmp_path / "writer.py"
    script.write_text(KILLED_WRITER)
    for k, text in enumerate(texts):
        (tmp_path / f"text{k}").write_text(text)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    for attempt in range(8):
        proc = subprocess.Popen([sys.executable, str(script), str(lock), str(tmp_path / "text0"),
                                 str(tmp_path / "text1")], stdout=subprocess.PIPE, text=True, env=env)
        assert proc.stdout.readline().strip() == "writing"
        time.sleep(0.013 * attempt)
        proc.kill()
        proc.wait()
        assert lock.read_text() in texts, (attempt, len(lock.read_text()))


def test_the_lock_writer_keeps_old_entries_in_place_and_adds_new_ones_in_dvc_order(tmp_path):
    from rlsac.runners.dvc_stage import LockFile, render_entry

    old = "schema: '2.0'\nstages:\n" + render_entry("b", {"cmd": "b"}) + render_entry("a", {"cmd": "a"})
    path = tmp_path / "dvc.lock"
    path.write_text(old)
    lock = LockFile(path, old, ["b", "a"], {"a": 0, "b": 1, "c": 2, "d": 3})
    lock.update({"d": {"cmd": "d"}})
    lock.update({"c": {"cmd": "c"}, "a": {"cmd": "A"}})  # c finished after d, goes before it as a serial run has it
    assert list(yaml.safe_load(path.read_text())["stages"].items()) == [
        ("b", {"cmd": "b"}), ("a", {"cmd": "A"}), ("c", {"cmd": "c"}), ("d", {"cmd": "d"})]

    # another dvc command wrote the file meanwhile (`dvc commit` of a stage): the next write keeps its change
    time.sleep(0.01)
    path.write_text(path.read_text() + render_entry("x", {"cmd": "x"}))
    lock.update({"b": {"cmd": "B"}})
    assert list(yaml.safe_load(path.read_text())["stages"].items()) == [
        ("b", {"cmd": "B"}), ("a", {"cmd": "A"}), ("c", {"cmd": "c"}), ("d", {"cmd": "d"}), ("x", {"cmd": "x"})]


# ------------------------------------------------------------------ one tracking server or a refusal (issue #50)


def test_a_cluster_needs_an_http_tracking_server(tmp_path, monkeypatch):
    """--address without an http(s) MLFLOW_TRACKING_URI: every node would log into its own sqlite file. One error
    line, exit 2, before Ray or MLflow is touched."""
    from rlsac.runners import pipeline as pipeline_module

    repo = make_repo(tmp_path / "repo", TOY)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(pipeline_module, "_start_ray", lambda o: pytest.fail("Ray started"))
    for uri in (None, "sqlite:///mlflow.db", "file:///tmp/mlruns"):
        if uri is None:
            monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
        else:
            monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
        for track in ([], ["--no-tracking"]):  # the stages' own rlsac commands log, whatever the driver does
            r = CliRunner().invoke(cli, ["pipeline", "--repo", str(repo), "--address", "127.0.0.1:9", *track])
            assert r.exit_code == 2, r.output
            assert r.output.startswith("error: --address runs stages on other machines: MLFLOW_TRACKING_URI must "
                                       "be an http(s) MLflow server"), r.output
            assert len(r.output.splitlines()) == 1, r.output
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "mlruns").exists()
    assert not (repo / "a.txt").exists()

    # with a server set, an address nothing answers at is the next error, within seconds (issue #49)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:9")
    t0 = time.monotonic()
    r = CliRunner().invoke(cli, ["pipeline", "--repo", str(repo), "--address", "127.0.0.1:1"])
    assert r.exit_code == 2 and "no Ray cluster answers there" in r.output and len(r.output.splitlines()) == 1, r.output
    assert time.monotonic() - t0 < 20
