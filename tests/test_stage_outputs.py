"""A stage that fails or is interrupted leaves its outputs as they were (rlsac.runners.dvc_stage.set_aside / restore):
DVC deletes a stage's outputs before its command, so a failed or cancelled stage of `rlsac pipeline` deleted committed
files (seen: an interrupted `fold_data_points` stage took two tracked reports/folds/data JSON files with it)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import yaml
from test_ray_pipeline import _env, make_repo  # tests/ is on sys.path (pytest prepend mode)

from rlsac.runners import dvc_stage
from rlsac.runners.plan import load_plan
from rlsac.runners.recovery import _restore_interrupted


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


def _dead_pid() -> int:
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(proc.stdout)


def _left_by_a_killed_driver(repo: Path) -> Path:
    """The state a SIGKILLed `rlsac pipeline` leaves (issue #64): a stage's committed outputs set aside by a worker
    that died with the driver, and a part-written output of its command in their place."""
    import json

    from dvc.repo import Repo

    with contextlib.chdir(repo), Repo(".") as r:
        stage = r.stage.collect("a")[0]
        aside = dvc_stage.set_aside(stage, str(repo), dvc_stage.stage_spec(stage, repo))
    owner = json.loads((aside / "owner.json").read_text())
    (aside / "owner.json").write_text(json.dumps({**owner, "pid": _dead_pid()}))
    (repo / "a.txt").write_text("part")
    return aside


def _committed_repo(path: Path) -> Path:
    from test_ray_pipeline import dvc

    repo = _repo(path, WRITE.format("good"))
    assert dvc(repo, "repro").returncode == 0  # dvc.lock: the stage is up to date
    return repo


def test_the_next_pipeline_puts_back_what_a_killed_driver_set_aside(tmp_path, monkeypatch):
    """A SIGKILLed driver's set-aside outputs stayed missing until the stage ran again: the next `rlsac pipeline`
    puts them back first (the stage is then up to date: nothing runs), what the command had written goes."""
    from click.testing import CliRunner

    from rlsac.cli import cli

    repo = _committed_repo(tmp_path / "repo")
    aside = _left_by_a_killed_driver(repo)
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(cli, ["pipeline", "--repo", "repo", "--no-tracking"])
    assert r.exit_code == 0, (r.output, r.exception)
    assert "2 set-aside outputs restored (a.txt, out)" in r.output and "0 done, 1 skipped" in r.output, r.output
    assert (repo / "a.txt").read_text() == "good" and (repo / "out" / "x").read_text() == "good"
    assert not aside.exists()


def test_recover_puts_back_dead_drivers_outputs_only_and_ends_their_ray_processes(tmp_path, monkeypatch):
    """`rlsac pipeline --recover`: a dead worker's set-aside folder is restored, a live one's is left to it; the
    processes of a dead driver's local Ray cluster (its agents outlived it) are ended by the session's name."""
    import json
    import uuid

    from click.testing import CliRunner

    from rlsac.cli import cli
    from rlsac.runners.recovery import DRIVERS

    repo = _committed_repo(tmp_path / "repo")
    dead = _left_by_a_killed_driver(repo)
    live = repo / dvc_stage.ASIDE / "0123456789abcdef"  # another stage's, of a worker still running (this process)
    live.mkdir()
    (live / "manifest.json").write_text(json.dumps([[str(repo / "b.txt"), None]]))
    (live / "owner.json").write_text(json.dumps(dvc_stage._owner()))
    session = f"session_test_{uuid.uuid4().hex}"
    agent = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)", f"--session-dir=/tmp/{session}"])
    (repo / DRIVERS).mkdir(parents=True)
    (repo / DRIVERS / "1.json").write_text(json.dumps({"owner": {**dvc_stage._owner(), "pid": _dead_pid()},
                                                       "session": session}))
    monkeypatch.chdir(tmp_path)
    try:
        r = CliRunner().invoke(cli, ["pipeline", "--recover", "--repo", "repo"])
        assert r.exit_code == 0, (r.output, r.exception)
        assert "2 set-aside outputs restored (a.txt, out)" in r.output and "1 Ray processes" in r.output, r.output
        assert agent.wait(timeout=10) is not None
    finally:
        agent.kill()
    assert (repo / "a.txt").read_text() == "good" and not dead.exists() and live.exists()
    assert not (repo / DRIVERS / "1.json").exists()
    r = CliRunner().invoke(cli, ["pipeline", "--recover", "--repo", "repo"])
    assert r.exit_code == 0 and "nothing to recover" in r.output, r.output
    r = CliRunner().invoke(cli, ["pipeline", "--recover", "--repo", str(tmp_path / "no-repo")])
    assert r.exit_code == 2 and "not in a DVC repository" in r.stderr, r.output


def _zombie_group_leader() -> subprocess.Popen:
    """A process group whose only member has exited but was never reaped (a zombie): what an orphaned stage shell
    leaves where PID 1 reaps nothing (docker without --init, the official CI's sandbox). ``wait()`` it afterwards."""
    import signal
    import time

    import psutil

    proc = subprocess.Popen(["sleep", "60"], start_new_session=True)
    os.kill(proc.pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while psutil.Process(proc.pid).status() != psutil.STATUS_ZOMBIE and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, 0)  # for killpg the group is still there
    return proc


def test_a_group_left_with_only_a_zombie_has_ended():
    from rlsac.runners.process_group import group_alive

    proc = subprocess.Popen(["sleep", "60"], start_new_session=True)
    try:
        assert group_alive(proc.pid)
    finally:
        proc.kill()
        proc.wait()
    assert not group_alive(proc.pid)
    zombie = _zombie_group_leader()
    try:
        assert not group_alive(zombie.pid)
    finally:
        zombie.wait()


def test_recover_does_not_wait_on_a_command_that_left_only_a_zombie(tmp_path):
    """The official CI's failure (a SIGKILLed pipeline, then `--recover`: "nothing to recover"): the stage's shell,
    orphaned by its dead worker, exited unreaped; killpg still found its group, so the outputs stayed set aside."""
    from rlsac.runners.recovery import recover

    repo = _committed_repo(tmp_path / "repo")
    aside = _left_by_a_killed_driver(repo)
    zombie = _zombie_group_leader()
    try:
        dvc_stage._note_pid(aside, zombie.pid)
        r = recover(repo)
    finally:
        zombie.wait()
    assert sorted(r["outputs"]) == ["a.txt", "out"], r  # before: 15 s waited on the zombie, then left set aside
    assert (repo / "a.txt").read_text() == "good" and not aside.exists()


def test_recover_ends_a_dead_workers_command_its_guard_did_not(tmp_path):
    """A dead worker's command still running after the wait (its guard gone too): nothing would record what it
    writes, so recover ends it and puts the outputs back (before: left set aside, "nothing to recover")."""
    from rlsac.runners.recovery import recover

    repo = _committed_repo(tmp_path / "repo")
    aside = _left_by_a_killed_driver(repo)
    proc = subprocess.Popen(["sleep", "120"], start_new_session=True)
    try:
        dvc_stage._note_pid(aside, proc.pid)
        r = dvc_stage.recover(repo, wait_s=0.5)
        assert proc.wait(timeout=10) == -15  # SIGTERM: it could end its run as an interrupted rlsac command does
    finally:
        proc.kill()
        proc.wait()
    assert sorted(r) == [str(repo / "a.txt"), str(repo / "out")], r
    assert (repo / "a.txt").read_text() == "good" and not aside.exists()
    assert recover(repo) == {"processes": 0, "outputs": []}


LATE = """import subprocess, sys
subprocess.Popen([sys.executable, "-c", "import time; time.sleep(1.5); open('a.txt', 'w').write('late')"])
sys.exit(1)
"""


def test_a_failed_stage_ends_what_its_command_left_running_before_restoring(tmp_path):
    """A failed command whose child lives on (a Ray worker ending gracefully kills the stage's shell, not the shell's
    child): the child wrote after the restore, so the failed stage changed a committed file. Its process group is
    ended first now (rlsac.runners.process_group.end_group)."""
    import time

    from rlsac.runners.stage_task import start_guarded

    repo = _repo(tmp_path / "repo", WRITE.format("good"))
    assert _run(repo)["status"] == "done"
    (repo / "late.py").write_text(LATE)
    _repo(repo, "python late.py")
    plan = load_plan(repo, runner="direct")
    r = dvc_stage.run(str(plan["root"]), plan["specs"]["a"], _env(), str(repo / "a.log"), start=start_guarded)
    assert r["status"] == "failed", r
    time.sleep(2.5)  # past the child's write, had it lived
    assert (repo / "a.txt").read_text() == "good" and (repo / "out" / "x").read_text() == "good"
    assert not list((repo / dvc_stage.ASIDE).iterdir())


def test_recover_removes_what_a_cut_short_removal_left(tmp_path):
    """A worker killed while it removed its aside folder (after putting the outputs back) left part of it: renamed
    first (``*.gone``), it holds nothing anyone needs, and recover removes it."""
    top = tmp_path / dvc_stage.ASIDE
    (top / f"0123456789abcdef.4242{dvc_stage.GONE}").mkdir(parents=True)
    (top / f"0123456789abcdef.4242{dvc_stage.GONE}" / "pid").write_text("")
    assert dvc_stage.recover(tmp_path) == [] and not list(top.iterdir())
