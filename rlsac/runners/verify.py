"""``rlsac verify``: re-run committed pipeline stages in a scratch copy and compare their outputs byte for byte.

A "committed" stage is one whose outputs are all ``cache: false``: its results are plain git files, so a
re-run must give the same bytes (timings live in untracked ``timing.json`` sidecars for this reason). Stages
with DVC-cached outputs are left to ``dvc repro`` / ``dvc status``; training stages (minutes to hours) only
run when asked for.

Each stage runs in ``<scratch>/repo``, a copy of the git-tracked files (as they are in the working tree) plus
links to the untracked inputs (generated data), so the workspace is never written. Every stage sees the
committed outputs of its upstream stages: the outputs of a stage that differs or fails are moved aside to
``<scratch>/rerun/<stage>/`` and the committed ones put back before the next stage runs.
"""

from __future__ import annotations

import contextlib
import csv
import fnmatch
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

from rlsac.errors import RlsacError

IGNORED_NAMES = {"timing.json"}  # untracked per-run sidecars (rlsac.evaluation.evaluate.TIMING_FILE), never committed
# stages that train (minutes each): by name, besides any stage writing a checkpoint; fold_select* replays a training
TRAINING_WORDS = ("train", "select")
DEFAULTS = {"stages": None, "sample": None, "seed": 0, "include_train": False, "scratch": None, "keep": False,
            "repo": ".", "tolerance": None, "workers": 1}


def verify(options: dict[str, Any], track: bool = True, report: Callable[[str], None] | None = None,
           checked: Callable[[], None] | None = None) -> dict:
    """Verify the stages ``options`` selects (keys of DEFAULTS); ``report`` gets one line per stage as it
    finishes; ``checked`` is called once every option and input has been checked, before any work.
    ``tolerance``: JSON numbers may differ by this much, CSV cells that are numbers are not compared
    (per-instance errors; another numeric platform, rlsac.numerics): a stage that agrees so is "close".
    -> {"results": [{stage, status, detail, seconds}], "n_identical", "n_close", "n_differs", "n_failed",
    "n_stages", "scratch" (None once removed), "run_id"}."""
    from rlsac.tracking import check_store, start_run

    o = {**DEFAULTS, **{k: v for k, v in options.items() if v is not None}}
    if o["tolerance"] is not None and not 0 <= o["tolerance"] < float("inf"):
        raise RlsacError(f"--tolerance must be a finite number >= 0, got {o['tolerance']}")
    if not isinstance(o["workers"], int) or o["workers"] < 1:
        raise RlsacError(f"--workers must be at least 1, got {o['workers']}")
    if o["sample"] is not None and o["sample"] < 1:  # before reading the pipeline (minutes on a large one)
        raise RlsacError(f"--sample {o['sample']}: must be at least 1")
    root, stages = load_stages(o["repo"])
    selected = select(stages, o["stages"], o["sample"], o["seed"], o["include_train"])
    tracked = git_files(root)
    # every check before any work and before the MLflow run: a user error leaves no run and no scratch behind
    check_inputs(root, selected, stages)
    scratch = _check_scratch(o["scratch"])
    check_store(track, "verify")
    if checked is not None:
        checked()

    made = scratch is None or not scratch.exists()
    if scratch is None:
        scratch = Path(tempfile.mkdtemp(prefix="rlsac-verify-"))
    scratch.mkdir(parents=True, exist_ok=True)
    results: list[dict] = []
    try:
        work = scratch / "repo"
        copy_workspace(root, tracked, work, [d for s in selected for d in s["deps"]])
        params = {"stages": o["stages"] or "", "sample": o["sample"], "seed": o["seed"],
                  "include_train": o["include_train"], "repo": str(root), "tolerance": o["tolerance"],
                  "selected": ",".join(s["address"] for s in selected)}
        with start_run("verify", f"verify {len(selected)} stages", params=params, enabled=track) as run:
            results = _run_all(root, work, scratch, selected, report or (lambda line: None), o["tolerance"],
                               o["workers"])
            counts = {f"n_{k}": sum(r["status"] == k for r in results)
                      for k in ("identical", "close", "differs", "failed")}
            run.metrics(counts)
            (scratch / "verify.json").write_text(json.dumps(results, indent=2) + "\n")
            run.artifact(scratch / "verify.json")
    finally:
        if not o["keep"]:
            if made:
                shutil.rmtree(scratch, ignore_errors=True)
            else:  # a --scratch folder that existed (empty) before: leave the folder, remove what we wrote
                for p in scratch.iterdir():
                    _remove(p)
    return {"results": results, **counts, "n_stages": len(results), "scratch": str(scratch) if o["keep"] else None,
            "run_id": run.run_id}


