"""``rlsac pipeline --remote`` (issue #50, item 2): stages on nodes that share no folder, their files through an S3
bucket (a moto server the test starts on this machine).

Every Ray task of ``--remote`` works in a fresh folder of its own under ``RLSAC_NODE_DIR`` (set here before the
module's 2-CPU Ray cluster starts, so its workers inherit it), with the code tree and its inputs fetched from the
bucket: no two stages, and no stage and the driver, share a folder, as on machines without a shared disk. The
driver's repository must end as a single-host run leaves it.
"""

from __future__ import annotations

import json
import os
import time

import pytest
import ray
import yaml
from click.testing import CliRunner
from test_ray_pipeline import PARAMS, PIPE, TOOL, TOY, _tree, _write, dvc, make_repo, run_pipeline, summary

from rlsac.cli import cli
from rlsac.tracking import free_port

BUCKET = "rlsac-test"


@pytest.fixture(scope="module", autouse=True)
def local_ray(tmp_path_factory):
    """One local Ray cluster of 2 CPUs for the module, its workers' node folder a temporary one."""
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    node_dir = tmp_path_factory.mktemp("node")
    old = os.environ.get("RLSAC_NODE_DIR")
    os.environ["RLSAC_NODE_DIR"] = str(node_dir)
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield node_dir
    ray.shutdown()
    if old is None:
        os.environ.pop("RLSAC_NODE_DIR", None)
    else:
        os.environ["RLSAC_NODE_DIR"] = old


@pytest.fixture
def s3(tmp_path, monkeypatch):
    """A local S3 server (moto) with one bucket; the AWS variables point at it, as they would at a real bucket."""
    import boto3
    from moto.server import ThreadedMotoServer

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "testing",
           "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1",
           # no ~/.aws of this machine's user in the way
           "AWS_CONFIG_FILE": str(tmp_path / "aws-config"), "AWS_SHARED_CREDENTIALS_FILE": str(tmp_path / "aws-cred")}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    for k in ("AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN", "AWS_PROFILE", "AWS_REGION"):
        monkeypatch.delenv(k, raising=False)
    client = boto3.client("s3", endpoint_url=env["AWS_ENDPOINT_URL"], region_name="us-east-1")
    client.create_bucket(Bucket=BUCKET)
    yield client
    server.stop()


def _object(client, key: str) -> bytes | None:
    try:
        return client.get_object(Bucket=BUCKET, Key=key)["Body"].read()
    except client.exceptions.NoSuchKey:
        return None


def _remote_run_ends_as(par, seq, counts: str) -> None:
    """``rlsac pipeline --remote`` on ``par``: ``counts`` in its summary, then the lock of ``seq``'s `dvc repro`
    byte for byte and `dvc status` clean."""
    r = run_pipeline("--repo", str(par), "--workers", "2", "--no-tracking", "--remote", f"s3://{BUCKET}/store")
    assert r.exit_code == 0, r.output
    assert summary(r.output)[0].startswith(f"pipeline: {counts} of 8 stages"), r.output
    assert (par / "dvc.lock").read_bytes() == (seq / "dvc.lock").read_bytes()
    assert json.loads(dvc(par, "status", "--json").stdout) == {}


def test_nodes_without_a_shared_folder_end_as_a_single_host_run(tmp_path, s3, local_ray):
    files = {"tool.py": TOOL, "params.yaml": PARAMS}
    seq, par = make_repo(tmp_path / "seq", PIPE, files), make_repo(tmp_path / "par", PIPE, files)
    assert dvc(seq, "repro").returncode == 0

    _remote_run_ends_as(par, seq, "8 done, 0 skipped, 0 failed, 0 not run")
    # the same outputs, .gitignore entries and DVC cache objects; the nodes' run cache entries stay on the nodes
    runs = ".dvc/cache/runs/"
    assert {k: v for k, v in _tree(par).items() if not k.startswith(runs)} == \
        {k: v for k, v in _tree(seq).items() if not k.startswith(runs)}
    assert "Running stage 'table'" in (par / "logs" / "pipeline" / "table.log").read_text()  # the node's log
    # a `cache: false` output travelled by its md5, in DVC's layout (a cache push would not have carried it)
    md5 = yaml.safe_load((par / "dvc.lock").read_text())["stages"]["grid@x-1"]["outs"][0]["md5"]
    assert _object(s3, f"store/files/md5/{md5[:2]}/{md5[2:]}") == (par / "reports" / "grid_x-1.txt").read_bytes()
    # every stage's folder was its own and is gone; the node keeps the code tree and the objects it fetched or made
    assert sorted(p.name for p in local_ray.iterdir()) == ["objects", "trees"]

    # a changed parameter: its stages and what follows re-run on the nodes, the driver's copy follows
    for repo in (seq, par):
        (repo / "params.yaml").write_text(PARAMS.replace("scale: 2", "scale: 3"))
    assert dvc(seq, "repro").returncode == 0
    before = (par / "reports" / "grid_x-1.txt").read_bytes()  # an output git would add: it travels in the tree
    _remote_run_ends_as(par, seq, "5 done, 3 skipped, 0 failed, 0 not run")
    assert (par / "reports" / "grid_x-1.txt").read_bytes() != before
    # a stage's folder is the node's unpacked tree by hard links: re-making that output in its folder left the
    # node's tree as packed (the output is removed before the command writes it, never written in place)
    trees = [t for t in (local_ray / "trees").iterdir() if (t / "reports" / "grid_x-1.txt").exists()]
    assert [(t / "reports" / "grid_x-1.txt").read_bytes() for t in trees] == [before]


