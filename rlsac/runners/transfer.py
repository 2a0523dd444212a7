"""Stages on machines that share no disk (issue #50, item 2): ``rlsac pipeline --remote s3://bucket/prefix``.

Without ``--remote`` every Ray node must see the driver's repository folder: a node ran its stages, their outputs
stayed on that node, and the driver reported success. With it, everything a stage needs or makes travels through an
S3 bucket, by DVC's own S3 filesystem (``dvc-s3``) and object layout (``dvc_data``):

- the code: the driver packs its working tree (``git ls-files --cached --others --exclude-standard``: tracked files
  and new ones git would add, not git-ignored data) into one tar, stored in the bucket by its md5. A packed tree,
  not a commit each node checks out, because the plan is the driver's working tree's (uncommitted edits of
  dvc.yaml, params.yaml or the code included; a toy or scratch repository may have no commit at all), and because a
  node then needs the bucket only, no access to the git server;
- a stage's inputs: before it starts, the driver hashes each of its dependencies (parameters files come with the
  tree) with DVC's code and uploads what the bucket lacks;
- the task (``run_on_node``), on whatever node Ray picks (the node of the stage's main parent, where it can), unpacks
  the tree into a fresh folder of its own, fetches the inputs (from the node's cache of objects, ``NodeCache``, where
  an earlier task of the node fetched or made them), runs the stage as the direct runner does
  (rlsac.runners.dvc_stage.run:
  its lock entry by DVC's code), uploads its outputs, removes the folder, and returns the lock entry, its outputs'
  hashes and its log;
- the driver (``Workspace.bring_back``) downloads the outputs into its own workspace, each checked against its md5
  and moved into place by a rename, before it writes the lock entry and before any dependent starts.

Every object lies under ``<prefix>/files/md5/<2 hex>/<30 hex>`` (a directory as DVC's ``.dir`` listing plus its
files), the layout of a DVC remote at that URL: cached outputs in it can be ``dvc pull``-ed. Outputs marked
``cache: false`` (most of this pipeline's: reports, figures, tables) are not in DVC's cache, so a cache push would
not carry them; they travel the same way, content-addressed by the md5 their lock entry records, rather than under
a per-run transfer prefix, because then a re-run uploads only what changed, identical bytes are stored once, a
download is checked by its own name, and nothing needs cleaning up after a run. They do not enter the driver's DVC
cache (a single-host run leaves them out of it too); cached outputs do, as ``dvc repro`` commits them.

Not carried: the run cache entries a node writes (``.dvc/cache/runs``) stay in its folder, which is removed.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path
from typing import Any, Callable
from urllib.parse import urlsplit

from rlsac.errors import RlsacError
from rlsac.io import atomic_path

NODE_DIR_ENV = "RLSAC_NODE_DIR"  # where a node keeps the code trees it fetched and its stages' folders
CONNECT_TIMEOUT_S = 10  # an endpoint that does not answer: botocore waited 60 s an attempt
# the standard AWS settings (``aws configure`` writes the same): the driver's are the run's, as MLFLOW_TRACKING_URI is
_ENV_CONFIG = (("endpointurl", ("AWS_ENDPOINT_URL_S3", "AWS_ENDPOINT_URL")), ("region", ("AWS_REGION",
               "AWS_DEFAULT_REGION")), ("access_key_id", ("AWS_ACCESS_KEY_ID",)),
               ("secret_access_key", ("AWS_SECRET_ACCESS_KEY",)), ("session_token", ("AWS_SESSION_TOKEN",)))


# --------------------------------------------------------------------------------------------- the store itself


def check_url(value: str) -> None:
    """``--remote``: ``s3://bucket[/prefix]`` or the name of a DVC remote of the repository (checked once the
    repository is read). RlsacError otherwise (no I/O)."""
    if "://" not in value:
        if not value.strip() or "/" in value:
            raise RlsacError(f"--remote {value!r}: not s3://bucket/prefix nor the name of a DVC remote")
        return
    where = urlsplit(value)
    if where.scheme != "s3" or not where.netloc or where.query or where.fragment:
        raise RlsacError(f"--remote {value}: not s3://bucket/prefix (an S3 bucket, through dvc-s3)")


def resolve(value: str, root: str | os.PathLike) -> dict:
    """-> the store's configuration (a DVC remote's keys: url, endpointurl, region, credentials): a DVC remote of
    the repository named ``value``, or with url ``value``, else ``value`` alone; what it leaves out comes from the
    standard AWS environment variables. It travels to every task (a node has its own environment otherwise)."""
    from dvc.config import Config

    check_url(value)
    remotes = Config(dvc_dir=str(Path(root) / ".dvc"))["remote"]  # the repository's, its local and global ones
    if "://" not in value:
        if value not in remotes:
            raise RlsacError(f"--remote {value}: no DVC remote of that name (`dvc remote list`), nor s3://bucket/prefix")
        conf = dict(remotes[value])
    else:
        conf = next((dict(r) for r in remotes.values() if r.get("url", "").rstrip("/") == value.rstrip("/")),
                    {"url": value})
    if urlsplit(conf["url"]).scheme != "s3":
        raise RlsacError(f"--remote {value}: {conf['url']} is not an s3:// URL")
    for key, names in _ENV_CONFIG:
        if key not in conf:
            found = next((os.environ[n] for n in names if os.environ.get(n)), None)
            if found:
                conf[key] = found
    conf.setdefault("connect_timeout", CONNECT_TIMEOUT_S)
    return conf


class Store:
    """The bucket as DVC's S3 filesystem and object database: objects by md5 under ``<prefix>/files/md5``."""

    def __init__(self, conf: dict, tries: int | None = None):
        from dvc.fs import get_cloud_fs
        from dvc_data.hashfile.db import HashFileDB

        cls, fs_conf, path = get_cloud_fs({}, **conf)
        self.url, self.fs = conf["url"], cls(**fs_conf)
        self.downloads = 0  # objects read from the bucket (a node's cache saves these: NodeCache)
        if tries is not None:  # botocore's retries: an endpoint that refuses took 15 s to give up on
            self.fs.fs_args.setdefault("config_kwargs", {})["retries"] = {"max_attempts": tries, "mode": "standard"}
        self.odb = HashFileDB(self.fs, self.fs.join(path.rstrip("/"), "files", "md5"))

    def exists(self, oid: str) -> bool:
        return self.odb.exists(oid)

    def put_files(self, paths: list[str], oids: list[str]) -> None:
        """Upload the local files whose md5 the bucket lacks."""
        from dvc_objects.fs import LocalFileSystem

        if paths:
            self.odb.add(paths, LocalFileSystem(), oids)

    def put_bytes(self, oid: str, data: bytes) -> None:
        if not self.exists(oid):
            self.odb.add_bytes(oid, data)

    def read(self, oid: str) -> bytes:
        self.downloads += 1
        return self.fs.cat_file(self.odb.oid_to_path(oid))

    def get_file(self, oid: str, dest: Path) -> None:
        """The object ``oid`` into ``dest`` (a new file), checked against its md5."""
        self.downloads += 1
        self.fs.get_file(self.odb.oid_to_path(oid), str(dest))
        if _md5(dest) != oid:
            raise RlsacError(f"{self.url}: object {oid} does not hold what its md5 names (a corrupt store)")