def format_result(r: dict) -> str:
    """``identical  <stage>  (<s> s)`` / ``differs    <stage>: <file>: <detail>`` / ``failed     <stage>: ...``."""
    if r["status"] == "identical":
        return f"identical  {r['stage']}  ({r['seconds']:.1f} s)"
    if r["status"] == "close":
        return f"close      {r['stage']}  ({r['seconds']:.1f} s): not the same bytes, {r['detail']}"
    return f"{r['status']:<9}  {r['stage']}: {r['detail']}"


def format_summary(s: dict) -> str:
    close = f"{s['n_close']} close, " if s.get("n_close") else ""
    return (f"verify: {s['n_identical']} identical, {close}{s['n_differs']} differ, {s['n_failed']} failed of "
            f"{s['n_stages']} stages (scratch: {s['scratch'] or 'removed'})")


# ------------------------------------------------------------------ stages


def pipeline_error(repo_dir: str | os.PathLike, e: Exception) -> RlsacError:
    """DVC's failure to read a pipeline as one line, not its traceback."""
    return RlsacError(f"{repo_dir}: cannot read the DVC pipeline ({e.__class__.__name__}: "
                      f"{' '.join(str(e).split())[:200]})")


def open_repo(repo_dir: str | os.PathLike):
    """DVC's Repo at ``repo_dir`` (the caller closes it); RlsacError on a path that is not a DVC repository's root
    (a folder inside one included) or an unparsable dvc.yaml."""
    from dvc.repo import Repo

    try:
        repo = Repo(str(repo_dir))
    except Exception as e:
        raise pipeline_error(repo_dir, e) from None
    if Path(repo.root_dir).resolve() != Path(repo_dir).resolve():  # DVC looks upward: the enclosing repository
        root = repo.root_dir
        repo.close()
        raise RlsacError(f"{repo_dir}: not a DVC repository's root (it lies inside the one at {root})")
    return repo


def load_stages(repo_dir: str | os.PathLike) -> tuple[Path, list[dict]]:
    """The pipeline's stages as plain dicts (address, cmds, wdir, deps, outs, committed, train, why), paths
    relative to the DVC root; DVC's Repo is closed before returning."""
    from dvc.dependency.param import ParamsDependency

    repo = open_repo(repo_dir)
    try:
        root = Path(repo.root_dir)
        rel = lambda p: Path(os.path.relpath(p, root)).as_posix()  # noqa: E731
        stages = []
        for st in repo.index.stages:
            cmd = getattr(st, "cmd", None)
            outs = [o for o in st.outs if o.protocol == "local"]
            cached = [rel(o.fs_path) for o in outs if o.use_cache]
            # st.addressing is relative to the current directory: make it relative to the root (dvc stage list);
            # a .dvc file's stage has no name, its address is the file
            name, dvcfile = getattr(st, "name", None), rel(st.dvcfile.path)
            address = dvcfile if name is None else name if dvcfile == "dvc.yaml" else f"{dvcfile}:{name}"
            why = (f"its outputs are DVC-cached ({cached[0]}); `dvc repro` and `dvc status` check those" if cached
                   else "it has no command or no outputs" if not cmd or not outs else None)
            stages.append({
                "address": address, "cmds": [cmd] if isinstance(cmd, str) else list(cmd or []),
                "wdir": rel(st.wdir),
                "deps": [rel(d.fs_path) for d in st.deps
                         if not isinstance(d, ParamsDependency) and d.protocol == "local"],
                "outs": [rel(o.fs_path) for o in outs], "committed": why is None, "why": why,
                "train": is_training(address, [rel(o.fs_path) for o in outs])})
    finally:
        repo.close()
    return root, stages


