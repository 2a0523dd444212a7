"""Warm stage commands (rlsac.runners.warm, issue #63 item 8): a stage command forked from a warm process writes
the bytes, the log and the exit status a cold one does; anything a shell would expand starts cold; a caller that
goes away before "go" leaves a child that never ran."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from rlsac.runners import warm
from rlsac.runners.dvc_stage import python_bin_env
from rlsac.runners.stage_task import start_guarded

ROOT = Path(__file__).resolve().parents[1]


def synth(out: Path, extra: str = "") -> list[str]:
    return ["/bin/sh", "-c", f"rlsac synth-lines --outlier 0.6 --n-instances 12 --n-points 40 --seed 5 "
                             f"--out {out} --no-tracking{extra}"]


def run(argv, log: Path, start, **kw):
    with open(log, "wb") as f:
        f.write(b"> the runner's line before the command\n")
        f.flush()
        proc = start(argv, cwd=str(ROOT), env=python_bin_env({}), stdout=f, stderr=subprocess.STDOUT,
                     stdin=subprocess.DEVNULL, close_fds=True, **kw)
        rc = proc.wait()
        f.write(b"the runner's line after it\n")  # after the command's output, as DVC's error line is
        return proc, rc


def warm_start(argv, **kw):
    return warm.start(argv, lambda pgid: None, start_guarded, **kw)


@pytest.fixture(autouse=True)
def fresh_server():
    warm.stop()
    yield
    warm.stop()


def test_warm_stage_writes_the_cold_bytes_and_log(tmp_path):
    cold, rc_cold = run(synth(tmp_path / "cold.h5"), tmp_path / "cold.log", start_guarded)
    hot, rc_hot = run(synth(tmp_path / "warm.h5"), tmp_path / "warm.log", warm_start)
    assert isinstance(hot, warm.WarmProcess) and rc_cold == rc_hot == 0
    assert (tmp_path / "warm.h5").read_bytes() == (tmp_path / "cold.h5").read_bytes()
    norm = lambda p: p.read_text().replace("warm.h5", "X").replace("cold.h5", "X")  # noqa: E731
    assert norm(tmp_path / "warm.log") == norm(tmp_path / "cold.log") != ""
    # the same warm process serves the next stage: a second fork, same bytes
    server = warm._get()
    again, rc = run(synth(tmp_path / "again.h5"), tmp_path / "again.log", warm_start)
    assert rc == 0 and warm._get() is server
    assert (tmp_path / "again.h5").read_bytes() == (tmp_path / "cold.h5").read_bytes()


def test_exit_status_and_error_as_cold(tmp_path):
    argv = ["/bin/sh", "-c", "rlsac synth-lines --outlier 2 --no-tracking"]
    _, rc_cold = run(argv, tmp_path / "cold.log", start_guarded)
    hot, rc_hot = run(argv, tmp_path / "warm.log", warm_start)
    assert isinstance(hot, warm.WarmProcess)
    assert rc_hot == rc_cold == 2
    assert (tmp_path / "warm.log").read_text() == (tmp_path / "cold.log").read_text()
    assert (tmp_path / "warm.log").read_text().splitlines()[1:] == [
        "error: outlier rate must be in [0, 1), got 2.0", "the runner's line after it"]


def test_shell_syntax_other_programs_and_opt_out_start_cold(tmp_path):
    env = python_bin_env({})
    assert warm.rlsac_args(["/bin/sh", "-c", "rlsac table --x 1"], env) == ["table", "--x", "1"]
    for cmd in ("rlsac table > out.md", "rlsac plot $X", "rlsac a && rlsac b", "rlsac x*", "python -m rlsac",
                "dvc repro", "OMP_NUM_THREADS=2 rlsac table"):
        assert warm.rlsac_args(["/bin/sh", "-c", cmd], env) is None, cmd
    assert warm.rlsac_args(["/usr/bin/env", "-c", "rlsac table"], env) is None
    # an `rlsac` on PATH that is not this interpreter's
    assert warm.rlsac_args(["/bin/sh", "-c", "rlsac table"], {**env, "PATH": "/usr/bin"}) is None
    calls = []

    def cold(argv, **kw):
        calls.append(argv)
        return subprocess.Popen(["true"])

    warm.start(["/bin/sh", "-c", "rlsac table > x"], lambda p: None, cold, env=env, stdout=sys.stdout,
               stderr=subprocess.STDOUT)
    warm.start(["/bin/sh", "-c", "rlsac table"], lambda p: None, cold, env={**env, warm.ENV: "0"},
               stdout=sys.stdout, stderr=subprocess.STDOUT)
    assert len(calls) == 2 and warm._get() is None


def test_a_caller_gone_before_go_leaves_a_child_that_never_ran(tmp_path):
    def failing_guard(pgid):
        raise RuntimeError("the worker went away")

    out = tmp_path / "never.h5"
    with open(tmp_path / "log", "wb") as f, pytest.raises(RuntimeError):
        warm.start(synth(out), failing_guard, start_guarded, cwd=str(ROOT), env=python_bin_env({}), stdout=f,
                   stderr=subprocess.STDOUT)
    assert warm._get() is None and not out.exists()
    # the next stage gets a new warm process
    hot, rc = run(synth(tmp_path / "next.h5"), tmp_path / "next.log", warm_start)
    assert isinstance(hot, warm.WarmProcess) and rc == 0 and (tmp_path / "next.h5").exists()


def test_stop_all_ends_a_stage_command_still_running(tmp_path):
    """An interrupted caller (rlsac verify's Ctrl-C) ends its warm processes' running commands, as a cold child would
    have ended on the terminal's signal: the threads waiting on them return."""
    import threading
    import time

    argv = synth(tmp_path / "long.h5").copy()
    argv[-1] = argv[-1].replace("--n-instances 12", "--n-instances 5000000")
    with open(tmp_path / "log", "wb") as f:
        proc = warm_start(argv, cwd=str(ROOT), env=python_bin_env({}), stdout=f, stderr=subprocess.STDOUT)
        got = []
        waiter = threading.Thread(target=lambda: got.append(proc.wait()))
        waiter.start()
        time.sleep(2.0)
        assert not got  # still running
        warm.stop_all()
        waiter.join(timeout=20)
    assert got and got[0] != 0 and not (tmp_path / "long.h5").exists()
    with pytest.raises(ProcessLookupError):
        os.killpg(proc.pid, 0)
