"""Stage commands started warm: one process per pipeline worker imports what ``rlsac`` commands import, once, and
forks a child for each stage command that is a single ``rlsac ...`` call (issue #63 item 8).

A cold stage spends about 3.5 s importing torch, OpenCV, h5py, pandas and MLflow's SQL store before its first line
of work; the quick profile's 217 stages spent more time importing than computing. The child of the warm process is
the program a shell would have started: the stage's environment, working directory, stdin /dev/null, stdout and
stderr to its log, a session of its own (the guard's process group), the interpreter's own exit (atexit handlers,
buffered output flushed) and the shell's exit status (a signal as its negative number). The numeric pins
(rlsac.numerics) are in the environment before torch loads, in the warm process as in a cold one, so a warm stage
writes a cold one's bytes (tests/test_warm.py compares them).

A command line with anything a shell would expand (``$``, globs, pipes, redirections), a program other than this
interpreter's ``rlsac``, or an environment other than the warm process's (apart from DVC_ROOT and DVC_STAGE, which
no module reads at import) starts cold, through the caller's ``start``, as does every stage off Linux.
``RLSAC_WARM=0`` starts every stage cold.

Protocol (JSON lines on the warm process's stdin and stdout): a request {args, cwd, env, log} is answered
{"pid"} once the child has its own session; the caller starts its guard on that process group and answers "go"
(the child runs) or closes the pipe (the child exits 111 without running, as start_guarded's shell does); the warm
process then answers {"rc"} when the child has ended.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Callable

from rlsac import numerics

ENV = "RLSAC_WARM"  # "0": every stage command starts cold
# the variables DVC sets per stage (dvc.stage.run.prepare_kwargs); nothing reads them at import
PER_STAGE = ("DVC_ROOT", "DVC_STAGE")
# what most stage commands import (-X importtime of `rlsac folds`, `rlsac evaluate`, `rlsac train`); matplotlib is
# left out: `rlsac plot` picks its backend before pyplot loads
PRELOAD = ("numpy", "torch", "cv2", "h5py", "pandas", "scipy.stats", "kornia", "mlflow",
           "mlflow.store.tracking.sqlalchemy_store", "rlsac.cli", "rlsac.tracking", "rlsac.config",
           "rlsac.data.lines", "rlsac.evaluation.evaluate", "rlsac.evaluation.train", "rlsac.experiments.folds",
           "rlsac.experiments.scale")
# a shell expands these (variables, globs, braces, home, pipes, lists, redirections, subshells, escapes, comments)
SHELL_CHARS = frozenset("$`\\*?[]{}~|&;<>()#\n")
NOT_STARTED = 111  # the exit status of a child whose caller went away before "go" (start_guarded's shell's)


def rlsac_args(argv: list[str], env: dict[str, str]) -> list[str] | None:
    """The arguments of ``rlsac`` if ``argv`` is ``[shell, (options), "-c", "rlsac ..."]`` with nothing for the
    shell to expand and ``rlsac`` on the environment's PATH is this interpreter's; None otherwise (start cold)."""
    if len(argv) < 3 or argv[-2] != "-c" or Path(argv[0]).name not in ("sh", "bash", "zsh", "dash"):
        return None
    cmd = argv[-1]
    if SHELL_CHARS & set(cmd):
        return None
    try:
        words = shlex.split(cmd)
    except ValueError:
        return None
    if not words or words[0] != "rlsac":
        return None
    import shutil

    found = shutil.which("rlsac", path=env.get("PATH"))
    if found is None or Path(found).resolve() != (Path(sys.executable).parent / "rlsac").resolve():
        return None
    return words[1:]


def _base(env: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in env.items() if k not in PER_STAGE}


class WarmProcess:
    """What ``start`` returns for a warm stage: the child's ``pid`` and ``wait()`` -> its exit status (Popen's)."""

    def __init__(self, server: Server, pid: int, out):
        self.server, self.pid, self.returncode, self.out = server, pid, None, out

    def wait(self) -> int:
        if self.returncode is None:
            try:
                reply = self.server.read()
            except BaseException:  # interrupted (Ctrl-C, a cancelled task): the child goes too, as subprocess.run's
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(self.pid, signal.SIGKILL)
                self.server.close()
                raise
            # the warm process died while the child ran: its status is lost, the stage counts as killed
            self.returncode = int(reply["rc"]) if reply is not None else -signal.SIGKILL
            if reply is None:
                self.server.close()
            self.server.child = None
            # the child appended to the log through a descriptor of its own: the caller's next line goes after it
            # (a cold child shares the caller's file offset)
            with contextlib.suppress(OSError, ValueError):
                self.out.seek(0, os.SEEK_END)
        return self.returncode

    def poll(self) -> int | None:
        return self.returncode


class Server:
    """The warm process, seen from its caller (a pipeline worker): started on the first warm stage, with that
    stage's environment less PER_STAGE; a stage with another environment restarts it."""

    def __init__(self, env: dict[str, str]):
        self.env = _base(env)
        self.child: int | None = None  # the stage command running now (its pid and process group)
        # in the interpreter's bin folder, as the `rlsac` script's sys.path[0] is: the driver's working directory
        # (a checkout with rlsac/ in it) is not on the warm process's path
        self.proc = subprocess.Popen([sys.executable, "-c", "from rlsac.runners.warm import serve; serve()"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=self.env, close_fds=True,
                                     cwd=Path(sys.executable).parent)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def send(self, message: Any) -> bool:
        try:
            self.proc.stdin.write((json.dumps(message) + "\n").encode())
            self.proc.stdin.flush()
            return True
        except (BrokenPipeError, OSError):
            return False

    def read(self) -> dict | None:
        line = self.proc.stdout.readline()
        return json.loads(line) if line else None

    def close(self) -> None:
        _every.discard(self)
        for f in (self.proc.stdin, self.proc.stdout):
            try:
                f.close()
            except OSError:
                pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


_local = threading.local()  # one warm process per thread: `rlsac verify --workers 2` runs two stages from two
_every: set[Server] = set()  # every thread's (stop_all)


def _get() -> Server | None:
    return getattr(_local, "server", None)


def _set(server: Server | None) -> None:
    _local.server = server
    if server is not None:
        _every.add(server)


def start(argv: list[str], guard: Callable[[int], None], cold: Callable[..., Any], **kwargs) -> Any:
    """Start one stage command line as ``cold(argv, **kwargs)`` would (Popen's keywords: cwd, env, stdout=<a file
    of a path>, ...), warm where it can (rlsac_args): ``guard(pgid)`` is called once the child has its session and
    before it runs. -> an object with ``pid`` and ``wait()``."""
    env = kwargs.get("env") or dict(os.environ)
    out = kwargs.get("stdout")
    # fork without exec is what Linux runs every day; elsewhere (macOS's system libraries) a stage starts cold
    warm_here = env.get(ENV, "1") != "0" and sys.platform.startswith("linux")
    args = rlsac_args(argv, env) if warm_here else None
    if (args is None or kwargs.get("stderr") != subprocess.STDOUT or not hasattr(out, "name")
            or getattr(_local, "failed", False)):
        return cold(argv, **kwargs)
    server = _get()
    if server is not None and (not server.alive() or server.env != _base(env)):
        stop()
        server = None
    if server is None:
        server = Server(env)
        _set(server)
    out.flush()
    request = {"args": args, "cwd": str(kwargs.get("cwd") or os.getcwd()), "env": env, "log": str(out.name)}
    reply = server.read() if server.send(request) else None
    if reply is None:  # the warm process could not start (an import failed): this stage, and the next, start cold
        stop()
        _local.failed = True
        return cold(argv, **kwargs)
    pid = int(reply["pid"])
    try:
        guard(pid)
    except BaseException:
        stop()  # the child reads EOF instead of "go" and exits NOT_STARTED
        raise
    server.send("go")
    server.child = pid
    return WarmProcess(server, pid, out)


def stop() -> None:
    """End this thread's warm process, if any (it also ends by itself when its worker goes: its stdin closes)."""
    server = _get()
    if server is not None:
        _set(None)
        server.close()


def stop_all() -> None:
    """End every thread's warm process (a thread pool's, when its stages have ended) and a stage command still
    running in one (SIGTERM: the caller was interrupted; a cold child would have had the terminal's signal)."""
    for server in list(_every):
        if server.child is not None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(server.child, signal.SIGTERM)
        server.close()


# ------------------------------------------------------------------------------------------- the warm process


def serve() -> None:
    """The warm process's loop (``python -c 'from rlsac.runners.warm import serve; serve()'``): requests on stdin,
    answers on stdout. In a child this function does not return: the stage command ends the interpreter."""
    requests, answers = os.fdopen(os.dup(0), "r"), os.dup(1)
    null = os.open(os.devnull, os.O_RDWR)
    os.dup2(null, 0)
    os.dup2(2, 1)  # nothing but answers on the answer pipe
    os.close(null)
    sys.path[0] = str(Path(sys.executable).parent)  # the `rlsac` script's first path entry, not '' (-c)
    for name in PRELOAD:
        importlib.import_module(name)
    for line in requests:
        # nothing buffered in the warm process reaches a stage's log: a child inherits the buffers
        sys.stdout.flush()
        sys.stderr.flush()
        request = json.loads(line)
        ready_r, ready_w = os.pipe()
        go_r, go_w = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(ready_r)
            os.close(go_w)
            requests.close()
            os.close(answers)
            _child(request, ready_w, go_r)  # the stage command's exit ends the interpreter (SystemExit)
            return
        os.close(ready_w)
        os.close(go_r)
        os.read(ready_r, 1)  # the child has its session: its process group exists for the guard
        os.close(ready_r)
        os.write(answers, (json.dumps({"pid": pid}) + "\n").encode())
        go = requests.readline()
        if go.strip() == '"go"':
            os.write(go_w, b"g")
        os.close(go_w)  # without "go": the child reads EOF and exits NOT_STARTED
        _, status = os.waitpid(pid, 0)
        if not go:
            return
        os.write(answers, (json.dumps({"rc": os.waitstatus_to_exitcode(status)}) + "\n").encode())


def _child(request: dict, ready_w: int, go_r: int) -> None:
    """In the forked child: a session of its own, wait for "go", then become the stage command."""
    os.setsid()
    os.write(ready_w, b"r")
    os.close(ready_w)
    go = os.read(go_r, 1)
    os.close(go_r)
    if not go:
        os._exit(NOT_STARTED)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    numerics.set_pins(os.environ)  # as `import rlsac` sets them in a cold stage (the libraries loaded under them)
    log = os.open(request["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.dup2(log, 1)
    os.dup2(log, 2)
    os.close(log)
    os.close(null)
    # signals as the warm process has them: it was started as a cold stage is (by the same worker, through exec),
    # so what is ignored there is ignored here, and the interpreter's own SIGINT handler is in place
    rlsac = str(Path(sys.executable).parent / "rlsac")
    sys.argv = [rlsac, *request["args"]]
    # what the `rlsac` script calls: its console-script entry point (the warm process launches it, as the script
    # does; it imports nothing of the command line itself)
    from importlib.metadata import entry_points

    (main,) = entry_points(group="console_scripts", name="rlsac")
    sys.exit(main.load()(request["args"]))  # click's standalone mode exits itself; the interpreter's exit follows