def is_training(address: str, outs: list[str]) -> bool:
    """Whether a stage trains (left out of a sample unless --include-train): it writes a checkpoint, or its name (the
    stage's, before any @item) holds a word of ``TRAINING_WORDS``."""
    name = address.split("@")[0].split(":")[-1]
    return any(p.endswith(".pt") for p in outs) or any(w in name for w in TRAINING_WORDS)


def select(stages: list[dict], names: str | None, sample: int | None, seed: int, include_train: bool) -> list[dict]:
    """--stages (addresses, fnmatch patterns or a foreach name) or every committed stage (training ones only
    with --include-train), then --sample N of them drawn with random.Random(seed); sorted by address."""
    if names is not None:  # given: '' or ',' name no stage (an error below), not every stage
        chosen: dict[str, dict] = {}
        for name in filter(None, (n.strip() for n in names.split(","))):
            hits = [s for s in stages if fnmatch.fnmatchcase(s["address"], name)
                    or fnmatch.fnmatchcase(s["address"], name + "@*")]  # `fold_eval` = every fold_eval@...
            if not hits:
                raise RlsacError(f"no stage matches '{name}' (dvc stage list shows the names)")
            ok = [s for s in hits if s["committed"]]
            if not ok:  # a pattern may also match data stages: only one that matches nothing else is an error
                raise RlsacError(f"{hits[0]['address']} cannot be verified: {hits[0]['why']}")
            chosen.update((s["address"], s) for s in ok)
        if not chosen:
            raise RlsacError(f"--stages {names!r}: names no stage (dvc stage list shows the names)")
        pool = list(chosen.values())
    else:
        pool = [s for s in stages if s["committed"] and (include_train or not s["train"])]
    if not pool:
        raise RlsacError("no committed stage to verify (stages whose outputs are all `cache: false`)")
    pool.sort(key=lambda s: s["address"])
    if sample is not None:
        if sample < 1:
            raise RlsacError(f"--sample {sample}: must be at least 1")
        pool = sorted(random.Random(seed).sample(pool, min(sample, len(pool))), key=lambda s: s["address"])
    return pool


def check_inputs(root: Path, selected: list[dict], stages: list[dict]) -> None:
    """Every dependency and every committed output of the selected stages exists in the workspace."""
    for s in selected:
        for d in s["deps"]:
            if not os.path.lexists(root / d):
                hint = f"`dvc repro -s {p}`" if (p := producer(d, stages)) else "`dvc repro`"
                raise RlsacError(f"{d}: missing dependency of {s['address']} (run {hint} first)")
        for out in s["outs"]:
            if not (root / out).exists():
                raise RlsacError(f"{out}: committed output of {s['address']} is missing "
                                 f"(`git checkout -- {out}` restores it)")


def producer(path: str, stages: list[dict]) -> str | None:
    """The one stage whose output is ``path``, holds it, or lies inside it (None if none or several)."""
    found = {s["address"] for s in stages for o in s["outs"] if _meets(o, path)}
    return found.pop() if len(found) == 1 else None


def _meets(p: str, q: str) -> bool:
    """Whether two repository paths are one, or one lies inside the other (a folder output and a file in it)."""
    return p == q or p.startswith(q.rstrip("/") + "/") or q.startswith(p.rstrip("/") + "/")


# ------------------------------------------------------------------ scratch copy


def git_files(root: Path) -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        raise RlsacError(f"{root}: `git ls-files` failed ({' '.join(str(getattr(e, 'stderr', e) or e).split())[:200]})"
                         "; verify needs a git repository") from None
    return [p for p in out.decode().split("\0") if p]


def _check_scratch(path: str | None) -> Path | None:
    from rlsac.io import check_writable

    if path is None:
        check_writable(Path(tempfile.gettempdir()), "the scratch folder", folder=True)
        return None
    p = Path(path).absolute()
    if p.exists() and (not p.is_dir() or any(p.iterdir())):
        raise RlsacError(f"--scratch {path}: exists and is not an empty folder (verify removes what it writes there)")
    return check_writable(p, "the scratch folder", folder=True)


