"""Atomic output writing and checked h5 reading.

Every file the workbench produces is written to a temporary sibling and renamed into place, so a
failing command never leaves a half-written output behind.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
import tempfile
from pathlib import Path
from typing import Iterator

import h5py
import numpy as np

from rlsac.errors import RlsacError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` only if the block succeeds."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:  # commands check their outputs first (check_writable); this is the last guard
        raise RlsacError(f"cannot write {path}: {e.strerror or e.__class__.__name__}") from None
    os.close(fd)
    tmp = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; outputs get the usual permissions
    pending = _PENDING.get()
    handed_over = False  # to the all_or_nothing block, which renames or removes it
    try:
        yield tmp
        if pending is not None:  # all_or_nothing: renamed with the block's other outputs when it ends
            pending.append((tmp, path))
            handed_over = True
            return
        os.replace(tmp, path)
    finally:
        if not handed_over and tmp.exists():
            tmp.unlink()


_PENDING: contextvars.ContextVar[list[tuple[Path, Path]] | None] = contextvars.ContextVar("pending", default=None)


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """A command that writes several outputs: every ``atomic_path`` write inside the block is renamed into place when
    the block ends without an error, after checking that no target is a folder; on an error none is (the temporary
    files go), so a command that fails half-way leaves every output as it was. Inside the block ``staged(path)`` is
    where a file written earlier in it can be read."""
    if _PENDING.get() is not None:  # nested: the outer block decides
        yield
        return
    pending: list[tuple[Path, Path]] = []
    token = _PENDING.set(pending)
    try:
        yield
        in_the_way = next((path for _, path in pending if path.is_dir()), None)
        if in_the_way is not None:
            raise RlsacError(f"cannot write {in_the_way}: a folder of that name is in the way")
        for tmp, path in pending:
            os.replace(tmp, path)
    finally:
        _PENDING.reset(token)
        for tmp, _ in pending:
            if tmp.exists():
                tmp.unlink()


def staged(path: str | os.PathLike) -> Path:
    """Where ``path``'s content is now: the temporary file of its latest write in the current ``all_or_nothing``
    block, else ``path`` itself."""
    path = Path(path)
    for tmp, target in reversed(_PENDING.get() or []):
        if target == path:
            return tmp
    return path


def check_writable(path: str | os.PathLike, what: str = "output", folder: bool = False) -> Path:
    """Fail early, with a one-line RlsacError, when ``path`` (a file to be written, or a directory to
    write into) could not be written: a parent that is a regular file, a folder that cannot be
    created or written (read-only, /proc, ...), a folder where the file goes. ``folder``: ``path`` is a folder
    to write into, so an existing file there is an error instead. Nothing is left behind: missing folders are
    not created, the probe file is removed at once. -> ``path`` as a Path."""
    path = Path(path)
    if path.exists() and not (path.is_file() or path.is_dir()):
        raise RlsacError(f"cannot write {what} {path}: not a regular file or folder")
    if folder and path.exists() and not path.is_dir():
        raise RlsacError(f"cannot write {what} {path}: {path} is not a folder")
    if not folder and path.is_dir():  # os.replace onto a folder fails only at the end, after the work
        raise RlsacError(f"cannot write {what} {path}: a folder of that name is in the way")
    anc = path if path.is_dir() else path.parent
    while not anc.exists():
        if anc.is_symlink():
            raise RlsacError(f"cannot write {what} {path}: {anc} is a broken link")
        anc = anc.parent
    if not anc.is_dir():
        raise RlsacError(f"cannot write {what} {path}: {anc} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".rlsac-probe.", suffix=".tmp", dir=anc)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise RlsacError(f"cannot write {what} {path}: {anc} is not writable ({e.strerror or e.__class__.__name__})") \
            from None
    if path.is_file() and not os.access(path, os.W_OK) and not os.access(anc, os.W_OK):
        raise RlsacError(f"cannot write {what} {path}: read-only file")
    return path


def clean_stale_temps(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary siblings ``atomic_path`` leaves when a process is killed mid-write
    (``.<name>.XXXX.tmp``); call it before writing ``path`` again. -> the removed files."""
    path = Path(path)
    removed = []
    if path.parent.is_dir():
        for p in path.parent.glob(f".{glob_escape(path.name)}.*.tmp"):
            try:
                p.unlink()
                removed.append(p)
            except OSError:
                pass
    return removed


def glob_escape(name: str) -> str:
    import glob

    return glob.escape(name)


def write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json(path: str | os.PathLike, obj) -> Path:
    return write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def open_h5(path: str | os.PathLike) -> h5py.File:
    """Open an h5 file for reading, turning every failure into a one-line RlsacError."""
    path = Path(path)
    if not path.is_file():
        raise RlsacError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise RlsacError(f"{path}: not a readable HDF5 file ({e.__class__.__name__})") from None


def read_array(f: h5py.File, key: str, shape: tuple | None = None, finite: bool = True) -> np.ndarray:
    """Read dataset ``key`` from an open h5 file and check its shape (None = any size on that axis)."""
    if key not in f:
        raise RlsacError(f"{f.filename}: missing key '{key}'")
    arr = np.asarray(f[key][()])
    if shape is not None:
        ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=True))
        if not ok:
            want = "(" + ",".join("N" if s is None else str(s) for s in shape) + ")"
            raise RlsacError(f"{f.filename}: key '{key}' has shape {arr.shape}, expected {want}")
    if finite and arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise RlsacError(f"{f.filename}: key '{key}' contains NaN or inf")
    return arr


def load_torch(path: str | os.PathLike, device="cpu", what: str = "checkpoint") -> dict:
    """``torch.load`` of a file ``rlsac train`` wrote -> its dict; anything else (a text or h5 file, a
    truncated save) is a one-line RlsacError."""
    import pickle

    import torch

    path = Path(path)
    if not path.is_file():
        raise RlsacError(f"{path}: no such {what} file")
    try:
        obj = torch.load(path, map_location=device, weights_only=False)
    except (pickle.UnpicklingError, EOFError, RuntimeError, ValueError, OSError, AttributeError, ImportError,
            IndexError, KeyError, TypeError, UnicodeDecodeError) as e:
        raise RlsacError(f"{path}: not an rlsac {what} ({e.__class__.__name__}: {' '.join(str(e).split())[:80]})") \
            from None
    if not isinstance(obj, dict):
        raise RlsacError(f"{path}: not an rlsac {what} (holds a {type(obj).__name__})")
    return obj
