"""A stage that fails or is interrupted leaves its outputs as they were (rlsac.dvc_stage.set_aside / restore): DVC
deletes a stage's outputs before its command, so a failed or cancelled stage of `rlsac pipeline` deleted committed
files (seen: an interrupted `fold_data_points` stage took two tracked reports/folds/data JSON files with it)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path

import yaml
from test_ray_pipeline import _env, make_repo  # tests/ is on sys.path (pytest prepend mode)

from rlsac import dvc_stage
from rlsac.pipeline import _restore_interrupted, load_plan


def _repo(path: Path, cmd: str) -> Path:
    """A DVC repository (made on first use) whose one stage ``a`` runs ``cmd`` and outputs a.txt and the folder out."""
    stages = {"a": {"cmd": cmd, "outs": ["a.txt", "out"]}}
    if not (path / ".dvc").exists():
        return make_repo(path, stages)
    (path / "dvc.yaml").write_text(yaml.safe_dump({"stages": stages}, sort_keys=False))
    return path


WRITE = ("python -c \"import os; os.makedirs('out', exist_ok=True); open('out/x','w').write('{0}'); "
         "open('a.txt','w').write('{0}')\"")
FAIL = "python -c \"import sys; open('a.txt','w').write('part'); sys.exit('error: a broke here')\""


def _run(repo: Path) -> dict:
    plan = load_plan(repo, runner="direct")
    return dvc_stage.run(str(plan["root"]), plan["specs"]["a"], _env(), str(repo / "a.log"))


def test_a_failed_stage_leaves_its_outputs_as_they_were(tmp_path):
    repo = _repo(tmp_path / "repo", WRITE.format("good"))
    assert _run(repo)["status"] == "done"
    assert (repo / "a.txt").read_text() == "good" and (repo / "out" / "x").read_text() == "good"
    assert not list((repo / dvc_stage.ASIDE).iterdir())  # nothing kept aside after a stage that succeeded

    _repo(repo, FAIL)  # a changed command that writes part of one output, then fails
    r = _run(repo)
    assert r["status"] == "failed" and "a broke here" in r["error"]
    assert (repo / "a.txt").read_text() == "good" and (repo / "out" / "x").read_text() == "good"
    assert not list((repo / dvc_stage.ASIDE).iterdir())


def test_a_failed_first_run_leaves_no_part_written_output(tmp_path):
    repo = _repo(tmp_path / "repo", FAIL)
    assert _run(repo)["status"] == "failed"
    assert not (repo / "a.txt").exists() and not (repo / "out").exists()


def test_an_interrupted_stage_gets_its_outputs_back_once_its_command_ended(tmp_path):
    repo = _repo(tmp_path / "repo", WRITE.format("good"))
    assert _run(repo)["status"] == "done"
    _repo(repo, WRITE.format("new"))
    plan = load_plan(repo, runner="direct")
    spec = plan["specs"]["a"]
    # what a worker does before its command, then the command still running (a group of its own) when the driver
    # is interrupted: the restore waits for it, so nothing it writes afterwards survives
    from dvc.repo import Repo

    with contextlib.chdir(repo), Repo(".") as r:
        stage = r.stage.collect("a")[0]
        aside = dvc_stage.set_aside(stage, str(repo), spec)
    assert not (repo / "a.txt").exists()
    cmd = "import time; time.sleep(1.5); open('a.txt','w').write('late')"
    proc = subprocess.Popen([sys.executable, "-c", cmd], cwd=repo, start_new_session=True)
    dvc_stage._note_pid(aside, proc.pid)
    _restore_interrupted(plan, ["a"])
    assert proc.poll() is not None  # waited for the command to end
    assert (repo / "a.txt").read_text() == "good" and (repo / "out" / "x").read_text() == "good"
    assert not aside.exists()
