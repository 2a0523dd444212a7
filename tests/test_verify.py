"""``rlsac verify`` on a toy git + DVC repository: a deterministic stage, a stage whose output depends on an
environment variable, a training stage and a data stage with a DVC-cached output."""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from click.testing import CliRunner
from test_cli import assert_user_error  # tests/ is on sys.path (pytest prepend mode)

from rlsac.cli import cli

BIN = Path(sys.executable).parent

SCRIPTS = {
    # data stage (DVC-cached output): the generated input of `make`, never git-tracked
    "gen_data.py": """
        from pathlib import Path
        Path("data").mkdir(exist_ok=True)
        Path("data/raw.txt").write_text("1 2 3 4\\n")
    """,
    # deterministic: a JSON summary, a CSV and an untracked timing sidecar that verify must ignore
    "make.py": """
        import json, time, yaml
        from pathlib import Path
        n = yaml.safe_load(open("params.yaml"))["make"]["n"]
        xs = [float(v) for v in Path("data/raw.txt").read_text().split()][:n]
        Path("out").mkdir(exist_ok=True)
        Path("out/a.json").write_text(json.dumps({"summary": {"mAA": 0.8125, "n": len(xs)}, "xs": xs}, indent=2))
        Path("out/b.csv").write_text("instance,err\\n" + "".join(f"{i},{x / 4}\\n" for i, x in enumerate(xs)))
        Path("out/timing.json").write_text(json.dumps({"seconds": time.time()}))
    """,
    # depends on an environment variable that is no input of the stage: differs when it changes
    "stamp.py": """
        import os
        open("stamp.txt", "w").write(os.environ.get("VERIFY_STAMP", "one") + "\\n")
    """,
    "train.py": """
        open("model.pt", "wb").write(bytes(range(16)))
    """,
}

DVC_YAML = """
stages:
  data:
    cmd: python gen_data.py
    deps: [gen_data.py]
    outs: [data/raw.txt]
  make:
    cmd: python make.py
    deps: [make.py, data/raw.txt]
    params: [make.n]
    outs:
      - out:
          cache: false
  stamp:
    cmd: python stamp.py
    deps: [stamp.py]
    outs:
      - stamp.txt:
          cache: false
  train_toy:
    cmd: python train.py
    deps: [train.py]
    outs:
      - model.pt:
          cache: false
"""


def _env(**extra) -> dict:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "OMP_NUM_THREADS": "1",
           "DVC_NO_ANALYTICS": "1", "VERIFY_STAMP": "one", **extra}
    env.pop("MLFLOW_TRACKING_URI", None)
    return env


def _sh(*args, cwd):
    subprocess.run([str(a) for a in args], cwd=cwd, env=_env(), check=True, capture_output=True)


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    """The committed toy repository, built once (git init, dvc init, dvc repro, git commit)."""
    root = tmp_path_factory.mktemp("toy") / "repo"
    root.mkdir()
    for name, text in SCRIPTS.items():
        (root / name).write_text(textwrap.dedent(text).lstrip())
    (root / "dvc.yaml").write_text(DVC_YAML.lstrip())
    (root / "params.yaml").write_text("make:\n  n: 3\n")
    (root / ".gitignore").write_text("timing.json\n")
    _sh("git", "init", "-q", cwd=root)
    _sh("git", "config", "user.name", "t", cwd=root)
    _sh("git", "config", "user.email", "t@example.com", cwd=root)
    _sh(BIN / "dvc", "init", "-q", cwd=root)
    (root / ".dvcignore").write_text("timing.json\n")
    _sh(BIN / "dvc", "repro", "-q", cwd=root)
    _sh("git", "add", "-A", cwd=root)
    _sh("git", "commit", "-q", "-m", "toy", cwd=root)
    assert (root / "out/timing.json").is_file() and not (root / "data/raw.txt").is_symlink()
    return root


@pytest.fixture
def repo(toy, tmp_path) -> Path:
    """A fresh copy of the toy repository that a test may tamper with."""
    dst = tmp_path / "repo"
    shutil.copytree(toy, dst, symlinks=True)
    return dst


def verify(repo, *args, env=None):
    return CliRunner().invoke(cli, ["verify", "--repo", str(repo), *map(str, args)], env=env or {"VERIFY_STAMP": "one"})


def lines(result) -> list[str]:
    return result.stdout.strip().splitlines()


def test_all_committed_stages_identical(repo, tmp_path):
    scratch = tmp_path / "scratch"
    r = verify(repo, "--no-tracking", "--scratch", scratch)
    assert r.exit_code == 0, r.output
    out = lines(r)
    # the data stage (cached) and the training stage (not asked for) are not run
    assert [ln.split()[:2] for ln in out[:-1]] == [["identical", "make"], ["identical", "stamp"]]
    assert out[-1] == "verify: 2 identical, 0 differ, 0 failed of 2 stages (scratch: removed)"
    assert not scratch.exists()
    assert not (repo / "out/a.json").is_symlink() and subprocess.run(
        ["git", "status", "--porcelain"], cwd=repo, capture_output=True, text=True).stdout == ""


