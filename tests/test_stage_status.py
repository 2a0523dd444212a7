"""The pipeline's plan from dvc.lock and the files' md5s (rlsac.runners.stage_status, issue #63 items 2 and 3): the same
answer as DVC's own ``Stage.changed`` on every kind of change, files hashed once and kept by size and time, and a
clean clone's dry run that runs only the stages whose git-ignored outputs are missing, also when a later stage
reads a file inside a folder such a stage records (``fold_data``'s data/folds/<regime>/<fold>)."""

from __future__ import annotations

import os
import time
from pathlib import Path

from click.testing import CliRunner
from test_ray_pipeline import dvc, make_repo  # tests/ is on sys.path (pytest prepend mode)

from rlsac.cli import cli
from rlsac.runners.stage_status import CACHE, Status

PY = "python -c"
FOLDER = {  # `data` records the folder d (as fold_data does); `x` and `y` read files inside it
    "data": {"cmd": f"{PY} \"import os; os.makedirs('d', exist_ok=True); open('d/x.h5','w').write('x'); "
                    "open('d/y.h5','w').write('y')\"", "outs": ["d"]},
    "x": {"cmd": f"{PY} \"open('x.txt','w').write(open('d/x.h5').read())\"", "deps": ["d/x.h5"], "outs": ["x.txt"]},
    "y": {"cmd": f"{PY} \"open('y.txt','w').write(open('d/y.h5').read())\"", "deps": ["d/y.h5"], "outs": ["y.txt"]},
}


def _dry_run(repo: Path) -> list[str]:
    r = CliRunner().invoke(cli, ["pipeline", "--repo", str(repo), "--dry-run", "--no-tracking"],
                           catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r.output.splitlines()


def test_a_clean_clone_runs_only_the_stage_that_remakes_the_folder(tmp_path):
    repo = make_repo(tmp_path / "repo", FOLDER)
    assert dvc(repo, "repro").returncode == 0
    for f in ("d/x.h5", "d/y.h5"):  # the folder output is git-ignored: a clean clone lacks it
        (repo / f).unlink()
    (repo / "d").rmdir()
    lines = _dry_run(repo)
    assert lines[0] == ("pipeline (dry run): 1 to run, 2 up to date of 3 stages (2 of them once the re-made outputs "
                        "match dvc.lock)"), lines
    assert lines[1] == "to run   data"
    assert lines[2] == "plan: 1 stages re-make missing outputs from unchanged inputs (data); after them 0 run", lines
    assert lines[3].startswith("checked against dvc.lock by md5: "), lines


def _age(repo: Path, seconds: float = 60.0) -> None:
    """Every file's time moved back (a file written in the last seconds is hashed but not kept: racy)."""
    then = time.time() - seconds
    for top, _, files in os.walk(repo):
        if ".git" not in Path(top).parts and ".dvc" not in Path(top).parts:
            for f in files:
                os.utime(Path(top, f), (then, then))


def _compare(repo: Path) -> tuple[dict, Status]:
    """{stage: (DVC's Stage.changed, ours)} and the Status that answered."""
    from rlsac.runners.verify import open_repo

    r = open_repo(repo)
    try:
        with r.lock:  # Stage.changed asserts it, as `dvc status` holds it
            status = Status(r)
            out = {s.name: (s.changed(), s.changed_stage() or any(status.changed(d) for d in s.deps)
                                  or status.changed_outs(s)) for s in r.index.stages}
            status.hashes.save()
    finally:
        r.close()
    return out, status


def test_the_plan_agrees_with_dvc_on_every_change(tmp_path):
    stages = {
        **FOLDER,
        "p": {"cmd": f"{PY} \"open('p.txt','w').write('p')\"", "params": ["a.k"], "outs": ["p.txt"]},
        "q": {"cmd": f"{PY} \"open('q.txt','w').write('q')\"", "params": ["a.other"], "outs": ["q.txt"]},
        "f": {"cmd": f"{PY} \"open('f.txt','w').write(open('in.txt').read())\"", "deps": ["in.txt"],
              "outs": ["f.txt"]},
        "o": {"cmd": f"{PY} \"open('o.txt','w').write('o')\"", "outs": [{"o.txt": {"cache": False}}]},
        "c": {"cmd": f"{PY} \"open('c.txt','w').write('c')\"", "outs": ["c.txt"]},
        "w": {"cmd": f"{PY} \"import os; os.makedirs('w', exist_ok=True); open('w/r.txt','w').write('r')\"",
              "deps": ["d"], "outs": [{"w": {"cache": False}}]},
    }
    repo = make_repo(tmp_path / "repo", stages, {"params.yaml": "a:\n  k: 1\n  other: [1, 2]\n", "in.txt": "in",
                                                 ".dvcignore": "timing.json\n"})
    assert dvc(repo, "repro").returncode == 0
    (repo / "w" / "timing.json").write_text("ignored by DVC: not part of w's md5")
    _age(repo)
    same, status = _compare(repo)
    assert same == {a: (False, False) for a in same}, same  # a folder's md5 (ignoring timing.json) is DVC's
    assert len(status.hashes.read) == 11 and (repo / CACHE).is_file()
    again, status = _compare(repo)  # the next plan reads no file: each is known by its size and time
    assert again == same and not status.hashes.read and len(status.hashes.reused) == 11

    (repo / "params.yaml").write_text("a:\n  k: 2\n  other: [1, 2]\n")  # p's parameter, not q's
    (repo / "in.txt").write_text("IN")  # f's input
    (repo / "o.txt").write_text("O")  # o's output (not cached)
    (repo / "dvc.yaml").write_text((repo / "dvc.yaml").read_text().replace("write('c')", "write('C')"))  # c's cmd
    (repo / "w" / "r.txt").write_text("R")  # a file inside w's folder output, same size
    (repo / "d" / "y.h5").unlink()  # a file inside d: d changed, and x, y and w (they depend on d or in it)
    changed, status = _compare(repo)
    assert {a for a, (dvc_says, _) in changed.items() if dvc_says} == {"p", "f", "o", "c", "w", "data", "y"}
    assert all(dvc_says == ours for dvc_says, ours in changed.values()), changed
    import shutil

    shutil.rmtree(repo / ".dvc" / "cache")  # cached outputs present but not in DVC's cache: changed, for both
    changed, _ = _compare(repo)
    assert {a for a, (dvc_says, _) in changed.items() if dvc_says} == {"p", "q", "f", "o", "c", "w", "data", "x", "y"}
    assert all(dvc_says == ours for dvc_says, ours in changed.values()), changed
