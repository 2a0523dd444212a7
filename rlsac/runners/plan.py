"""What ``rlsac pipeline`` would run: DVC's stage graph, each stage's reason to run (DVC's rules on
dvc.lock, rlsac.runners.stage_status), and the direct runner's specs and lock writer."""

from __future__ import annotations

import fnmatch
import os
import time
from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError

LOCK_TRIES = 10  # a stage's outputs locked by another dvc process: seconds to wait before giving up


def _address(stage, root: Path) -> str:
    """The stage's address from the repository root (``dvc stage list``): ``name``, ``sub/dvc.yaml:name``, or a
    .dvc file."""
    name, dvcfile = getattr(stage, "name", None), Path(os.path.relpath(stage.dvcfile.path, root)).as_posix()
    return dvcfile if name is None else name if dvcfile == "dvc.yaml" else f"{dvcfile}:{name}"


def load_plan(repo_dir: str | os.PathLike, names: str | None = None, runner: str | None = None,
              remote: bool = False) -> dict:
    """-> {"root", "order" (every runnable stage, dependencies first), "deps" {address: [addresses it needs]},
    "todo" (addresses to run, in order), "selected" (addresses considered), "specs" and "writer"}. With ``runner``
    "direct", "specs" {address: what a task needs to run it, rlsac.runners.dvc_stage.stage_spec} (a ``.dvc`` file's
    stage has none: it keeps ``dvc repro -s``) and "writer" (the lock files' one writer,
    rlsac.runners.dvc_stage.LockWriter), made while the repository lock is held; else {} and None. Raises RlsacError on
    a path that is not a DVC repository, an unreadable pipeline, a lock file not laid out as DVC writes it, or a name
    that matches no stage. With
    ``remote`` (nodes share no disk), "paths" {address: its dependencies that travel,
    rlsac.runners.transfer.stage_paths},
    and RlsacError for a stage to run that only ``dvc repro -s`` runs (a ``.dvc`` file's)."""
    import networkx as nx

    from rlsac.runners.verify import open_repo, pipeline_error

    repo = open_repo(repo_dir)
    try:
        root = Path(repo.root_dir)
        try:
            graph = repo.index.graph  # edges go from a stage to the stages it depends on
        except Exception as e:
            raise pipeline_error(repo_dir, e) from None
        addr = {s: _address(s, root) for s in graph.nodes}
        by_addr = {a: s for s, a in addr.items()}
        if names is not None:  # given: '' or ',' name no stage (an error), not every stage
            chosen = set()
            for name in filter(None, (n.strip() for n in names.split(","))):
                hits = [a for a in by_addr if a == name or fnmatch.fnmatchcase(a, name)
                        or fnmatch.fnmatchcase(a, name + "@*")]  # `train_lines` = every train_lines@...
                if not hits:
                    raise RlsacError(f"no stage matches '{name}' (`dvc stage list` shows the names)")
                chosen.update(hits)
            if not chosen:  # `rlsac pipeline ','` ran nothing at exit 0 (verify refuses the same)
                raise RlsacError(f"stages {names!r}: names no stage (`dvc stage list` shows the names)")
            # what the named stages need comes along (as `dvc repro <stage>`)
            nodes = set()
            for a in chosen:
                nodes |= {by_addr[a], *nx.descendants(graph, by_addr[a])}
        else:
            nodes = set(graph.nodes)
        sub = graph.subgraph(nodes)
        # dependencies first; ties by address so the plan is stable
        ordered = list(nx.lexicographical_topological_sort(sub.reverse(copy=True), key=lambda s: addr[s]))
        runnable = [s for s in ordered if getattr(s, "cmd", None) and not s.frozen]
        run_set = set(runnable)
        deps = {addr[s]: sorted(addr[d] for d in graph.successors(s) if d in run_set) for s in runnable}
        todo: list[str] = []
        why: dict[str, str] = {}
        how = ""
        specs, writer, paths = {}, None, {}
        from dvc.lock import LockError

        for attempt in range(LOCK_TRIES):
            try:
                with repo.lock:
                    todo, (why, how) = [], _reasons(repo, runnable, addr, deps)
                    for s in runnable:  # an upstream stage that runs makes everything downstream of it run
                        if any(d in todo for d in deps[addr[s]]) or why[addr[s]] != UP_TO_DATE:
                            todo.append(addr[s])
                    if runner == "direct" and todo:
                        specs, writer = _direct(repo, root, [by_addr[a] for a in todo])
                    if remote and todo:
                        paths = _travelling(root, [by_addr[a] for a in todo], specs)
                break
            except LockError as e:  # another dvc process holds the repository or a stage's outputs (or has
                # just been killed and is not yet reaped: DVC drops its entries once the process is gone)
                if attempt == LOCK_TRIES - 1:
                    raise RlsacError(f"{repo_dir}: {' '.join(str(e).split())[:300]}") from None
                time.sleep(1.0)
    finally:
        repo.close()
    return {"root": root, "order": [addr[s] for s in runnable], "deps": deps, "todo": todo, "why": why, "how": how,
            "selected": sorted(addr[s] for s in ordered), "specs": specs, "writer": writer, "paths": paths}


