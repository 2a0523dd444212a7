"""Recorded provenance of pipeline files, read from ``dvc.lock``: which stage made a file, with which command,
params and content hash.

Reports use it so that what they show follows from what was recorded, not from whether ``data/`` happens
to exist in this checkout (``data/`` is git-ignored: a fresh clone has none of it):

* :func:`prepared_attrs`: scenes, N and source of a prepared two-view file, from its ``prepare-cvpr2020``
  stage (table captions);
* :func:`recorded_lines`: a line test file as recorded: the file itself when its hash matches the lock,
  else regenerated from the recorded stage params (``rlsac lines-data``) and checked against the hash.

The lock read is the one of the working directory: ``dvc.lock`` for the paper profile, the quick profile's
own when run from ``experiments/quick/``.
"""

from __future__ import annotations

import contextlib
import hashlib
import shlex
import tempfile
from pathlib import Path
from typing import Any, Iterator

import yaml

from rlsac.errors import RlsacError

LOCK = "dvc.lock"


def _norm(path: str | Path) -> str:
    return Path(path).as_posix().removeprefix("./")


def lock_stage(path: str | Path, lock: str | Path = LOCK) -> tuple[str, dict[str, Any], dict[str, Any]] | None:
    """-> (stage name, stage entry, out entry) of the stage in ``lock`` that outputs ``path``, or None."""
    lock = Path(lock)
    if not lock.is_file():
        return None
    try:
        stages = (yaml.safe_load(lock.read_text()) or {}).get("stages") or {}
    except (OSError, yaml.YAMLError):
        return None
    want = _norm(path)
    inside = None  # a directory output that holds ``path`` (data/folds/<regime>/<fold> holds its test.h5)
    for name, st in stages.items():
        for out in (st or {}).get("outs") or []:
            if not isinstance(out, dict):
                continue
            if _norm(out.get("path", "")) == want:
                return name, st, out
            if inside is None and want.startswith(_norm(out.get("path", "")).rstrip("/") + "/"):
                inside = name, st, out
    return inside


def cmd_options(cmd: str) -> dict[str, str]:
    """``rlsac x --a 1 --b c && rlsac y --a 2`` -> {"--a": "2", "--b": "c"} (later parts win; flags -> "")."""
    out: dict[str, str] = {}
    for part in " ".join(str(cmd).split()).split("&&"):
        argv = shlex.split(part)
        for i, tok in enumerate(argv):
            if tok.startswith("--"):
                key, eq, val = tok.partition("=")
                if eq:
                    out[key] = val
                else:
                    nxt = argv[i + 1] if i + 1 < len(argv) else ""
                    out[key] = "" if nxt.startswith("--") else nxt
    return out


def prepared_attrs(path: str | Path, lock: str | Path = LOCK) -> dict[str, Any] | None:
    """The attrs a prepared two-view file was made with (scenes, n_points, root, split), from the
    ``rlsac prepare-cvpr2020`` command that dvc.lock records for it; None without such a record."""
    hit = lock_stage(path, lock)
    if hit is None:
        return None
    name, st, _ = hit
    parts = [p for p in " ".join(str(st.get("cmd", "")).split()).split("&&") if f"--out {_norm(path)}" in
             " ".join(p.split()) or f"--out={_norm(path)}" in p]
    cmd = parts[0] if parts else str(st.get("cmd", ""))
    if "prepare-cvpr2020" not in cmd:
        return None
    o = cmd_options(cmd)
    return {"scenes": o.get("--scenes", "?"), "n_points": o.get("--n-points", "?"), "root": o.get("--root", ""),
            "split": o.get("--split", "?"), "stage": name}


def md5(path: str | Path) -> str:
    h = hashlib.md5()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _nested(flat: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in flat.items():
        d = out
        parts = str(key).split(".")
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = value
    return out


@contextlib.contextmanager
def recorded_lines(path: str | Path, lock: str | Path = LOCK) -> Iterator[Path]:
    """Yield a readable line file with the content dvc.lock records for ``path``.

    ``path`` itself when it exists and matches the recorded hash (or nothing is recorded for it); else the
    file regenerated from the recorded ``rlsac lines-data`` stage into a temporary folder (nothing is written
    under ``data/``) and checked against the recorded hash. RlsacError when neither is possible.
    """
    path = Path(path)
    hit = lock_stage(path, lock)
    if hit is None:
        if not path.is_file():
            raise RlsacError(f"{path}: no such line file, and {lock} records no stage that makes it")
        yield path
        return
    name, st, out = hit
    want = out.get("md5")
    if path.is_file() and (not want or md5(path) == want):
        yield path
        return
    o = cmd_options(st.get("cmd", ""))
    if "lines-data" not in str(st.get("cmd", "")) or "--rate" not in o:
        raise RlsacError(f"{path}: missing, and its stage {name} is not `rlsac lines-data`: run `dvc repro {name}`")
    split = path.name.split("_o")[0]
    from rlsac.data.line_files import lines_protocol_data

    with tempfile.TemporaryDirectory(prefix="rlsac-lines-") as tmp:
        params = Path(tmp) / "params.yaml"
        params.write_text(yaml.safe_dump(_nested((st.get("params") or {}).get("params.yaml") or {})))
        s = lines_protocol_data({"rate": float(o["--rate"]), "splits": split, "out_dir": tmp}, track=False,
                                params_path=params)
        made = Path(s["files"][0])
        if want and md5(made) != want:
            raise RlsacError(f"{path}: {'not the file recorded' if path.is_file() else 'missing'} in {lock} (stage "
                             f"{name}), and regenerating it from the recorded params gives other bytes: run "
                             f"`dvc repro {name}`")
        yield made