NESTED = {  # a DVC project in a subfolder of a git repository, reading a file of the repository outside it (as the
    # quick profile, experiments/quick, reads ../../data/strecha)
    "a": {"cmd": _write("a.txt", "a", ("../shared/in.txt",)), "deps": ["../shared/in.txt"], "outs": ["a.txt"]},
    "b": {"cmd": _write("b.txt", "b", ("a.txt",)), "deps": ["a.txt"], "outs": [{"b.txt": {"cache": False}}]},
}


def _nested(path):
    """A git repository with ``shared/in.txt`` and a DVC project at ``proj`` (``dvc init --subdir``). -> proj."""
    import subprocess
    import sys

    from test_ray_pipeline import _env

    (path / "shared").mkdir(parents=True)
    (path / "shared" / "in.txt").write_text("in")
    subprocess.run(["git", "init", "-q"], cwd=path, check=True)
    (path / "proj").mkdir()
    subprocess.run([sys.executable, "-m", "dvc", "init", "-q", "--subdir"], cwd=path / "proj", check=True, env=_env())
    (path / "proj" / "dvc.yaml").write_text(yaml.safe_dump({"stages": NESTED}, sort_keys=False))
    return path / "proj"


def test_a_dvc_project_nested_in_a_git_repository_takes_its_outside_inputs_along(tmp_path, s3, local_ray):
    """The quick profile's case: the code tree and the inputs' paths start at the git repository's top, the stage
    runs in the project's folder inside it; the lock is a serial `dvc repro`'s."""
    seq, par = _nested(tmp_path / "seq"), _nested(tmp_path / "par")
    assert dvc(seq, "repro").returncode == 0
    r = run_pipeline("--repo", str(par), "--workers", "2", "--no-tracking", "--remote", f"s3://{BUCKET}/nested")
    assert r.exit_code == 0, r.output
    assert summary(r.output)[0].startswith("pipeline: 2 done"), r.output
    assert (par / "dvc.lock").read_bytes() == (seq / "dvc.lock").read_bytes()
    assert (par / "b.txt").read_text() == "bain"
    assert json.loads(dvc(par, "status", "--json").stdout) == {}


def test_bad_remote_is_one_error_line_before_any_work(tmp_path, s3, monkeypatch):
    repo = make_repo(tmp_path / "repo", {"a": TOY["a"]})
    closed = f"http://127.0.0.1:{free_port()}"
    for args, env, message in (
            (["--remote", "http://host/bucket"], {}, "not s3://bucket/prefix"),
            (["--remote", "s3://"], {}, "not s3://bucket/prefix"),
            (["--remote", "nosuch"], {}, "no DVC remote of that name"),
            (["--remote", "s3://b/p", "--runner", "dvc"], {}, "direct runner only"),
            (["--remote", "s3://no-such-bucket/p"], {}, "cannot write to the store"),
            (["--remote", f"s3://{BUCKET}/p"], {"AWS_ENDPOINT_URL": closed}, "cannot write to the store")):
        with monkeypatch.context() as m:
            for k, v in env.items():
                m.setenv(k, v)
            t0 = time.monotonic()
            r = CliRunner().invoke(cli, ["pipeline", "--repo", str(repo), *args, "--no-tracking"])
        assert r.exit_code == 2, (args, r.output)
        assert r.output.startswith("error: ") and message in r.output and len(r.output.splitlines()) == 1, r.output
        assert time.monotonic() - t0 < 60, args  # an endpoint that does not answer is not waited on for minutes
    assert not (repo / "a.txt").exists() and not (repo / "dvc.lock").exists()