def _md5(path: Path) -> str:
    h = hashlib.md5()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def open_store(value: str, root: str | os.PathLike) -> tuple[Store, dict]:
    """The driver's check of ``--remote``, before any stage runs: the configuration resolves and the bucket takes a
    small object. -> (store, configuration). RlsacError with one line otherwise (unreachable endpoint, no such
    bucket, no credentials, a malformed URL)."""
    conf = resolve(value, root)
    try:
        Store(conf, tries=1).put_bytes(hashlib.md5(b"rlsac\n").hexdigest(), b"rlsac\n")
        store = Store(conf)
    except RlsacError:
        raise
    except Exception as e:
        raise RlsacError(f"--remote {value}: cannot write to the store ({e.__class__.__name__}: "
                         f"{' '.join(str(e).split())[:200]})") from None
    return store, conf


# ------------------------------------------------------------------------------------------------ what travels


def hash_path(repo, path: str) -> tuple[str, Any]:
    """-> (md5, DVC's Tree for a directory else None) of a file or directory, by DVC's code (``dvc_data``'s
    build, with the repository's hash cache and .dvcignore), so the md5 is the one dvc.lock records."""
    from dvc_data.hashfile.build import build

    _, _, obj = build(repo.cache.local, path, repo.fs, "md5", ignore=repo.dvcignore, dry_run=True)
    return obj.hash_info.value, (obj if obj.hash_info.isdir else None)