def copy_workspace(root: Path, tracked: list[str], work: Path, deps: list[str]) -> None:
    """Copy the git-tracked files (working-tree contents, symlinks as symlinks) to ``work``, then link every
    untracked dependency (generated data, a DVC-cached folder) to its absolute workspace path."""
    for rel in tracked:
        src, dst = root / rel, work / rel
        if not (src.is_symlink() or src.is_file()):  # deleted in the working tree, or a submodule
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            os.symlink(os.readlink(src), dst)
        else:
            shutil.copy(src, dst)  # contents and mode bits
    # a dependency that is (or holds) a tracked file exists by now; parents first, as a linked folder then
    # already provides the files beneath it
    for d in sorted(set(deps), key=lambda d: d.count("/")):
        if os.path.lexists(work / d):
            continue
        (work / d).parent.mkdir(parents=True, exist_ok=True)
        os.symlink(root / d, work / d)


# ------------------------------------------------------------------ running and comparing


def _run_all(root: Path, work: Path, scratch: Path, selected: list[dict], report: Callable[[str], None],
             tolerance: float | None = None, workers: int = 1) -> list[dict]:
    """Run and compare each selected stage, ``workers`` at a time; two stages where one reads or writes what the
    other writes never run at once (a re-run deletes its outputs first). -> the results in ``selected``'s order."""
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    from rlsac.progress import tqdm
    from rlsac.runners import warm

    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{scratch / 'mlflow.db'}", "CI": "true"}
    env.setdefault("OMP_NUM_THREADS", "1")
    # the stages call `rlsac`/`python`: the same installation as this process, even from an unactivated venv
    bindir = os.path.dirname(sys.executable)
    if bindir not in env.get("PATH", "").split(os.pathsep):
        env["PATH"] = bindir + os.pathsep + env.get("PATH", "")
    (scratch / "logs").mkdir(exist_ok=True)
    ignore = _ignore_spec(root)
    results: dict[str, dict] = {}
    pending, running = list(selected), {}

    with tqdm(total=len(selected), desc="verify", unit="stage", disable=None, leave=False) as bar, \
            ThreadPoolExecutor(max_workers=workers) as pool, contextlib.ExitStack() as stack:
        stack.callback(warm.stop_all)  # the threads' warm processes, once every stage has ended
        while pending or running:
            for s in [s for s in pending if not any(_overlap(s, r) for r in running.values())][:workers - len(running)]:
                pending.remove(s)
                running[pool.submit(run_stage, s, root, work, scratch, env, ignore, tolerance)] = s
            bar.set_postfix_str(",".join(s["address"] for s in running.values()))
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in done:
                r = f.result()
                results[running.pop(f)["address"]] = r
                with bar.external_write_mode():
                    report(format_result(r))
                bar.update(1)
    return [results[s["address"]] for s in selected]


def _overlap(a: dict, b: dict) -> bool:
    """Whether stages ``a`` and ``b`` may not run at once: an output of one is, holds or lies in a path the other
    reads or writes."""
    return any(_meets(o, p) for o in a["outs"] for p in b["deps"] + b["outs"]) or \
        any(_meets(o, p) for o in b["outs"] for p in a["deps"])


def run_stage(s: dict, root: Path, work: Path, scratch: Path, env: dict, ignore,
              tolerance: float | None = None) -> dict:
    """Delete the stage's outputs in ``work``, run its command(s), compare each output with the workspace
    (byte for byte; then, with ``tolerance``, by value: status "close")."""
    r = {"stage": s["address"], "status": "identical", "detail": "", "seconds": 0.0}
    real = os.path.realpath(work)
    for out in s["outs"]:
        if not os.path.realpath(work / out).startswith(real + os.sep):  # never delete through a link
            return {**r, "status": "failed", "detail": f"{out}: lies under a linked workspace folder, not re-run"}
        _remove(work / out)
    log = scratch / "logs" / (s["address"].replace("/", "_").replace(":", "_") + ".log")
    t0 = time.perf_counter()
    with open(log, "wb") as f:
        for cmd in s["cmds"]:  # a list of commands runs in order, stopping at the first failure, as in DVC
            rc = _start(["bash", "-c", cmd], cwd=work / s["wdir"], env=env, stdout=f, stderr=subprocess.STDOUT,
                        stdin=subprocess.DEVNULL).wait()
            if rc:
                break
    r["seconds"] = time.perf_counter() - t0
    if rc:
        lines = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
        r.update(status="failed", detail=f"exit {rc}: {lines[-1].strip() if lines else '(no output)'} (log {log})")
    else:
        for out in s["outs"]:
            if detail := compare(root / out, work / out, out, ignore):
                r.update(status="differs", detail=detail)
                break
        if r["status"] == "differs" and tolerance is not None:
            far = next((d for out in s["outs"] if (d := compare(root / out, work / out, out, ignore, tolerance))),
                       None)
            if far:
                r["detail"] = far
            else:
                r.update(status="close", detail=f"every JSON number within {tolerance:g} ({r['detail']})")
    if r["status"] != "identical":  # later stages must see the committed outputs; keep these for inspection
        aside = scratch / "rerun" / log.stem
        for out in s["outs"]:
            if os.path.lexists(work / out):
                (aside / out).parent.mkdir(parents=True, exist_ok=True)
                os.replace(work / out, aside / out)
            (shutil.copytree if (root / out).is_dir() else shutil.copy)(root / out, work / out)
    return r


