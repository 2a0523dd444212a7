"""Atomic output writing and checked h5 reading.

Every file the workbench produces is written to a temporary sibling and renamed into place, so a
failing command never leaves a half-written output behind.
"""

from __future__ import annotations

import contextlib
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
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; outputs get the usual permissions
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


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