def push(store: Store, repo, root: str, rel: str, cache: NodeCache | None = None) -> dict:
    """Upload ``root/rel`` (a file or directory) where the bucket lacks it; with ``cache`` (a node's), also into
    it. -> {"path": rel, "oid": its md5}."""
    path = os.path.join(root, rel)
    oid, tree = hash_path(repo, path)
    files = [(path, oid)] if tree is None else [(os.path.join(path, *key), hi.value) for key, _, hi in tree]
    if tree is None:
        store.put_files([path], [oid])
    elif not store.exists(oid):  # the listing last: a listing in the bucket means its files are there
        store.put_files([p for p, _ in files], [o for _, o in files])
        store.put_bytes(oid, tree.as_bytes())
    if cache is not None:
        for p, o in files:
            cache.add(Path(p), o)
        if tree is not None:
            cache.add_bytes(oid, tree.as_bytes())
    return {"path": rel, "oid": oid}


def fetch(store: Store | NodeCache, root: str | os.PathLike, item: dict) -> list[tuple[str, str]]:
    """``item`` ({"path", "oid"}) from the bucket (or a node's cache of it) into ``root/path``, replacing what is
    there by a rename (a file) or two (a directory: the old one moved aside, the new one in, the old one removed).
    -> [(file path, md5)] of what it wrote."""
    dest = Path(root) / item["path"]
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".tmp"))
    try:
        if not item["oid"].endswith(".dir"):
            store.get_file(item["oid"], tmp / "f")
            os.replace(tmp / "f", dest)
            return [(str(dest), item["oid"])]
        files = [(e["relpath"], e["md5"]) for e in json.loads(store.read(item["oid"]))]
        for rel, oid in files:
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            store.get_file(oid, tmp / rel)
        old = None
        if dest.is_dir() and not dest.is_symlink():
            old = Path(tempfile.mkdtemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".old"))
            os.replace(dest, old / "d")
        elif dest.exists() or dest.is_symlink():
            dest.unlink()
        os.replace(tmp, dest)
        if old is not None:
            shutil.rmtree(old)
        return [(str(dest / rel), oid) for rel, oid in files]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def tree_root(root: str | os.PathLike) -> tuple[str, str]:
    """-> (the top of the git working tree that holds the DVC repository ``root``, ``root`` from there as a POSIX
    path, "." when they are one). A DVC project nested in a git repository (the quick profile,
    ``experiments/quick``) depends on files of the repository outside it (``../../data/strecha``): the packed tree and
    the paths that travel start at the top. Outside any git repository: the root itself."""
    r = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=root, capture_output=True, text=True)
    top = os.path.realpath(r.stdout.strip()) if r.returncode == 0 and r.stdout.strip() else os.path.realpath(root)
    return top, Path(os.path.relpath(os.path.realpath(root), top)).as_posix()


def pack_tree(root: str | os.PathLike) -> bytes:
    """The working tree as git sees it (tracked files and new ones not ignored; ``.dvc/config`` included, not the
    DVC cache or git-ignored data) as a gzip'd tar whose bytes depend on the files only (names sorted, times and
    owners zeroed), so an unchanged tree is one object in the bucket."""
    names = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=root,
                           check=True, capture_output=True).stdout.decode().split("\0")
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=1, format=tarfile.PAX_FORMAT) as tar:
        for name in sorted(set(filter(None, names))):
            path = os.path.join(root, name)
            if not os.path.lexists(path):  # deleted, not yet staged
                continue
            info = tar.gettarinfo(path, arcname=name)
            info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
            if info.isreg():
                with open(path, "rb") as f:
                    tar.addfile(info, f)
            else:
                tar.addfile(info)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------- the driver