def test_tampered_json_differs_with_key_and_values(repo):
    a = repo / "out/a.json"
    a.write_text(a.read_text().replace("0.8125", "0.8126"))
    r = verify(repo, "--stages", "make", "--no-tracking")
    assert r.exit_code == 1, r.output
    assert lines(r)[0] == "differs    make: out/a.json: summary.mAA committed 0.8126 re-run 0.8125"
    assert lines(r)[-1].startswith("verify: 0 identical, 1 differ, 0 failed of 1 stages")


def test_tampered_csv_names_line_and_column(repo):
    b = repo / "out/b.csv"
    b.write_text(b.read_text().replace("1,0.5", "1,0.55"))
    r = verify(repo, "--stages", "make", "--no-tracking")
    assert r.exit_code == 1, r.output
    assert "out/b.csv: line 3, column err: committed 0.55 re-run 0.5" in lines(r)[0]


def test_extra_file_in_output_folder_differs_but_timing_is_ignored(repo):
    (repo / "out/timing.json").write_text("{}")  # ignored: a per-run sidecar
    (repo / "out/stale.txt").write_text("x")
    r = verify(repo, "--stages", "make", "--no-tracking")
    assert r.exit_code == 1 and "out: missing in re-run: stale.txt" in lines(r)[0], r.output


def test_environment_dependent_stage_differs_and_keep_leaves_logs(repo, tmp_path):
    scratch = tmp_path / "scratch"
    r = verify(repo, "--stages", "stamp,make", "--keep", "--scratch", scratch, "--no-tracking",
               env={"VERIFY_STAMP": "two"})
    assert r.exit_code == 1, r.output
    out = lines(r)
    assert out[0].startswith("identical  make  (")
    assert out[1] == "differs    stamp: stamp.txt: line 1: committed 'one' re-run 'two'"
    assert out[-1] == f"verify: 1 identical, 1 differ, 0 failed of 2 stages (scratch: {scratch})"
    assert (scratch / "logs/stamp.log").is_file() and (scratch / "rerun/stamp/stamp.txt").read_text() == "two\n"
    assert (scratch / "repo/data/raw.txt").is_symlink()  # the untracked input, linked, not copied
    assert (scratch / "repo/stamp.txt").read_text() == "one\n"  # committed output put back for later stages


def test_failing_stage_reports_its_last_line(repo):
    (repo / "stamp.py").write_text("raise SystemExit('stamp broke')\n")
    r = verify(repo, "--stages", "stamp", "--no-tracking")
    assert r.exit_code == 1 and lines(r)[0].startswith("failed     stamp: exit 1: stamp broke"), r.output


def test_sample_is_deterministic(repo):
    expected = random.Random(0).sample(["make", "stamp"], 1)[0]
    r = verify(repo, "--sample", 1, "--seed", 0, "--no-tracking")
    assert r.exit_code == 0, r.output
    assert [ln.split()[1] for ln in lines(r)[:-1]] == [expected]


def test_training_stage_only_when_asked(repo):
    r = verify(repo, "--include-train", "--no-tracking")
    assert r.exit_code == 0 and [ln.split()[1] for ln in lines(r)[:-1]] == ["make", "stamp", "train_toy"], r.output
    r = verify(repo, "--stages", "train_*", "--no-tracking")
    assert r.exit_code == 0 and lines(r)[0].startswith("identical  train_toy"), r.output


def test_unknown_stage_is_a_user_error(repo):
    assert_user_error(verify(repo, "--stages", "make,nope", "--no-tracking"), "no stage matches 'nope'")


def test_data_stage_is_refused_by_name(repo):
    assert_user_error(verify(repo, "--stages", "data", "--no-tracking"), "data cannot be verified", "DVC-cached")


def test_missing_dependency_fails_before_any_work(repo, tmp_path):
    """Through the console script: one error line naming the producing stage; no MLflow store, no scratch."""
    (repo / "data/raw.txt").unlink()
    scratch, db = tmp_path / "scratch", tmp_path / "mlflow.db"
    r = subprocess.run([sys.executable, "-c", "from rlsac.cli import main; main()", "verify", "--repo", str(repo),
                        "--stages", "make", "--scratch", str(scratch)], cwd=tmp_path, capture_output=True, text=True,
                       env=_env(MLFLOW_TRACKING_URI=f"sqlite:///{db}"))
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and r.stderr.startswith(
        "error: data/raw.txt: missing dependency of make (run `dvc repro -s data` first)"), r.stderr
    assert not db.exists() and not scratch.exists()


