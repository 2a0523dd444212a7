"""Whether a stage command's process group still runs: a member that has exited but was never reaped (a zombie)
does not count.

``os.killpg(pgid, 0)`` succeeds while any member exists, zombies included. A stage's shell outlives its Ray worker
as an orphan, and an orphan's exit is reaped by PID 1 or the nearest subreaper: in a container whose PID 1 reaps
nothing (``docker run`` without ``--init``, some CI sandboxes) the group never ended for ``killpg``, and a killed
pipeline's set-aside outputs were never put back (`rlsac pipeline --recover`: "nothing to recover").
"""

from __future__ import annotations

import os
import signal
import time

import psutil


def group_alive(pgid: int) -> bool:
    """Whether process group ``pgid`` has a member that runs (any state but zombie or dead). A group of another
    user's is treated as ended: its id is not ours."""
    try:
        os.killpg(pgid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    for p in psutil.process_iter():
        try:
            if os.getpgid(p.pid) == pgid and p.status() not in (psutil.STATUS_ZOMBIE, psutil.STATUS_DEAD):
                return True
        except (ProcessLookupError, psutil.Error):
            continue  # it ended while we looked
    return False


def wait_group(pgid: int, wait_s: float) -> bool:
    """Wait up to ``wait_s`` for process group ``pgid`` to end. -> whether it has ended."""
    end = time.monotonic() + wait_s
    while group_alive(pgid):
        if time.monotonic() >= end:
            return False
        time.sleep(0.2)
    return True


def end_group(pgid: int, wait_s: float = 0.0, grace_s: float = 5.0) -> bool:
    """Wait up to ``wait_s`` for process group ``pgid`` to end by itself (a guard is ending it), then end it: SIGTERM,
    ``grace_s`` to exit (an rlsac command ends its run KILLED), SIGKILL. -> whether it has ended."""
    if wait_group(pgid, wait_s):
        return True
    for sig, grace in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 2.0)):
        try:
            os.killpg(pgid, sig)
        except (ProcessLookupError, PermissionError):
            return True
        if wait_group(pgid, grace):
            return True
    return False
