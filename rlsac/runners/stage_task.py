"""One stage as a Ray task's body: its command started guarded (a process group that ends with its
worker) and warm where it can (rlsac.runners.warm), its log, and its result."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

LOG_DIR = Path("logs") / "pipeline"


_ERROR_LINE = re.compile(r"^(error\b|ERROR\b|[A-Za-z_][\w.]*(Error|Exception|Interrupt)\b)")


_SKIPPED = re.compile(r"Stage '.*' didn't change, skipping")


KILL_GRACE_S = 10.0


_GUARD = """
import os, sys, time
import psutil
sys.path.append(sys.argv[4])  # last, for a worker that found rlsac where a new interpreter would not
from rlsac.runners.process_group import end_group, group_alive
pgid, worker, grace = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
if os.fork():  # detach: Ray kills a dead worker's direct children, which would take this guard with them
    os._exit(0)
os.setsid()

def alive(pid):
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False

while alive(worker):
    if not group_alive(pgid):  # the stage ended: nothing to guard (a zombie member left does not count)
        sys.exit(0)
    time.sleep(0.5)
end_group(pgid, grace_s=grace)  # SIGTERM, the grace, SIGKILL
"""


def first_error_line(text: str) -> str:
    """The first line that reads as an error (``error: ...`` of an rlsac command, the ``XxxError: ...`` line that
    ends a traceback, DVC's ``ERROR: ...``), else the last non-empty line."""
    lines = [ln.rstrip() for ln in text.splitlines() if ln.strip()]
    for ln in lines:
        if _ERROR_LINE.match(ln):
            return ln.strip()
    return lines[-1].strip() if lines else "(no output)"


def start_guarded(argv: list[str], **kwargs) -> subprocess.Popen:
    """``subprocess.Popen(argv, **kwargs)`` in a process group of its own, stdin /dev/null, watched by the guard: it
    ends the group if this worker dies, and itself once the group is gone. The command starts once the guard
    watches (a shell reads a line from a pipe on its stdin, then execs it): a stage that ended its worker at once
    outlived it otherwise; if this worker dies first, the pipe closes and the command never starts."""
    kwargs.pop("stdin", None)
    ready, go = os.pipe()
    try:
        proc = subprocess.Popen(["/bin/sh", "-c", 'read _ || exit 111; exec "$@" </dev/null', "sh", *argv],
                                stdin=ready, start_new_session=True, **kwargs)
        guard(proc.pid)
        os.write(go, b"\n")
    finally:
        os.close(ready)
        os.close(go)
    return proc


def guard(pgid: int) -> None:
    """Start the guard of process group ``pgid`` (a stage command's session): it ends the group if this worker
    dies, and itself once the group is gone; it watches when this returns."""
    here = str(Path(__file__).resolve().parents[2])  # the tree this rlsac is in: the guard imports from it
    subprocess.run([sys.executable, "-c", _GUARD, str(pgid), str(os.getpid()), str(KILL_GRACE_S), here],
                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def start_stage_command(argv: list[str], **kwargs):
    """How the direct runner starts a stage's command line: warm where it is a plain ``rlsac ...`` call
    (rlsac.runners.warm: the imports done once per worker), else start_guarded; guarded either way."""
    from rlsac.runners import warm

    return warm.start(argv, guard, start_guarded, **kwargs)


def _error(rc: int | None, log: str) -> str:
    return _error_text(rc, Path(log).read_text(errors="replace"))


def run_stage(root: str, address: str, env: dict[str, str], log: str) -> dict:
    """Run ``dvc --wait-for-lock repro -s <address>`` in ``root`` (the dvc runner: a Ray task's body; plain Python
    too). -> {stage, status (done / skipped / failed), seconds, rc, error, log, node}."""
    import socket

    from rlsac.runners.dvc_stage import python_bin_env

    Path(log).parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with open(log, "wb") as f:
        proc = start_guarded([sys.executable, "-m", "dvc", "--wait-for-lock", "repro", "-s", address], cwd=root,
                             env=python_bin_env(env), stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        rc = proc.wait()
    seconds = time.time() - t0
    status = "failed" if rc else "skipped" if _SKIPPED.search(Path(log).read_text(errors="replace")) else "done"
    return {"stage": address, "status": status, "seconds": seconds, "rc": rc, "error": _error(rc, log) if rc else None,
            "log": log, "node": socket.gethostname()}


def run_direct(root: str, address: str, spec: dict, env: dict[str, str], log: str) -> dict:
    """Run the stage's own command in ``root`` and compute its lock entry (the direct runner,
    rlsac.runners.dvc_stage.run: a
    Ray task's body; plain Python too). -> run_stage's result with "entry" and "ignore" for the driver's writer."""
    from rlsac.runners.dvc_stage import python_bin_env
    from rlsac.runners.dvc_stage import run as run_direct_stage

    r = run_direct_stage(root, spec, python_bin_env(env), log, start=start_stage_command)
    r["stage"] = address
    if r["status"] == "failed":
        r["error"] = _error(r["rc"], log)
    return r


def run_remote(conf: dict, tree: str, address: str, spec: dict, deps: list[dict], env: dict[str, str],
               log: str, sub: str = ".") -> dict:
    """The direct runner on a node that shares no folder with the driver (``--remote``,
    rlsac.runners.transfer.run_on_node:
    a Ray task's body). ``log``: its path from the repository root. -> run_direct's result with "outs" (what the
    driver brings back), "log_text" and "ignore" as paths from the root, "out_bytes", "node_id" (Ray's), and
    "downloads" and "cache_hits" (rlsac.runners.transfer.NodeCache)."""
    from rlsac.runners.dvc_stage import python_bin_env
    from rlsac.runners.dvc_stage import run as run_direct_stage
    from rlsac.runners.transfer import run_on_node

    def run(root: str, spec: dict, env: dict[str, str], log: str) -> dict:
        return run_direct_stage(root, spec, python_bin_env(env), log, start=start_stage_command)

    r = run_on_node(conf, tree, spec, deps, env, log, run, sub)
    r["stage"] = address
    with contextlib.suppress(Exception):  # the node its dependents prefer (its cache holds the outputs): a Ray task
        import ray

        r["node_id"] = ray.get_runtime_context().get_node_id()
    if r["status"] == "failed":
        r["error"] = _error_text(r["rc"], r["log_text"])
    return r


def _error_text(rc: int | None, text: str) -> str:
    line = first_error_line(text)
    return f"killed by {signal.Signals(-rc).name}: {line}" if rc and rc < 0 else line