def test_bad_remote_creates_nothing_and_starts_no_run(tmp_path, s3, monkeypatch):
    """Issue #64: with tracking on, a bad --remote was refused only after the tracking store was made (its sqlite
    file, the stage times read from it): the bucket is now checked first, nothing is created and no run starts."""
    repo = make_repo(tmp_path / "repo", {"a": TOY["a"]})
    store = tmp_path / "store" / "mlflow.db"
    store.parent.mkdir()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}")
    monkeypatch.chdir(tmp_path)
    closed = f"http://127.0.0.1:{free_port()}"
    dvc(repo, "status")  # DVC's own files of .dvc/tmp (its lock), which any read of the repository makes

    def paths() -> set[str]:  # every file and folder but git's and DVC's own state
        skip = (repo / ".git", repo / ".dvc" / "tmp")
        return {p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")
                if not any(p.is_relative_to(s) for s in skip)}

    before = paths()
    for args, env, message in ((["--remote", "nosuch"], {}, "no DVC remote of that name"),
                               (["--remote", "s3://no-such-bucket/p"], {}, "cannot write to the store"),
                               (["--remote", f"s3://{BUCKET}/p"], {"AWS_ENDPOINT_URL": closed},
                                "cannot write to the store")):
        with monkeypatch.context() as m:
            for k, v in env.items():
                m.setenv(k, v)
            r = CliRunner().invoke(cli, ["pipeline", "--repo", str(repo), *args])
        assert r.exit_code == 2 and message in r.output and len(r.output.splitlines()) == 1, (args, r.output)
        assert paths() == before, args
        assert not store.exists(), args  # the tracking store untouched: no run could have started


def test_a_dvc_remote_by_name_carries_its_endpoint(tmp_path, s3, monkeypatch):
    """`--remote NAME`: a DVC remote of the repository, its `endpointurl` from `dvc remote modify` (no AWS_ENDPOINT_URL
    in the environment), as docs/reproducing.md shows it."""
    endpoint = os.environ["AWS_ENDPOINT_URL"]
    monkeypatch.delenv("AWS_ENDPOINT_URL")
    repo = make_repo(tmp_path / "repo", {"a": TOY["a"], "b": TOY["b"]})
    for args in (["remote", "add", "store", f"s3://{BUCKET}/named"], ["remote", "modify", "store", "endpointurl",
                                                                       endpoint]):
        assert dvc(repo, *args).returncode == 0
    r = run_pipeline("--repo", str(repo), "--no-tracking", "--remote", "store")
    assert r.exit_code == 0, r.output
    assert summary(r.output)[0].startswith("pipeline: 2 done"), r.output
    assert (repo / "b.txt").read_text() == "ba"
    assert json.loads(dvc(repo, "status", "--json").stdout) == {}
    assert s3.list_objects_v2(Bucket=BUCKET, Prefix="named/files/md5/")["KeyCount"] > 0


CHAIN = {"a": TOY["a"], "b": TOY["b"],
         "c": {"cmd": _write("c.txt", "c", ("b.txt",)), "deps": ["b.txt"], "outs": ["c.txt"]}}


def test_a_chain_on_one_node_reads_its_inputs_from_the_nodes_cache(tmp_path, s3, local_ray):
    """a -> b -> c with --remote: b and c run where their parent ran (one node here; on a cluster Ray is asked for
    the parent's node, softly) and find their inputs in the node's cache of objects, not in the bucket; the
    results and the lock are a serial `dvc repro`'s."""
    from rlsac.runners.pipeline import pipeline

    seq, par = make_repo(tmp_path / "seq", CHAIN), make_repo(tmp_path / "par", CHAIN)
    assert dvc(seq, "repro").returncode == 0
    s = pipeline({"repo": str(par), "workers": 2, "remote": f"s3://{BUCKET}/chain"}, track=False)
    assert s["counts"]["done"] == 3, s["results"]
    r = s["results"]
    # each of b and c needs one object, its parent's output: without the cache, one download each
    assert [(r[a]["downloads"], r[a]["cache_hits"]) for a in ("b", "c")] == [(0, 1), (0, 1)], r
    assert r["a"]["node_id"] == r["b"]["node_id"] == r["c"]["node_id"]
    assert (par / "dvc.lock").read_bytes() == (seq / "dvc.lock").read_bytes()
    assert [(par / f).read_text() for f in ("a.txt", "b.txt", "c.txt")] == ["a", "ba", "cba"]
    assert json.loads(dvc(par, "status", "--json").stdout) == {}