def _direct(repo, root: Path, stages: list) -> tuple[dict, Any]:
    """The direct runner's part of the plan: each stage's spec and the lock files' writer."""
    from rlsac.runners.dvc_stage import LockWriter, stage_spec

    files: dict = {}
    for s in stages:  # one dvc.yaml object per file: each stage's own would parse its lock file again (3 s each)
        s.dvcfile = files.setdefault(s.path, s.dvcfile)
    specs = {_address(s, root): stage_spec(s, root) for s in stages}
    return {a: sp for a, sp in specs.items() if sp is not None}, LockWriter(repo, stages)


def _travelling(root: Path, stages: list, specs: dict) -> dict[str, list[str]]:
    """--remote's part of the plan: each stage's dependencies that go through the bucket (paths from the top of the
    git working tree: a nested DVC project's stages read files of the repository around it)."""
    from rlsac.runners.transfer import stage_paths, tree_root

    top, _ = tree_root(root)
    out = {}
    for s in stages:
        a = _address(s, root)
        if a not in specs:
            raise RlsacError(f"--remote: {a} is a .dvc file's stage (`dvc repro -s` runs it, in a shared folder only)")
        out[a] = stage_paths(s, top)
    return out


# Why a stage is out of date (the dry run's plan): its own change; an upstream stage's change; only its outputs are
# missing (git-ignored data a clean clone lacks: re-made from unchanged inputs, they are what dvc.lock recorded); only
# inputs that such a stage re-makes are missing (up to date once they are back); nothing.
CHANGED, UPSTREAM, REGENERATE, AFTER_DATA, UP_TO_DATE = ("changed", "upstream changed", "outputs missing",
                                                        "inputs missing", "up to date")


def _reasons(repo, runnable: list, addr: dict, deps: dict) -> tuple[dict[str, str], str]:
    """({address: one of the reasons above}, how the files were checked), in dependency order, by DVC's rules on
    dvc.lock and the files' md5s (rlsac.runners.stage_status: each file hashed once, kept by size and time across
    plans). A missing input counts as a change unless a stage that only re-makes missing outputs makes it: it is one of
    their outputs or lies inside one (``fold_data`` records the folder data/folds/<regime>/<fold>, later stages read
    files in it)."""
    from rlsac.runners.stage_status import Status

    status = Status(repo)
    why: dict[str, str] = {}
    remade: list[str] = []  # output paths of the stages that only re-make missing outputs

    def remade_by_data(d) -> bool:
        path = str(d.fs_path)
        return status.missing(d) and any(path == o or path.startswith(o.rstrip(os.sep) + os.sep) for o in remade)

    for s in runnable:
        a = addr[s]
        changed = [d for d in s.deps if status.changed(d)]
        own = (s.changed_stage() or s.always_changed or s.is_callback
               or any(not remade_by_data(d) for d in changed))
        if own:
            why[a] = CHANGED
        elif any(why[u] in (CHANGED, UPSTREAM) for u in deps[a]):
            why[a] = UPSTREAM
        elif status.changed_outs(s):
            why[a] = REGENERATE
            remade.extend(str(o.fs_path) for o in s.outs)
        else:
            why[a] = AFTER_DATA if changed else UP_TO_DATE
    status.hashes.save()
    return why, status.hashes.summary()


def _groups(addresses: list[str]) -> dict[str, int]:
    """Stage group (the name before ``@``) -> how many of ``addresses`` it holds, in first-seen order."""
    out: dict[str, int] = {}
    for a in addresses:
        g = a.split("@", 1)[0]
        out[g] = out.get(g, 0) + 1
    return out
