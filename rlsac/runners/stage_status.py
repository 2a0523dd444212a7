"""Which pipeline stages are out of date, from dvc.lock and the files' bytes hashed once (issue #63, item 3).

DVC answers the same question (``dvc status``, ``Stage.changed``), but each dependency and output costs it a
round through its file system layers and its state database: 1646 stages took minutes on a clean clone. Here each
path is hashed at most once per plan, and a file's md5 is kept in ``.dvc/tmp/rlsac-md5.json`` keyed by its size,
modification time (ns) and inode (as DVC's own state and git's index key theirs): a later plan re-reads only the
files that changed since. A clean clone hashes its committed outputs once (tens of MB: seconds); a file written in
the last ``RACY_S`` seconds is hashed but not kept (its time could still change within the clock's tick).

The rules are DVC's (``Stage.changed_stage``/``changed_deps``/``changed_outs``): a stage changed when its command
is not the lock's, a parameter's value differs, a dependency is missing or its md5 is not the lock's, or it has no
lock entry; its outputs changed when one is missing, differs, or (a cached output) is not in DVC's cache. A file's
md5 is the md5 of its bytes and a folder's is DVC's ``.dir`` md5 (of its files' md5s and paths, ``.dvcignore``
applied); a lock entry in another hash (DVC 2's md5-dos2unix) is left to DVC's own check.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any

CACHE = Path(".dvc") / "tmp" / "rlsac-md5.json"  # under the repository root: DVC's scratch folder, git-ignored
RACY_S = 2.0
CHUNK = 1 << 20


class Hashes:
    """md5 of the repository's files and folders, each computed once, files' kept across plans (see the module)."""

    def __init__(self, repo):
        self.repo, self.root = repo, Path(repo.root_dir)
        self.path = self.root / CACHE
        try:
            self.known: dict[str, list] = json.loads(self.path.read_text())
        except (OSError, ValueError):  # none yet, or unreadable: hashed again
            self.known = {}
        self.seen: dict[str, str | None] = {}  # this plan's answers by absolute path
        self.read: set[str] = set()  # files read this plan
        self.reused: set[str] = set()  # files whose kept md5 served
        self.dirty = False

    def file_md5(self, path: str, st: os.stat_result | None = None) -> str:
        st = st or os.stat(path)
        key = os.path.relpath(path, self.root)
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        hit = self.known.get(key)
        if hit is not None and hit[:3] == stamp:
            self.reused.add(key)
            return hit[3]
        h = hashlib.md5()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(CHUNK), b""):
                h.update(chunk)
        self.read.add(key)
        if time.time() - st.st_mtime_ns / 1e9 > RACY_S:
            self.known[key], self.dirty = [*stamp, h.hexdigest()], True
        return h.hexdigest()

    def md5(self, path: str) -> str | None:
        """The path's md5 as dvc.lock writes it (a folder's ends in ``.dir``); None when it does not exist."""
        if path not in self.seen:
            self.seen[path] = self._md5(path)
        return self.seen[path]

    def _md5(self, path: str) -> str | None:
        try:
            st = os.stat(path)
        except OSError:
            return None
        if not os.path.isdir(path):
            return self.file_md5(path, st)
        entries = []
        for top, _, files in self.repo.dvcignore.walk(self.repo.fs, path):
            for name in files:
                full = os.path.join(top, name)
                entries.append({"md5": self.file_md5(full), "relpath": Path(os.path.relpath(full, path)).as_posix()})
        entries.sort(key=lambda e: e["relpath"])  # dvc_data's Tree.as_bytes, byte for byte
        return hashlib.md5(json.dumps(entries, sort_keys=True).encode("utf-8")).hexdigest() + ".dir"

    def summary(self) -> str:
        """How this plan knew the files' md5s (the dry run prints it)."""
        known = len(self.reused - self.read)
        return f"checked against dvc.lock by md5: {len(self.read)} files read, {known} known by size and time " \
               f"({CACHE.as_posix()})"

    def save(self) -> None:
        """Keep the files' md5s for the next plan (atomic; a plan that cannot write it is only slower next time)."""
        if not self.dirty:
            return
        tmp = self.path.with_name(self.path.name + f".{os.getpid()}.tmp")
        try:
            tmp.write_text(json.dumps(self.known, separators=(",", ":")))
            os.replace(tmp, self.path)
        except OSError:
            tmp.unlink(missing_ok=True)


class Status:
    """A stage's state against dvc.lock (DVC's rules, see the module), its files hashed by ``Hashes``."""

    def __init__(self, repo):
        self.repo, self.hashes = repo, Hashes(repo)
        self.params: dict[str, Any] = {}  # params file -> its parsed contents, read once

    def missing(self, item) -> bool:
        return self.hashes.md5(item.fs_path) is None

    def changed(self, item) -> bool:
        """A dependency's or output's workspace status (missing, new or modified) is not empty."""
        from dvc.dependency import ParamsDependency

        if isinstance(item, ParamsDependency):
            return self._params_changed(item)
        hi = item.hash_info
        if hi and hi.name != "md5":  # a hash this module does not compute: DVC's own check
            return bool(item.workspace_status())
        actual = self.hashes.md5(item.fs_path)
        return actual is None or not hi or actual != hi.value

    def not_in_cache(self, out) -> bool:
        """A cached output whose object (a folder's: its listing and every file) is not in DVC's cache."""
        if not (out.use_cache and out.hash_info):
            return False
        odb = out.cache
        oid = out.hash_info.value
        if not os.path.exists(odb.oid_to_path(oid)):
            return True
        if not out.hash_info.isdir:
            return False
        try:
            listing = json.loads(Path(odb.oid_to_path(oid)).read_text())
        except (OSError, ValueError):
            return True
        return any(not os.path.exists(odb.oid_to_path(e["md5"])) for e in listing)

    def changed_outs(self, stage) -> bool:
        return any(self.not_in_cache(o) or self.changed(o) for o in stage.outs)

    def _params_changed(self, dep) -> bool:
        from dvc.utils.serialize import load_path

        path = dep.fs_path
        if path not in self.params:
            self.params[path] = load_path(path, self.repo.fs) if os.path.exists(path) else None
        config = self.params[path]

        def read_params(**_):  # DVC's read_param_file on the file parsed once
            if config is None:
                return {}
            if not dep.params:
                return config
            out = {}
            for key in dep.params:
                try:
                    out[key] = _get(config, key)
                except KeyError:
                    continue
            return out

        dep.read_params = read_params  # the comparison itself stays DVC's (ParamsDependency.workspace_status)
        return bool(dep.workspace_status())


def _get(config, key: str):
    """``dpath.get(config, key, separator=".")`` as DVC calls it, without dpath's walk over the whole file (that
    walk, once per parameter of each of 1646 stages, was most of a plan's time); anything but plain keys and list
    indexes is left to dpath."""
    node = config
    for part in key.split("."):
        if isinstance(node, dict) and part in node:
            node = node[part]
        elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
            node = node[int(part)]
        else:
            import dpath

            return dpath.get(config, key, separator=".")
    return node