class Workspace:
    """The driver's side: the store, the packed code tree's md5 (the git working tree that holds the DVC repository:
    ``top``, with the repository at ``sub`` in it), the dependencies already in the bucket."""

    def __init__(self, value: str, root: str | os.PathLike):
        self.root = str(root)
        self.top, self.sub = tree_root(root)
        self.store, self.conf = open_store(value, root)
        tree = pack_tree(self.top)
        self.tree = hashlib.md5(tree).hexdigest()
        self.store.put_bytes(self.tree, tree)
        self.sent: dict[str, tuple[tuple, dict]] = {}  # path -> (its stat, {"path", "oid"}) this run uploaded
        self._repo = None

    def _open(self):
        if self._repo is None:
            from dvc.repo import Repo

            self._repo = Repo(self.root)
        return self._repo

    def send(self, paths: list[str]) -> list[dict]:
        """A stage's dependencies (paths from the top of the tree, stage_paths) into the bucket. -> their {"path",
        "oid"}; a missing one is left out (the stage then fails on it, as DVC reports a missing dependency)."""
        out = []
        for rel in paths:
            path = os.path.join(self.top, rel)
            if not os.path.exists(path):
                continue
            st = os.stat(path)
            key = (st.st_ino, st.st_size, st.st_mtime_ns)
            if rel not in self.sent or self.sent[rel][0] != key or os.path.isdir(path):
                self.sent[rel] = (key, push(self.store, self._open(), self.top, rel))
            out.append(self.sent[rel][1])
        return out

    def bring_back(self, outs: list[dict]) -> None:
        """A finished stage's outputs from the bucket into the workspace; a cached one also into the DVC cache, as
        ``dvc repro`` commits it."""
        from dvc_objects.fs import LocalFileSystem

        for item in outs:
            written = fetch(self.store, self.root, item)
            if item.get("cached"):
                cache = self._open().cache.local
                cache.add([p for p, _ in written], LocalFileSystem(), [o for _, o in written])
                if item["oid"].endswith(".dir"):
                    cache.add_bytes(item["oid"], self.store.read(item["oid"]))
            path = os.path.join(self.root, item["path"])
            if os.path.isfile(path):  # a dependent's send need not hash it again (its key: the path from the top)
                st = os.stat(path)
                rel = os.path.normpath(os.path.join(self.sub, item["path"]))
                self.sent[rel] = ((st.st_ino, st.st_size, st.st_mtime_ns), {"path": rel, "oid": item["oid"]})

    def close(self) -> None:
        if self._repo is not None:
            self._repo.close()
            self._repo = None


def stage_paths(stage, top: str | os.PathLike) -> list[str]:
    """The stage's dependencies that travel (every one but parameters files, which come with the code tree), as
    paths from ``top``, the top of the git working tree (tree_root). RlsacError for one outside it (no node could
    fetch it by that path)."""
    from dvc.dependency import ParamsDependency

    out = []
    for d in stage.deps:
        if isinstance(d, ParamsDependency):
            continue
        rel = os.path.relpath(os.path.realpath(d.fs_path), top)
        if rel.startswith(".."):
            raise RlsacError(f"--remote: {stage.addressing} depends on {d.fs_path}, outside the repository's git "
                             f"working tree ({top})")
        out.append(Path(rel).as_posix())
    return out


# ------------------------------------------------------------------------------------------------- a node


def _node_dir() -> Path:
    base = Path(os.environ.get(NODE_DIR_ENV) or Path(tempfile.gettempdir()) / "rlsac-node")
    base.mkdir(parents=True, exist_ok=True)
    return base


class NodeCache:
    """The objects a node fetched from the bucket or its stages made, by md5, under ``<node dir>/objects`` (issue
    #50, item 4): a stage that runs on the node where its parent ran (the scheduler asks Ray for that node) reads the
    parent's outputs from here, not from the bucket. An object appears by a rename, whole; a stage gets a copy (a
    stage that wrote into an input in place would change the cache otherwise). Nothing is evicted: the folder can
    be deleted between runs."""

    def __init__(self, store: Store, base: Path | None = None):
        self.store, self.base = store, base or _node_dir() / "objects"
        self.hits = 0  # objects found here instead of downloaded

    def _path(self, oid: str) -> Path:
        return self.base / oid[:2] / oid[2:]

    def get_file(self, oid: str, dest: Path) -> None:
        """The object ``oid`` into ``dest`` (a new file): from the cache, else from the bucket into the cache."""
        path = self._path(oid)
        if path.exists():
            self.hits += 1
        else:
            with atomic_path(path) as tmp:
                self.store.get_file(oid, tmp)
        shutil.copyfile(path, dest)

    def read(self, oid: str) -> bytes:
        """A directory's listing."""
        path = self._path(oid)
        if path.exists():
            self.hits += 1
            return path.read_bytes()
        data = self.store.read(oid)
        self.add_bytes(oid, data)
        return data

    def add(self, src: Path, oid: str) -> None:
        """A file the node made (a finished stage's output, never written again): linked in, else copied."""
        path = self._path(oid)
        if path.exists():
            return
        with atomic_path(path) as tmp:
            os.unlink(tmp)
            _link_or_copy(src, tmp)

    def add_bytes(self, oid: str, data: bytes) -> None:
        path = self._path(oid)
        if path.exists():
            return
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)


