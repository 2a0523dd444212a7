"""A DVC pipeline stage run outside ``dvc repro``, and the one writer of dvc.lock (issue #50, item 1).

``dvc repro -s <stage>`` parses the whole dvc.lock and writes it back under the repository lock for every stage
(13 s a stage on the paper profile's 1.5 MB lock). Here DVC's own code does each part without that lock:

- the driver plans once and hands a worker each stage's ``spec`` (its dvc.yaml, name, resolved definition and
  lock entry: ``stage_spec``), so the worker rebuilds the stage with DVC's loader without parsing either file;
- the worker (``run``) does what ``Stage.reproduce`` / ``Stage.run`` do, minus the locks: it skips a stage that
  DVC would find unchanged, sets its outputs aside (``set_aside``; persistent ones are kept), runs each line of its
  ``cmd`` as DVC does (DVC's shell, working directory and environment), hashes deps and outs (``Stage.save``,
  which also fills the run cache), commits cached outputs to the DVC cache (``Output.commit``) and returns the
  stage's lock entry as ``dvc.stage.serialize.to_lockfile`` makes it; the .gitignore entries DVC would add are
  returned, not written (several workers would append to one file at once). The outputs set aside are deleted once
  the entry is made and put back when the command fails (``restore``; the driver does it for a stage it
  interrupts): `dvc repro` deletes a stage's outputs before its command, so a failed or interrupted stage would
  leave committed files deleted, and a failed command must not change tracked files;
- the driver (``LockWriter``) adds the .gitignore entries and merges the entries into dvc.lock: each entry is
  rendered by DVC's YAML dumper and spliced into the file's text in the place DVC puts it (an existing entry where
  it was, a new one at the end in ``dvc repro``'s order), and the file is written to a temporary file beside it
  and renamed over it, so a kill leaves the old or the new lock, never a part of one. The bytes are those a serial
  ``dvc repro`` of the pipeline writes (tests/test_ray_pipeline.py compares them), at milliseconds a write instead
  of seconds. (For named stages, ``dvc repro <stages>`` orders new entries by a Python set's iteration, which varies
  between runs: there the entries are the same, their order may not be.)

What ``dvc repro`` does that this does not: restore a stage's outputs from the run cache instead of running it
(a stage here always runs its command), and stages of ``.dvc`` files (they keep ``dvc repro -s``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from rlsac.errors import RlsacError
from rlsac.runners.process_group import end_group, group_alive

SCHEMA_HEAD = "schema: '2.0'\n"  # what DVC writes first in a new lock file (Lockfile.dump_stages)


# ---------------------------------------------------------------------------------------------- the driver's side


def stage_spec(stage, root: Path) -> dict | None:
    """What a worker needs to rebuild ``stage`` (a dvc.yaml stage) with DVC's loader: None for a ``.dvc`` file's
    stage, which keeps ``dvc repro -s``."""
    from dvc.stage import PipelineStage

    if not isinstance(stage, PipelineStage):
        return None
    dvcfile, name = stage.dvcfile, stage.name
    return {"dvcfile": os.path.relpath(dvcfile.path, root), "name": name,
            "definition": dvcfile.resolver.resolve_one(name)[name],
            "lock": dvcfile.lockfile_contents.get("stages", {}).get(name, {})}


def serial_order(repo) -> list:
    """The stages in the order a serial ``dvc repro`` of the whole pipeline runs them (its ``plan_repro``): new
    lock entries go into dvc.lock in this order."""
    from dvc.repo.reproduce import get_active_graph, plan_repro

    return plan_repro(get_active_graph(repo.index.graph))


def render_entry(name: str, entry: dict) -> str:
    """A stage's lock entry as text, as DVC's dumper writes it under ``stages:`` (two spaces in)."""
    from dvc.utils.serialize import dumps_yaml

    text = dumps_yaml({"stages": {name: entry}})
    head = "stages:\n"
    assert text.startswith(head) and text[len(head):].startswith("  "), text[:200]
    return text[len(head):]


_ENTRY_START = re.compile(r"  [^ \n]")  # a line that starts a stage's entry under `stages:`


def split_lock(text: str, names: list[str]) -> tuple[str, dict[str, str], str]:
    """dvc.lock's text -> (the text up to ``stages:``, {stage name: its entry's text} in file order, the text after
    the stages). ``names``: the stage names in file order as a YAML parser read them (DVC's load of the same
    text): the split must find exactly those, else RlsacError (a lock not laid out as DVC writes it)."""
    if not text.strip():  # no lock, or an empty one: DVC starts it with the schema
        return SCHEMA_HEAD + "stages:\n", {}, ""
    lines = text.splitlines(keepends=True)
    if "stages: {}\n" in lines:  # stages emptied: DVC writes them where the key was
        lines[lines.index("stages: {}\n")] = "stages:\n"
    elif "stages:\n" not in lines:  # a lock of datasets only: DVC adds the stages at the end
        lines.append("stages:\n" if text.endswith("\n") else "\nstages:\n")
    start = lines.index("stages:\n") + 1
    end = next((i for i in range(start, len(lines)) if lines[i][:1] not in (" ", "\n", "")), len(lines))
    entries: dict[str, str] = {}
    current: list[str] = []
    for line in lines[start:end]:
        if _ENTRY_START.match(line):
            current = [line]
            entries[_key(line)] = current  # type: ignore[assignment]
        elif current:
            current.append(line)
        else:
            raise RlsacError(f"dvc.lock: line {start + 1} is not a stage's entry ({line.strip()[:80]!r})")
    if list(entries) != list(names):
        raise RlsacError("dvc.lock: not laid out as DVC writes it (its stages could not be told apart); `dvc commit` "
                         "rewrites it")
    return "".join(lines[:start]), {k: "".join(v) for k, v in entries.items()}, "".join(lines[end:])


_PLAIN_KEY = re.compile(r"  ([\w@.+-]+):\n")  # a stage name YAML writes as it is (every name DVC makes, in practice)


def _key(line: str) -> str | None:
    from dvc.utils.serialize import parse_yaml

    plain = _PLAIN_KEY.fullmatch(line)
    if plain:
        return plain.group(1)
    try:
        data = parse_yaml(line, "dvc.lock")
    except Exception:
        return None
    return next(iter(data)) if isinstance(data, dict) and len(data) == 1 else None


def write_atomic(path: Path, text: str) -> None:
    """``text`` into ``path`` through a temporary file beside it and a rename: a kill at any instant leaves the old
    file or the new one, whole. The file keeps its permissions (a new one gets the umask's)."""
    path = Path(path)
    try:
        mode = path.stat().st_mode & 0o7777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _stat(path: Path) -> tuple | None:
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


class LockFile:
    """One dvc.lock as text, one piece per stage entry; ``update`` merges finished stages' entries and writes it.

    ``order``: stage name -> rank in ``serial_order``. Entries the file had stay where they are (DVC updates them in
    place); entries new to it follow, by rank, as a serial ``dvc repro`` appends them one by one. ``text`` is the
    file as it was when ``names`` were read from it; a file changed since (another dvc command wrote it) is read again
    before a write, so the write keeps that change."""

    def __init__(self, path: Path, text: str, names: list[str], order: dict[str, int]):
        self.path, self.order = Path(path), order
        self.stat = _stat(self.path)
        self._load(text, names)

    def _load(self, text: str, names: list[str]) -> None:
        self.head, self.entries, self.tail = split_lock(text, names)
        self.old = list(self.entries)

    def text(self) -> str:
        old = set(self.old)
        new = sorted((n for n in self.entries if n not in old), key=lambda n: (self.order.get(n, len(self.order)), n))
        return self.head + "".join(self.entries[n] for n in self.old + new) + self.tail

    def update(self, entries: dict[str, dict]) -> None:
        if _stat(self.path) != self.stat:
            from dvc.utils.serialize import parse_yaml

            text = self.path.read_text(encoding="utf-8") if self.path.exists() else ""
            self._load(text, list((parse_yaml(text, str(self.path)) or {}).get("stages", {}) or {}))
        for name, entry in entries.items():
            self.entries[name] = render_entry(name, entry)
        write_atomic(self.path, self.text())
        self.stat = _stat(self.path)


class LockWriter:
    """The driver's one writer of every dvc.lock the run touches (the repository's, and a sub-folder dvc.yaml's).

    Made while the plan holds the repository lock (the texts are those DVC just parsed); ``record`` takes a finished
    stage's result: its .gitignore entries, then its lock entry, written at once. A write takes DVC's repository
    lock for its moment, so a ``dvc`` command run meanwhile never reads a lock in the middle of a change."""

    def __init__(self, repo, stages: list):
        root = Path(repo.root_dir)
        order = {s.name: i for i, s in enumerate(serial_order(repo)) if getattr(s, "name", None)}
        self.root, self.files = root, {}
        for s in stages:
            spec_file = getattr(s, "dvcfile", None)
            if spec_file is None or not getattr(s, "name", None):
                continue
            lock_path = Path(os.path.splitext(spec_file.path)[0] + ".lock")
            if lock_path in self.files:
                continue
            text = lock_path.read_text(encoding="utf-8") if lock_path.exists() else ""
            names = list(spec_file.lockfile_contents.get("stages", {}) or {})
            self.files[lock_path] = LockFile(lock_path, text, names, order)
        self._repo = None

    def _open(self):
        if self._repo is None:
            from dvc.repo import Repo

            self._repo = Repo(str(self.root))
        return self._repo

    def record(self, spec: dict, result: dict, tries: int = 10) -> None:
        """Add ``result``'s .gitignore entries and write its lock entry (``result["entry"]``) into the lock of
        ``spec["dvcfile"]``. Raises RlsacError when the repository lock stays held ``tries`` seconds."""
        from dvc.lock import LockError

        repo = self._open()
        lock = self.files[Path(os.path.splitext(self.root / spec["dvcfile"])[0] + ".lock")]
        for attempt in range(tries):
            try:
                with repo.lock:
                    for path in result.get("ignore", []):
                        repo.scm_context.ignore(path)
                    lock.update({spec["name"]: result["entry"]})
                return
            except LockError:
                if attempt == tries - 1:
                    raise RlsacError(f"{lock.path}: the DVC repository lock stayed held (another dvc command); "
                                     f"{spec['name']} ran but is not recorded") from None
                time.sleep(1.0)

    def close(self) -> None:
        if self._repo is not None:
            self._repo.close()
            self._repo = None


# ------------------------------------------------------------------------------------------------ the worker's side


class _Ignores:
    """Stands in for DVC's ``scm_context`` in a worker: the paths DVC would add to a .gitignore, kept for the
    driver (``Output.ignore`` still refuses an output git tracks)."""

    def __init__(self):
        self.paths: list[str] = []

    def ignore(self, path: str) -> None:
        self.paths.append(path)


def open_stage(root: str, spec: dict):
    """-> (repo, stage): the stage rebuilt by DVC's loader from ``spec`` (``stage_spec``), with its lock entry's
    hashes, in a Repo whose .gitignore edits are recorded, not made."""
    from dvc.dvcfile import ProjectFile
    from dvc.repo import Repo
    from dvc.stage.loader import StageLoader

    repo = Repo(root)
    repo.scm_context = _Ignores()
    dvcfile = ProjectFile(repo, os.path.join(repo.root_dir, spec["dvcfile"]))
    return repo, StageLoader.load_stage(dvcfile, spec["name"], spec["definition"], spec["lock"])


def changed(stage) -> bool:
    """``Stage.changed()`` as ``dvc repro`` asks it (missing data counts), without its read locks."""
    return (stage.is_callback or stage.always_changed or stage.changed_stage()
            or any(d.status() for d in stage.deps) or any(o.status() for o in stage.outs))


def commands(stage, env: dict[str, str]) -> tuple[list[list[str]], dict]:
    """The stage's command lines as DVC runs them (``dvc.stage.run.cmd_run``: each line in ``$SHELL`` without its
    rc files) and the Popen keywords (its working directory; the environment with DVC_ROOT and DVC_STAGE)."""
    from dvc.stage.run import _enforce_cmd_list, _make_cmd, get_executable, prepare_kwargs

    kwargs = prepare_kwargs(stage, run_env=env)
    executable = get_executable()
    return [_make_cmd(executable, cmd) for cmd in _enforce_cmd_list(stage.cmd)], kwargs


def prepare(stage, root: str | os.PathLike, spec: dict) -> Path:
    """Before the command, as ``Stage.run``: its deps must exist (hashed, as DVC does when the run cache misses),
    its outputs go (persistent ones stay, unprotected), here into ``set_aside``'s folder. -> that folder."""
    stage.save_deps()
    aside = set_aside(stage, root, spec)  # every other output that exists, moved: nothing is left to remove
    for out in stage.outs:
        if out.persist:
            out.unprotect()
    return aside


ASIDE = Path(".dvc") / "tmp" / "rlsac-aside"  # under the repository's root; DVC's own .gitignore ignores .dvc/tmp
GONE = ".gone"  # the suffix of an aside folder being removed (``_discard``)


def aside_dir(root: str | os.PathLike, spec: dict) -> Path:
    """Where ``spec``'s stage keeps its outputs while its command runs: .dvc/tmp/rlsac-aside/<hash of file:name>."""
    key = f"{spec['dvcfile']}:{spec['name']}".encode()
    return Path(root) / ASIDE / hashlib.sha256(key).hexdigest()[:16]


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def set_aside(stage, root: str | os.PathLike, spec: dict) -> Path:
    """Move the stage's outputs that exist (persistent ones stay) into ``aside_dir`` (a rename where it can), with a
    manifest of where each came from and the process that moved them (``owner``). A folder left by a run that was
    never restored (its driver killed) is restored first: it holds the last good outputs. -> the folder."""
    d = aside_dir(root, spec)
    if d.exists():  # a lost worker's attempt: its guard ends its command within seconds
        restore(root, spec, wait_s=15.0)
    d.mkdir(parents=True)
    outs = [Path(o.fs_path) for o in stage.outs if not o.persist]
    # [path, the name it has here, or None: it did not exist, and what the command writes there goes]; written
    # before the moves, so a kill among them loses nothing (``_restore_dir`` leaves an output not yet moved)
    moved = [[str(p), str(i) if p.exists() or p.is_symlink() else None] for i, p in enumerate(outs)]
    (d / "owner.json").write_text(json.dumps(_owner()))
    write_atomic(d / "manifest.json", json.dumps(moved))
    for path, key in moved:
        if key is not None:
            shutil.move(path, d / key)  # a rename; a copy when data/ is linked to another disk
    return d


def _owner() -> dict:
    """This process, as ``_alive`` knows it again: host, pid and start time (a pid is reused)."""
    import socket

    import psutil

    return {"host": socket.gethostname(), "pid": os.getpid(), "started": psutil.Process().create_time()}


def _alive(owner: dict) -> bool:
    """Whether the process ``owner`` (``_owner``) still runs; one of another host counts as running (unknown)."""
    import socket

    import psutil

    if owner.get("host") != socket.gethostname():
        return True
    try:
        p = psutil.Process(int(owner["pid"]))
        return p.create_time() == owner["started"] and p.status() != psutil.STATUS_ZOMBIE
    except (psutil.NoSuchProcess, psutil.AccessDenied, KeyError, TypeError, ValueError):
        return False


def _note_pid(d: Path, pid: int | None) -> None:
    """The running command's process (its group's leader) in the aside folder: ``restore`` waits for it to end."""
    (d / "pid").write_text("" if pid is None else str(pid))


def _noted_group(d: Path) -> int | None:
    """The process group of the command ``_note_pid`` noted in ``d``; None while none runs."""
    pid = (d / "pid").read_text().strip() if (d / "pid").is_file() else ""
    return int(pid) if pid else None


def _group_alive(d: Path) -> bool:
    """Whether the command noted in ``d`` still runs (an unreaped zombie member does not count, nor another user's
    group of that id: rlsac.runners.process_group)."""
    group = _noted_group(d)
    return group is not None and group_alive(group)


def restore(root: str | os.PathLike, spec: dict, wait_s: float = 0.0) -> bool:
    """Put the stage's outputs back as they were before its command (the ones ``set_aside`` moved return, what the
    command wrote is deleted) and remove the folder. ``wait_s``: wait up to this long for the command's process
    group to end first (an interrupted stage is being stopped by its guard). -> whether there was anything to
    restore."""
    return _restore_dir(aside_dir(root, spec), wait_s)


def _restore_dir(d: Path, wait_s: float = 0.0) -> bool:
    if not (d / "manifest.json").is_file():
        if d.exists():
            _discard(d)
        return False
    end = time.monotonic() + wait_s
    while _group_alive(d) and time.monotonic() < end:  # read each time: a worker notes each command line's group
        time.sleep(0.2)
    for path, key in json.loads((d / "manifest.json").read_text()):
        if key is not None and not (d / key).exists() and not (d / key).is_symlink():
            continue  # killed before this one moved: it is where it was
        _remove(Path(path))  # a part-written output goes
        if key is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            shutil.move(d / key, path)
    _discard(d)
    return True


def recover(root: str | os.PathLike, wait_s: float = 0.0) -> list[str]:
    """Put back the outputs that runs of dead processes set aside (a SIGKILLed ``rlsac pipeline``: its workers died
    with it, before any ``restore``; the outputs were missing from the tree until the stage ran again): the folders
    of ``ASIDE`` whose owner (the worker that moved them, on this host) is gone, once their command has ended too
    (its guard ends it: ``wait_s``; one still running then, its guard gone, is ended here: nothing would record what
    it writes). A folder of a live worker, or of another
    host's (a cluster sharing this folder), stays. -> the outputs of the stages restored (their paths: each as it
    was before the stage's command, there or absent)."""
    top = Path(root) / ASIDE
    back = []
    for d in sorted(top.iterdir()) if top.is_dir() else []:
        if d.name.endswith(GONE):  # what a process killed while removing a folder left: nothing of it is needed
            shutil.rmtree(d, ignore_errors=True)
            continue
        try:
            owner = json.loads((d / "owner.json").read_text())
        except (OSError, ValueError):
            continue  # an older run's (no owner): the stage's next run restores it (``set_aside``)
        if not isinstance(owner, dict) or _alive(owner):
            continue
        if not _ended(d, wait_s):
            continue
        manifest = json.loads((d / "manifest.json").read_text()) if (d / "manifest.json").is_file() else []
        if _restore_dir(d):
            back += [p for p, _ in manifest]
    return back


def _ended(d: Path, wait_s: float) -> bool:
    """Wait up to ``wait_s`` for the command noted in ``d`` (of a dead worker) to end, as its guard ends it; then end
    it here (SIGTERM, 5 s, SIGKILL): nothing would record what it writes. -> whether it has ended."""
    group = _noted_group(d)
    return group is None or end_group(group, wait_s)


def _discard(d: Path) -> None:
    """Remove the aside folder ``d``, renamed first (one atomic step): a process killed while removing it (a Ray
    worker ended as it restored) leaves no part of it under its name, only a ``*.gone`` folder that ``recover``
    removes."""
    trash = d.with_name(f"{d.name}.{os.getpid()}{GONE}")
    d.rename(trash)
    shutil.rmtree(trash, ignore_errors=True)


def record(stage) -> dict[str, Any]:
    """After the command, as ``Stage.run`` then ``dvc repro``'s dump: hash deps and outs, fill the run cache when
    every output is cached, commit cached outputs to the DVC cache. -> {"entry": the lock entry, "ignore": the
    paths to add to .gitignore}."""
    from dvc.stage.serialize import to_lockfile

    no_cache_outs = any(not o.use_cache for o in stage.outs if not (o.is_metric or o.is_plot))
    stage.save(allow_missing=False, run_cache=not no_cache_outs)
    for out in stage.outs:
        out.commit()
    return {"entry": to_lockfile(stage)[stage.name], "ignore": list(stage.repo.scm_context.paths)}


def run(root: str, spec: dict, env: dict[str, str], log: str,
        start: Callable[..., subprocess.Popen] | None = None) -> dict:
    """Run one stage (a Ray task's body): -> {stage, status (done / skipped / failed), seconds, rc, error, log,
    node, entry, ignore}. ``start(argv, **popen_kwargs)`` starts one command line (the pipeline's, which guards its
    process group); a failed stage has no entry, and DVC's error is its ``error``."""
    import socket

    start = start or subprocess.Popen
    t0 = time.time()
    out = {"stage": spec["name"], "status": "failed", "rc": None, "error": None, "log": log,
           "node": socket.gethostname(), "entry": None, "ignore": []}
    Path(log).parent.mkdir(parents=True, exist_ok=True)
    # DVC's paths are relative to the working directory (DVC_STAGE, .gitignore entries, hashing): `dvc repro` runs in
    # the repository's root, so the task does too, and gives the worker its directory back
    with open(log, "wb") as f, contextlib.chdir(root):
        repo, aside, proc = None, None, None
        try:
            repo, stage = open_stage(root, spec)
            if not changed(stage):
                f.write(f"Stage '{stage.addressing}' didn't change, skipping\n".encode())
                out["status"] = "skipped"
            else:
                aside = prepare(stage, root, spec)
                argvs, kwargs = commands(stage, env)
                f.write(f"Running stage '{stage.addressing}':\n".encode())
                for argv, line in zip(argvs, _lines(stage.cmd), strict=True):
                    f.write(f"> {line}\n".encode())
                    f.flush()
                    proc = start(argv, **kwargs, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
                    _note_pid(aside, proc.pid)
                    out["rc"] = proc.wait()
                    _note_pid(aside, None)
                    if out["rc"]:
                        raise _Failed(line, out["rc"])
                out.update(record(stage), status="done")
                _discard(aside)
        except Exception as e:  # DVC's errors (a missing dependency or output) and a failed command: one line
            out["error"] = e.message if isinstance(e, _Failed) else f"ERROR: {' '.join(str(e).split())[:500]}"
            f.write(f"\n{out['error']}\n".encode())
            if aside is not None:  # the outputs as they were: a failed stage changes no file
                if proc is not None:  # once what its command left running has ended (its shell killed, not its child)
                    end_group(proc.pid)
                restore(root, spec)
        finally:
            if repo is not None:
                repo.close()
    out["seconds"] = time.time() - t0
    return out


def _lines(cmd) -> list[str]:
    return cmd if isinstance(cmd, list) else cmd.splitlines()


class _Failed(Exception):
    """A command line of the stage exited non-zero (DVC's StageCmdFailedError, worded as DVC words it)."""

    def __init__(self, line: str, rc: int):
        how = f"exited with {rc}" if rc > 0 else f"killed by {signal.Signals(-rc).name}"
        self.message = f"ERROR: failed to reproduce: failed to run: {line}, {how}"
        super().__init__(self.message)


def python_bin_env(env: dict[str, str]) -> dict[str, str]:
    """The stage's environment: this process's, the driver's ``env`` over it, and this interpreter's bin folder
    first on PATH (the stage's ``rlsac`` / ``dvc``)."""
    full = {**os.environ, **env}
    full["PATH"] = str(Path(sys.executable).parent) + os.pathsep + full.get("PATH", "")
    return full
