"""The quick profile four ways, from one commit, in one run (issue #50, item 5): `dvc repro` against `rlsac pipeline`
on one worker, on one node with two, and on two nodes that share no folder.

    python benchmarks/pipeline_cluster.py                         # the four arms, one after the other
    python benchmarks/pipeline_cluster.py --arms dvc,two-nodes    # some of them
    python benchmarks/pipeline_cluster.py --keep /tmp/bench       # keep the clones, logs and stores there

Each arm runs in a fresh clone of ``--repo``'s HEAD (uncommitted changes are not measured), so each starts from an
empty quick-profile lock, with this interpreter's environment, its own MLflow store and ``OMP_NUM_THREADS=1``:

- ``dvc``: ``dvc --cd experiments/quick repro`` (CI's command; serial, DVC's own runner);
- ``workers1`` / ``workers2``: ``rlsac pipeline --repo experiments/quick --workers 1`` / ``2`` (one local Ray node);
- ``two-nodes``: two Ray nodes of one CPU each (``ray.cluster_utils.Cluster``), each with its own node folder
  (``RLSAC_NODE_DIR``), the stages' files through an S3 bucket of a local S3 server (moto) with ``--remote``, and one
  MLflow server (``--address`` requires it): every stage works in a folder of its own, as on machines that share no
  disk. Both nodes are on this machine, so they share its cores: the arm measures the transfers' cost, not a speed-up.

Prints each arm's wall time (the whole command, planning and Ray's start included) and its ratio to ``dvc repro``'s;
whether its ``dvc.lock`` is byte for byte the ``dvc`` arm's (which implies every output, tables included, hashes the
same) and ``dvc status`` is clean; then the stage times the ``workers2`` arm logged (``stage_s/<stage>``), the
overhead per stage they imply against each arm's wall time, and ``benchmarks/pipeline_projection.py``'s list
scheduling on them (with that overhead) against the measured walls: how far the paper profile's projection can be
trusted. ``--json FILE`` writes it all.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rlsac.tracking import free_port, mlflow_server

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

ARMS = ("dvc", "workers1", "workers2", "two-nodes")
QUICK = "experiments/quick"
BUCKET = "rlsac-bench"


def _env(clone: Path, tracking: str, extra: dict[str, str] | None = None) -> dict[str, str]:
    """This interpreter's tools first on PATH, the clone's own code first on PYTHONPATH."""
    bin_dir = str(Path(sys.executable).parent)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "CI": "true", "MLFLOW_TRACKING_URI": tracking,
           "PATH": bin_dir + os.pathsep + os.environ.get("PATH", ""), "PYTHONPATH": str(clone)}
    env.update(extra or {})
    return env


def _clone(src: Path, dst: Path) -> Path:
    subprocess.run(["git", "clone", "-q", str(src), str(dst)], check=True)
    return dst


def _timed(cmd: list[str], cwd: Path, env: dict[str, str], log: Path) -> tuple[int, float]:
    t0 = time.perf_counter()
    with open(log, "wb") as f:
        rc = subprocess.run(cmd, cwd=cwd, env=env, stdout=f, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL).returncode
    return rc, time.perf_counter() - t0


@contextlib.contextmanager
def _s3_server():
    """A local S3 server (moto) with one bucket; yields the AWS variables that point at it."""
    import logging

    import boto3
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # not a line per request

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "bench",
           "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}
    try:
        boto3.client("s3", endpoint_url=env["AWS_ENDPOINT_URL"], region_name="us-east-1",
                     aws_access_key_id="bench", aws_secret_access_key="bench").create_bucket(Bucket=BUCKET)
        yield env
    finally:
        server.stop()


@contextlib.contextmanager
def _two_nodes(work: Path):
    """Two Ray nodes of one CPU each on this machine, each with a node folder of its own; yields the address."""
    os.environ["RAY_AUTH_MODE"] = "token"  # as on a real cluster (Ray 2.60: the token of ~/.ray, made if missing)
    if not (Path.home() / ".ray" / "auth_token").is_file():
        subprocess.run([str(Path(sys.executable).parent / "ray"), "get-auth-token", "--generate"], check=True,
                       stdout=subprocess.DEVNULL)
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={
        "num_cpus": 1, "include_dashboard": False, "env_vars": {"RLSAC_NODE_DIR": str(work / "nodeA")}})
    try:
        cluster.add_node(num_cpus=1, env_vars={"RLSAC_NODE_DIR": str(work / "nodeB")})
        cluster.wait_for_nodes()
        yield cluster.address
    finally:
        cluster.shutdown()


def run_arm(arm: str, src: Path, work: Path, targets: list[str]) -> dict:
    """One arm in a fresh clone under ``work/arm``. -> {arm, rc, wall_s, n_stages, lock (bytes), clone, log}."""
    clone = _clone(src, work / arm / "repo")
    log = work / arm / "command.log"
    store = f"sqlite:///{work / arm / 'mlflow.db'}"
    with contextlib.ExitStack() as stack:
        if arm == "dvc":
            cmd = [sys.executable, "-m", "dvc", "--cd", QUICK, "repro", *targets]
            env = _env(clone, store)
        elif arm in ("workers1", "workers2"):
            cmd = ["rlsac", "pipeline", *targets, "--repo", QUICK, "--workers", arm[-1]]
            env = _env(clone, store)
        else:
            aws = stack.enter_context(_s3_server())
            store = stack.enter_context(mlflow_server(f"sqlite:///{work / arm / 'server.db'}", work / arm))
            address = stack.enter_context(_two_nodes(work / arm))
            cmd = ["rlsac", "pipeline", *targets, "--repo", QUICK, "--address", address, "--remote",
                   f"s3://{BUCKET}/quick"]
            env = _env(clone, store, {**aws, "RAY_AUTH_MODE": "token"})
        rc, wall = _timed(cmd, clone, env, log)
        # the stage times a pipeline arm logged, read while its tracking server is still up
        deps, times = stage_seconds(clone, store) if arm != "dvc" and rc == 0 else (None, None)
    lock = clone / QUICK / "dvc.lock"
    status = subprocess.run([sys.executable, "-m", "dvc", "--cd", QUICK, "status", "--json", *targets], cwd=clone,
                            env=_env(clone, store), capture_output=True, text=True)
    import yaml

    n = len((yaml.safe_load(lock.read_text()) or {}).get("stages", {})) if lock.is_file() else 0
    return {"arm": arm, "rc": rc, "wall_s": wall, "n_stages": n, "lock": lock.read_bytes() if lock.is_file() else b"",
            "status": status.stdout.strip(), "clone": str(clone), "log": str(log), "times": times,
            "deps": deps}


def stage_seconds(clone: Path, store: str) -> tuple[dict, dict[str, float]]:
    """-> the quick profile's DAG (pipeline_projection.load_dag) and the stage times an ``rlsac pipeline`` run logged
    to its MLflow store (``stage_s/<stage>``)."""
    from pipeline_projection import load_dag, mlflow_times

    repo = clone / QUICK
    deps = load_dag(repo)
    return deps, mlflow_times(store, deps, repo)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repo", default=str(HERE.parent), help="The git repository whose HEAD is cloned "
                                                            "[default: this one].")
    p.add_argument("--stages", default="", help="Comma-separated stages (names, foreach groups) and what they "
                                                "need, for a short run [default: every stage].")
    p.add_argument("--arms", default=",".join(ARMS), help=f"Comma-separated, of {', '.join(ARMS)} [default: all].")
    p.add_argument("--keep", help="Keep the clones, logs and stores in this folder (absent or empty).")
    p.add_argument("--json", help="Write the results to this JSON file.")
    a = p.parse_args(argv)
    arms = [x for x in a.arms.split(",") if x]
    bad = [x for x in arms if x not in ARMS]
    if bad or not arms:
        p.error(f"--arms: unknown arm {bad[0] if bad else '(none)'}; choose from {', '.join(ARMS)}")
    if a.keep and Path(a.keep).exists() and any(Path(a.keep).iterdir()):
        p.error(f"--keep {a.keep}: not empty")
    os.environ["OMP_NUM_THREADS"] = "1"
    src = Path(a.repo).resolve()
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=src, capture_output=True, text=True,
                          check=True).stdout.strip()
    work = Path(a.keep).resolve() if a.keep else Path(tempfile.mkdtemp(prefix="rlsac-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    results = {}
    try:
        for arm in arms:
            print(f"{arm}: running (log {work / arm / 'command.log'})", flush=True)
            results[arm] = r = run_arm(arm, src, work, [x for x in a.stages.split(",") if x])
            print(f"{arm}: rc {r['rc']}, {r['wall_s']:.1f} s, {r['n_stages']} stages in dvc.lock", flush=True)
        report = summarise(results, head, bytewise=not a.stages)
    finally:
        if not a.keep:
            shutil.rmtree(work, ignore_errors=True)
    print(report["text"])
    if a.json:
        Path(a.json).write_text(json.dumps({k: v for k, v in report.items() if k != "text"}, indent=1) + "\n")
    if any(r["rc"] for r in results.values()) or not report["all_same"]:
        sys.exit(1)


def summarise(results: dict, head: str, bytewise: bool = True) -> dict:
    """The table of walls and checks, and the projection against the measured walls. ``bytewise``: compare the locks
    byte for byte (a whole pipeline); else their entries (`dvc repro <stages>` orders new entries as a Python set
    iterates)."""
    import yaml
    from pipeline_projection import list_schedule

    def same_lock(x: bytes, y: bytes) -> bool:
        return x == y if bytewise else yaml.safe_load(x) == yaml.safe_load(y)

    ref = results.get("dvc")
    rows, out = [], {"commit": head, "arms": {}}
    for arm, r in results.items():
        same = None if ref is None or arm == "dvc" else same_lock(r["lock"], ref["lock"])
        out["arms"][arm] = {"rc": r["rc"], "wall_s": round(r["wall_s"], 1), "n_stages": r["n_stages"],
                            "lock_same_as_dvc": same, "status_clean": r["status"] == "{}"}
        ratio = f"{ref['wall_s'] / r['wall_s']:.2f}x" if ref else "–"
        rows.append(f"| {arm} | {r['rc']} | {r['wall_s']:.1f} | {ratio} | {r['n_stages']} | "
                    f"{'–' if same is None else 'yes' if same else 'NO'} | {'yes' if r['status'] == '{}' else 'NO'} |")
    out["all_same"] = all(v["lock_same_as_dvc"] in (None, True) and v["status_clean"] for v in out["arms"].values())
    lines = [f"The quick profile from a fresh clone of {head}, one arm after the other on this machine "
             f"({os.cpu_count()} cores, OMP_NUM_THREADS=1):", "",
             "| arm | rc | wall s | dvc repro / arm | stages | dvc.lock = dvc repro's | dvc status clean |",
             "| --- | --- | --- | --- | --- | --- | --- |", *rows, "",
             "Per-stage overhead (wall time against list scheduling on the stage times, which the pipeline arms log as"
             " stage_s/<stage>):"]
    # each pipeline arm against its own stage times; dvc repro against the one-worker arm's (the same commands, one at
    # a time), else the two-worker arm's: the difference is what each runner adds per stage (planning, Ray's start,
    # hashing, dvc.lock; with --remote the transfers)
    serial_arm = next((k for k in ("workers1", "workers2") if results.get(k, {}).get("times")), None)
    serial = results[serial_arm]["times"] if serial_arm else None
    dag = results[serial_arm]["deps"] if serial_arm else None  # every arm's clone is of one commit: one DAG
    for arm, workers in (("dvc", 1), ("workers1", 1), ("workers2", 2), ("two-nodes", 2)):
        r = results.get(arm)
        times = serial if arm == "dvc" else (r or {}).get("times")
        if r is None or r["rc"] or not times:
            continue
        deps = r["deps"] or dag
        times = {a: times.get(a, 0.0) for a in deps}
        bare = list_schedule(deps, times, workers)
        over = (r["wall_s"] - bare) * workers / max(r["n_stages"], 1)
        out["arms"][arm].update(stage_time_total_s=round(sum(times.values()), 1),
                                projection_without_overhead_s=round(bare, 1), overhead_per_stage_s=round(over, 2))
        whose = f"the {serial_arm} arm's" if arm == "dvc" else "its own"
        lines.append(f"- {arm}: stage times {sum(times.values()):.1f} s in all ({whose}); "
                     f"list scheduling on {workers} worker(s) {bare:.1f} s; measured {r['wall_s']:.1f} s: "
                     f"{over:.2f} s per stage beyond the stages' own time")
    out["text"] = "\n".join(lines)
    return out


if __name__ == "__main__":
    main()