def _tree_dir(store: Store, oid: str) -> Path:
    """The code tree, fetched and unpacked once per node (a rename makes it appear whole): each stage's folder is a
    copy of it by hard links (the quick profile's tree is 9,300 files, 85 MB packed; unpacking it for every stage
    cost seconds a stage). Safe because a stage never writes into a file of the tree in place: its outputs are
    removed before its command runs (rlsac.runners.dvc_stage.run), so what it writes are new files, and DVC's .gitignore
    edits are recorded, not made (rlsac.runners.dvc_stage)."""
    path = _node_dir() / "trees" / oid
    if not path.is_dir():
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{oid}.", suffix=".tmp"))
        try:
            store.get_file(oid, tmp / "tree.tar.gz")
            with tarfile.open(tmp / "tree.tar.gz") as tar:
                tar.extractall(tmp / "tree", filter="tar")
            try:
                os.rename(tmp / "tree", path)
            except OSError:
                if not path.is_dir():  # a real failure, not another task of the node making it first (theirs is ours)
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    return path


def _link_or_copy(src: str | os.PathLike, dest: str | os.PathLike) -> None:
    """``dest`` (absent) as a hard link to ``src``, a copy where a link is refused (another file system)."""
    try:
        os.link(src, dest)
    except OSError:
        shutil.copy2(src, dest)


def _link_copy(src: Path, dest: Path) -> None:
    """``src``'s files into the folder ``dest`` by hard links (symbolic links as links), copies where a link is
    refused."""
    shutil.copytree(src, dest, symlinks=True, copy_function=_link_or_copy, dirs_exist_ok=True)


def run_on_node(conf: dict, tree: str, spec: dict, deps: list[dict], env: dict[str, str], log: str,
                run: Callable[..., dict], sub: str = ".") -> dict:
    """A Ray task's body on a node that shares no folder with the driver: a fresh folder with the code tree and the
    stage's inputs, ``run(folder, spec, env, log)`` (the direct runner), then the outputs into the bucket. -> run's
    result with "outs" [{"path", "oid", "cached"}], "ignore" as paths from the root, "log_text"; the folder is
    removed. ``log``: the log's path from the root; ``sub``: the DVC repository in the tree (Workspace.sub); ``deps``'
    paths are from the tree's top, the outputs' from the repository. "downloads" and "cache_hits": the objects it read
    from the bucket and from the node's cache (NodeCache)."""
    store = Store(conf)
    cache = NodeCache(store)
    work = Path(tempfile.mkdtemp(prefix="stage-", dir=_node_dir()))
    try:
        _link_copy(_tree_dir(store, tree), work)
        # DVC's output checks ask git (an output git tracks is refused): an empty repository, nothing tracked
        subprocess.run(["git", "init", "-q"], cwd=work, check=True)
        for item in deps:
            fetch(cache, work, item)
        # the stage runs the driver's code (the tree's rlsac), not whatever version this node's environment holds
        env = {**env, "PYTHONPATH": os.pathsep.join(filter(None, [str(work), env.get("PYTHONPATH")]))}
        root = work / sub
        r = run(str(root), spec, env, str(root / log))
        r["log_text"] = (root / log).read_text(errors="replace") if (root / log).exists() else ""
        r["ignore"] = [os.path.relpath(p, root) for p in r.get("ignore") or []]
        if r["status"] == "done":
            r["outs"] = _push_outs(store, root, spec, r["entry"], cache)
            r["out_bytes"] = sum(_size(root / o["path"]) for o in r["outs"])
        r["downloads"], r["cache_hits"] = store.downloads, cache.hits
        return r
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _size(path: Path) -> int:
    """Bytes of a file, or of the files under a directory."""
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _push_outs(store: Store, work: Path, spec: dict, entry: dict, cache: NodeCache | None = None) -> list[dict]:
    """Every output of the finished stage into the bucket (and the node's cache); each md5 must be its lock
    entry's."""
    from dvc.repo import Repo

    base = Path(os.path.dirname(spec["dvcfile"])) / spec["definition"].get("wdir", ".")
    cached = _cached(spec["definition"])
    outs = []
    with Repo(str(work)) as repo:
        for o in entry.get("outs", []):
            rel = os.path.normpath(base / o["path"])
            item = push(store, repo, str(work), rel, cache)
            if item["oid"] != o.get("md5"):
                raise RlsacError(f"{rel}: md5 {item['oid']} on the node, {o.get('md5')} in its lock entry")
            outs.append({**item, "cached": cached.get(o["path"], True)})
    return outs


def _cached(definition: dict) -> dict[str, bool]:
    """Output path (as written in dvc.yaml) -> whether DVC caches it (``cache: false`` says not; metrics and plots
    listed plainly are cached too)."""
    out = {}
    for key in ("outs", "metrics", "plots"):
        for o in definition.get(key) or []:
            if isinstance(o, dict):
                (path, opts), = o.items()
                out[path] = (opts or {}).get("cache", True)
            else:
                out[o] = True
    return out