def _start(argv: list[str], **kwargs):
    """A stage's command line, started warm where it is a plain ``rlsac ...`` call (rlsac.runners.warm: the imports
    done once per thread), else as a child of this process."""
    from rlsac.runners import warm

    return warm.start(argv, lambda pgid: None, subprocess.Popen, **kwargs)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif os.path.lexists(p):
        p.unlink()


def _ignore_spec(root: Path):
    """The repo's .dvcignore (gitignore syntax, via pathspec when installed; DVC depends on it)."""
    try:
        import pathspec

        return pathspec.GitIgnoreSpec.from_lines((root / ".dvcignore").read_text().splitlines())
    except (ImportError, OSError):
        return None


def _files(folder: Path, rel: str, ignore) -> set[str]:
    names = set()
    for dirpath, _, files in os.walk(folder):
        for f in files:
            name = (Path(dirpath) / f).relative_to(folder).as_posix()
            if f not in IGNORED_NAMES and not (ignore and ignore.match_file(f"{rel}/{name}")):
                names.add(name)
    return names


def compare(committed: Path, rerun: Path, rel: str, ignore=None, tolerance: float | None = None) -> str | None:
    """None if the re-run output equals the committed one (with ``tolerance``: agrees by value, see
    ``close_file``), else ``<file>: <first difference>``."""
    if not rerun.exists():
        return f"{rel}: not written by the re-run"
    if committed.is_dir() != rerun.is_dir():
        return f"{rel}: committed a {'folder' if committed.is_dir() else 'file'}, re-run wrote the other"
    if not committed.is_dir():
        return compare_file(committed, rerun, rel, tolerance)
    a, b = _files(committed, rel, ignore), _files(rerun, rel, ignore)
    if a != b:
        parts = [f"{what} in re-run: {', '.join(sorted(names)[:5])}{' ...' if len(names) > 5 else ''}"
                 for what, names in (("missing", a - b), ("extra", b - a)) if names]
        return f"{rel}: {'; '.join(parts)}"
    for name in sorted(a):
        if detail := compare_file(committed / name, rerun / name, f"{rel}/{name}", tolerance):
            return detail
    return None


def compare_file(committed: Path, rerun: Path, rel: str, tolerance: float | None = None) -> str | None:
    x, y = committed.read_bytes(), rerun.read_bytes()
    if x == y:
        return None
    if tolerance is not None:
        detail = close_file(x, y, committed.suffix.lower(), tolerance)
        return None if detail is None else f"{rel}: {detail}"
    suffix = committed.suffix.lower()
    # JSON by key path; text and CSV by line (CSV: the column); anything else by byte offset
    detail = _json_diff(x, y) if suffix == ".json" else None
    if detail is None:
        detail = _text_diff(x, y, suffix == ".csv")
    if detail is None:
        k = _mismatch(x, y)
        detail = f"first differing byte at offset {k} (committed {len(x)} bytes, re-run {len(y)} bytes)"
    return f"{rel}: {detail}"


_ABSENT = object()


