"""What ``rlsac pipeline`` prints and logs at the end: the counts, one line per status, the dry run's
plan."""

from __future__ import annotations

import json
import os
from pathlib import Path

from rlsac.runners.plan import AFTER_DATA, CHANGED, REGENERATE, UP_TO_DATE, UPSTREAM, _groups

STATUSES = ("done", "skipped", "failed", "not run", "interrupted")


def _summary(plan: dict, base: dict, skipped: list[str], results: dict, wall: float, workers: int, run,
             track: bool) -> dict:
    """-> the command's result (see ``pipeline``), logged to the run; stages never reached are "not run"."""
    results = dict(results)
    for a in skipped:
        results[a] = {"stage": a, "status": "skipped", "seconds": None}
    for a in plan["todo"]:
        results.setdefault(a, {"stage": a, "status": "not run"})
    results = {a: results[a] for a in plan["order"] if a in results}
    counts = {s: sum(r["status"] == s for r in results.values()) for s in STATUSES}
    run.metrics({f"n_{k.replace(' ', '_')}": v for k, v in counts.items()})
    run.metrics({"wall_s": wall, "workers": workers})
    if track:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "pipeline.json"
            path.write_text(json.dumps({"deps": plan["deps"], "results": results}, indent=1) + "\n")
            run.artifact(path)
    return {**base, "dry_run": False, "results": results, "counts": counts, "wall_s": wall, "workers": workers,
            "run_id": run.run_id}


def _names(items: list[str], width: int = 110) -> str:
    """Comma-separated names cut to about one line: ``a, b, c, ... and 40 more``."""
    out, n = "", 0
    for i, a in enumerate(items):
        piece = (", " if out else "") + a
        if len(out) + len(piece) > width and i < len(items) - 1:
            return out + f", ... and {len(items) - n} more"
        out += piece
        n += 1
    return out


def _shown(path: str) -> str:
    """A path relative to the current directory when it lies under it, else as it is."""
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def _plan_lines(s: dict, by: dict) -> list[str]:
    """The dry run: the count, the stages to run; where some only re-make missing outputs (a clean clone's data),
    what runs after them (one line per stage group when any does), and how the files were checked. A stage that
    waits only on re-made outputs counts as up to date: it is skipped when its turn comes if they match dvc.lock."""
    why = s.get("why") or {}
    waiting = [a for a in s["todo"] if why.get(a) in (AFTER_DATA, UP_TO_DATE)]  # in todo after a waiting stage
    run = [a for a in s["todo"] if a not in set(waiting)]
    lines = [f"pipeline (dry run): {len(run)} to run, {len(by['skipped']) + len(waiting)} up to date of "
             f"{s['n_selected']} stages" + (f" ({len(waiting)} of them once the re-made outputs match dvc.lock)"
                                             if waiting else "")]
    if run:
        lines.append(f"to run   {_names(run)}")
    remake = [a for a in run if why.get(a) == REGENERATE]
    if remake:
        after = [a for a in run if why.get(a) in (CHANGED, UPSTREAM)]
        lines.append(f"plan: {len(remake)} stages re-make missing outputs from unchanged inputs ({_names(remake)}); "
                     f"after them {len(after)} run" + (", by group:" if after else ""))
        if after:
            lines.append("  group                          run  up to date")
            run_g, all_g = _groups(after), _groups([a for a in s["why"] if a not in remake])
            for g, n in all_g.items():
                lines.append(f"  {g:<30} {run_g.get(g, 0):>3}  {n - run_g.get(g, 0):>10}")
    if s.get("how"):
        lines.append(s["how"])
    return lines


def format_summary(s: dict) -> str:
    """The one-screen summary: counts, then one line per status (names cut to a line), failed stages one per
    line with the error's first line and their log (the first 10)."""
    by = {k: [a for a, r in s["results"].items() if r["status"] == k] for k in STATUSES}
    if s["dry_run"]:
        return "\n".join(_plan_lines(s, by))
    head = ", ".join(f"{len(by[k])} {k}" for k in STATUSES if k != "interrupted" or by[k])
    lines = [f"pipeline: {head} of {s['n_selected']} stages in {s['wall_s']:.1f} s"
             + (f" ({s['workers']} CPUs)" if s["workers"] else "")]
    for k in ("done", "skipped"):
        if by[k]:
            lines.append(f"{k:<8} {_names(by[k])}")
    retried = [a for a, r in s["results"].items() if r.get("retried")]
    if retried:  # their worker or node died, then a new run of the stage ended as its status says
        lines.append(f"retried  {_names(retried)} (worker or node lost: {s['results'][retried[0]]['retried'][0]})")
    for a in by["failed"][:10]:
        r = s["results"][a]
        lines.append(f"failed   {a}: {r['error']}" + (f" (log {_shown(r['log'])})" if r.get("log") else ""))
    if len(by["failed"]) > 10:
        lines.append(f"failed   ... and {len(by['failed']) - 10} more")
    if by["not run"]:
        lines.append(f"not run  {_names(by['not run'])}")
    if by["interrupted"]:  # in flight at SIGINT / SIGTERM: their tasks cancelled, their runs ended KILLED
        lines.append(f"interrupted {_names(by['interrupted'])}")
    return "\n".join(lines)