def test_tracking_logs_a_finished_run(repo, workdir):
    r = verify(repo, "--stages", "make", "--tracking")
    assert r.exit_code == 0, r.output
    import mlflow

    mlflow.set_tracking_uri(os.environ["MLFLOW_TRACKING_URI"])
    runs = mlflow.search_runs(experiment_names=["verify"], output_format="list")
    assert len(runs) == 1 and runs[0].info.status == "FINISHED"
    assert runs[0].data.metrics == {"n_identical": 1.0, "n_close": 0.0, "n_differs": 0.0, "n_failed": 0.0}
    assert runs[0].data.params["selected"] == "make"
    local = mlflow.artifacts.download_artifacts(run_id=runs[0].info.run_id, artifact_path="verify.json",
                                                dst_path=str(workdir / "art"))
    assert json.loads(Path(local).read_text())[0]["status"] == "identical"


def test_stages_that_train_are_told_by_their_checkpoint_or_their_name():
    """fold_select* replays a training (minutes per stage, no checkpoint written): a training stage like fold_train."""
    from rlsac.runners.verify import is_training

    assert is_training("fold_select_seed@castle-rlsac-1", ["reports/selection/hard/castle/rlsac-s1.csv"])
    assert is_training("fold_train@castle-rlsac", ["checkpoints/folds/hard/castle/rlsac.pt"])
    assert is_training("custom@x", ["model.pt"])
    assert not is_training("fold_eval@hard-castle-rlsac", ["reports/eval/folds/hard/castle/rlsac"])
    assert not is_training("experiments/quick/dvc.yaml:tables", ["reports/claims.md"])


# ------------------------------------------------------------------ another numeric platform (--tolerance, --platform)


def test_tolerance_accepts_a_json_number_within_it_and_ignores_csv_numbers(repo):
    a, b = repo / "out/a.json", repo / "out/b.csv"
    a.write_text(a.read_text().replace("0.8125", "0.8145"))  # another platform's rounding: 0.002 away
    b.write_text(b.read_text().replace("1,0.5", "1,0.73"))  # a per-instance error: any amount
    r = verify(repo, "--stages", "make", "--no-tracking", "--tolerance", "0.005")
    assert r.exit_code == 0, r.output
    assert lines(r)[0].startswith("close      make")
    assert "every JSON number within 0.005 (out/a.json: summary.mAA committed 0.8145 re-run 0.8125)" in lines(r)[0]
    assert lines(r)[-1].startswith("verify: 0 identical, 1 close, 0 differ, 0 failed of 1 stages")


def test_tolerance_refuses_a_number_past_it_and_any_other_change(repo):
    a = repo / "out/a.json"
    a.write_text(a.read_text().replace("0.8125", "0.8185"))
    r = verify(repo, "--stages", "make", "--no-tracking", "--tolerance", "0.005")
    assert r.exit_code == 1, r.output
    assert lines(r)[0] == ("differs    make: out/a.json: summary.mAA committed 0.8185 re-run 0.8125 "
                           "(tolerance 0.005)")
    a.write_text(a.read_text().replace("0.8185", "0.8125").replace('"n": 3', '"n": 4'))
    assert "summary.n committed 4 re-run 3" in lines(verify(repo, "--stages", "make", "--no-tracking",
                                                           "--tolerance", "0.005"))[0]
    a.write_text(a.read_text().replace('"n": 4', '"n": 3, "extra": 1'))  # a key the re-run does not write
    assert "summary.extra committed 1 re-run (absent) (tolerance 0.005)" in lines(
        verify(repo, "--stages", "make", "--no-tracking", "--tolerance", "0.005"))[0]
    b = repo / "out/b.csv"
    a.write_text(a.read_text().replace('"n": 3, "extra": 1', '"n": 3'))
    b.write_text(b.read_text() + "3,1.0\n")  # a row more is no rounding
    r = verify(repo, "--stages", "make", "--no-tracking", "--tolerance", "0.005")
    assert r.exit_code == 1 and "out/b.csv: committed has 5 rows, re-run 4" in lines(r)[0], r.output


def test_bad_tolerance_is_a_user_error(repo):
    assert_user_error(verify(repo, "--stages", "make", "--no-tracking", "--tolerance", "-1"), "--tolerance")