def close_file(x: bytes, y: bytes, suffix: str, tolerance: float) -> str | None:
    """None where two outputs agree by value: JSON with every number within ``tolerance`` and everything else
    equal; CSV with the same header, rows and non-numeric cells (numeric cells are per-instance errors, which
    another platform's rounding may move by any amount: a different minimal set wins); other files byte for
    byte. Else the first disagreement."""
    if suffix == ".json":
        try:
            a, b = json.loads(x), json.loads(y)
        except ValueError:
            return "not JSON"
        found = _first_json_diff(a, b, "", tolerance)
        return None if found is None else f"{_json_difference(*found)} (tolerance {tolerance:g})"
    if suffix == ".csv":
        ra, rb = (list(csv.reader(v.decode(errors="replace").splitlines())) for v in (x, y))
        if len(ra) != len(rb) or ra[:1] != rb[:1]:
            return f"committed has {len(ra)} rows, re-run {len(rb)} (or another header)"
        for i, (fa, fb) in enumerate(zip(ra, rb, strict=True)):
            if len(fa) != len(fb) or any(p != q and not (_number(p) and _number(q))
                                         for p, q in zip(fa, fb, strict=True)):
                return f"line {i + 1}: committed {_short(','.join(fa))!r} re-run {_short(','.join(fb))!r}"
        return None
    return f"first differing byte at offset {_mismatch(x, y)}"


def _number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _json_diff(x: bytes, y: bytes) -> str | None:
    try:
        a, b = json.loads(x), json.loads(y)
    except ValueError:
        return None
    found = _first_json_diff(a, b, "")
    if found is None:  # same values, other formatting: the text diff says where
        return None
    return _json_difference(*found)


def _json_difference(path: str, va, vb) -> str:
    """``<key path> committed <value> re-run <value>`` of ``_first_json_diff``'s find."""
    show = lambda v: "(absent)" if v is _ABSENT else _short(json.dumps(v))  # noqa: E731
    return f"{path or '(top level)'} committed {show(va)} re-run {show(vb)}"


def _first_json_diff(a, b, path: str, tolerance: float | None = None):
    if isinstance(a, dict) and isinstance(b, dict):
        for k in [*a, *(k for k in b if k not in a)]:
            sub = f"{path}.{k}" if path else str(k)
            if (d := _first_json_diff(a.get(k, _ABSENT), b.get(k, _ABSENT), sub, tolerance)) is not None:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        for i in range(max(len(a), len(b))):
            va, vb = a[i] if i < len(a) else _ABSENT, b[i] if i < len(b) else _ABSENT
            if (d := _first_json_diff(va, vb, f"{path}[{i}]", tolerance)) is not None:
                return d
        return None
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in (a, b))
    if tolerance is not None and numbers:  # NaN only matches NaN
        return None if (a != a and b != b) or abs(a - b) <= tolerance else (path, a, b)
    same_nan = isinstance(a, float) and isinstance(b, float) and a != a and b != b
    if type(a) is not type(b) or (a != b and not same_nan):  # 1 vs 1.0 vs true differ in bytes too
        return path, a, b
    return None


def _text_diff(x: bytes, y: bytes, is_csv: bool) -> str | None:
    try:
        la, lb = x.decode().splitlines(), y.decode().splitlines()
    except UnicodeDecodeError:
        return None
    if b"\0" in x or b"\0" in y:
        return None
    i = _mismatch(la, lb)
    if i == min(len(la), len(lb)):
        if len(la) == len(lb):  # only line endings or the final newline differ
            return None
        return f"committed has {len(la)} lines, re-run {len(lb)}"
    if is_csv:
        header = next(csv.reader([la[0]]), [])
        fa, fb = next(csv.reader([la[i]]), []), next(csv.reader([lb[i]]), [])
        j = _mismatch(fa, fb)
        col = header[j] if j < len(header) else f"#{j + 1}"
        va, vb = (f[j] if j < len(f) else "(absent)" for f in (fa, fb))
        return f"line {i + 1}, column {col}: committed {_short(va)} re-run {_short(vb)}"
    return f"line {i + 1}: committed {_short(la[i])!r} re-run {_short(lb[i])!r}"


def _mismatch(a, b) -> int:
    """Index of the first differing item (the shorter length when one is a prefix of the other)."""
    return next((i for i, (p, q) in enumerate(zip(a, b, strict=False)) if p != q), min(len(a), len(b)))


def _short(s: str, n: int = 80) -> str:
    return s if len(s) <= n else s[: n - 3] + "..."