def test_bad_options_fail_before_the_platform_note_and_with_platform(repo):
    """A user error is the only line printed (no platform note before it); --platform takes no other option; a folder
    inside the repository is not a repository (DVC would look upward and verify the enclosing one)."""
    _record(repo, cpu_vendor="SomeOtherVendor")
    r = verify(repo, "--stages", "nosuch", "--no-tracking")
    assert_user_error(r, "no stage matches 'nosuch'")
    assert "note:" not in r.output
    assert_user_error(verify(repo, "--platform", "--tolerance", "-1", "--no-tracking"), "it takes no --tolerance")
    assert_user_error(verify(repo, "--platform", "--stages", "nosuch", "--no-tracking"), "it takes no --stages")
    (repo / "sub").mkdir()
    assert_user_error(verify(repo / "sub", "--stages", "make", "--no-tracking"), "not a DVC repository's root")


def _record(repo, **over):
    from rlsac import numerics

    rec = {**{k: v for k, v in numerics.describe().items() if k in ("numerics", *numerics.KEYS)}, **over}
    (repo / "reports").mkdir(exist_ok=True)
    (repo / numerics.RECORD).write_text(json.dumps(rec))


def test_platform_same_and_other(repo):
    _record(repo)
    r = verify(repo, "--platform", "--no-tracking")
    assert r.exit_code == 0 and lines(r)[-1] == "platform: the record's", r.output
    _record(repo, machine="riscv64", aten_capability="AVX-9")  # fields that decide in either numeric mode
    r = verify(repo, "--platform", "--no-tracking")
    assert r.exit_code == 1, r.output
    assert "machine riscv64 -> " in lines(r)[-1] and "aten_capability AVX-9 -> " in lines(r)[-1]
    # a run on another platform says so before its first stage, and still compares bytes
    r = verify(repo, "--stages", "make", "--no-tracking")
    assert r.exit_code == 0 and lines(r)[0].startswith("note: this machine's numeric platform is not the record's")


def test_platform_record_missing_or_malformed_is_a_user_error(repo):
    assert_user_error(verify(repo, "--platform", "--no-tracking"), "cannot read the record's platform")
    (repo / "reports").mkdir()
    (repo / "reports/platform.json").write_text('{"machine": "x86_64"}')
    assert_user_error(verify(repo, "--platform", "--no-tracking"), "needs the string keys")


def test_mkl_family_reads_the_branch_mkl_names():
    from rlsac.numerics import mkl_family

    assert mkl_family("Intel(R) Advanced Vector Extensions 512 (Intel(R) AVX-512) with support of Intel(R) Deep "
                      "Learning Boost (Intel(R) DL Boost) and bfloat16") == "AVX-512"
    assert mkl_family("Intel(R) Advanced Vector Extensions 2 (Intel(R) AVX2) enabled processors") == "AVX2"
    assert mkl_family("Intel(R) Architecture processors") == "generic"
    assert mkl_family("something new") == "unknown"


def test_this_machines_platform_is_described():
    import torch

    from rlsac.numerics import describe

    d = describe()
    assert d["aten_capability"] == torch.backends.cpu.get_cpu_capability()
    # torch's CPU wheels are built with MKL: its verbose line must be found (else every platform compares alike)
    assert d["mkl_branch"] in ("AVX-512", "AVX2", "AVX", "SSE4.2", "generic") and d["mkl_branch_text"]


def test_workers_two_gives_the_serial_verdicts(repo):
    serial, parallel = verify(repo, "--no-tracking"), verify(repo, "--no-tracking", "--workers", 2)
    assert serial.exit_code == parallel.exit_code == 0, parallel.output
    # stages report as they finish: the same lines but their times, the summary last
    untimed = lambda r: sorted(re.sub(r"\(\d+\.\d s\)", "", ln) for ln in lines(r)[:-1])  # noqa: E731
    assert untimed(parallel) == untimed(serial) and lines(parallel)[-1] == lines(serial)[-1]
    (repo / "out" / "a.json").write_text("{}")  # a tampered output is found with two workers too
    r = verify(repo, "--no-tracking", "--workers", 2)
    assert r.exit_code == 1 and any(ln.split()[:2] == ["differs", "make:"] for ln in lines(r)), r.output
    assert_user_error(verify(repo, "--no-tracking", "--workers", 0), "--workers")


def test_stages_that_read_or_write_one_anothers_outputs_never_run_at_once():
    from rlsac.runners.verify import _overlap

    make = {"deps": ["data/raw.txt", "make.py"], "outs": ["out"]}
    table = {"deps": ["out/a.json"], "outs": ["reports/t.md"]}
    stamp = {"deps": ["stamp.py"], "outs": ["stamp.txt"]}
    assert _overlap(make, table) and _overlap(table, make)  # an output folder and a file in it, either way round
    assert not _overlap(make, stamp) and not _overlap(stamp, table)
    assert not _overlap({"deps": [], "outs": ["out2"]}, {"deps": ["out/a.json"], "outs": []})  # a prefix, no folder
    assert _overlap({"deps": [], "outs": ["x.csv"]}, {"deps": [], "outs": ["x.csv"]})
