"""Projected wall time of the DVC pipeline on N workers, from stage times (issue #30, item 4).

    python benchmarks/pipeline_projection.py                          # the paper profile, recorded group means
    python benchmarks/pipeline_projection.py --times pipeline.json    # an `rlsac pipeline` run's MLflow artifact
    python benchmarks/pipeline_projection.py --times times.json --workers 1,2,4
    python benchmarks/pipeline_projection.py --from-mlflow sqlite:///mlflow.db --groups   # a record's measured cost

Reads the pipeline's DAG from DVC (``--repo``, nothing is hashed or run) and a time per stage: ``--times`` is
either the ``pipeline.json`` artifact an ``rlsac pipeline`` run logs to MLflow (its dependencies and each stage's
seconds) or a JSON object ``{stage address or fnmatch pattern: seconds}`` (an exact address wins over a pattern,
then the first matching pattern). Without ``--times``: ``RECORDED``, the per-stage means of the portable record's stage
times per group (``reports/cost.md``; 2 cores, ``OMP_NUM_THREADS=1``). ``--from-mlflow URI``: the
times every ``rlsac pipeline`` run of that MLflow store logged as its stages ended (metrics ``stage_s/<address>``, an
interrupted run's included; the latest run's time of a stage wins), over several sittings; a stage with no time takes
its group's mean (the group: the address before ``@``), and the output says how many were measured; with
``--fallback-recorded`` a group none of whose stages was measured takes ``RECORDED``'s times (and is named).
``--from-logs DIR`` (with ``--from-mlflow``): a stage no run logged takes the span of its log under DIR
(``logs/pipeline``: created when the stage started, last written when it ended; GNU ``stat``'s birth time), for the
stages of runs that were killed before their times reached MLflow; a span over ``LOG_OUTLIER`` times its group's
median is a log a later run rewrote (its birth time is the first run's) and is left out.
``--groups``: also a Markdown table of the stage time per group (stages, total, mean, range): issue #27's cost table.

Prints the total stage time (the wall time on one worker), the critical path (the wall time on unlimited
workers) and, for each N of ``--workers``, the wall time of list scheduling on the DAG: whenever a worker is
free it starts the ready stage with the longest path to the end (ties by address). Scheduling overhead, DVC's
own work between stages and contention between stages on a shared machine are not modelled.
"""

from __future__ import annotations

import argparse
import fnmatch
import heapq
import json
import os
import sys
from pathlib import Path

# Seconds per stage: each group's mean stage time in the portable record (reports/cost.md: an `rlsac pipeline
# --workers 2` run's MLflow times and stage logs, 2 cores, DVC's own work included); `tables` and `figures` as recorded
# before (their stages had not run when this was taken)
RECORDED = {
    "calibrate_lines": 3.2, "essential_eval@*": 20.9, "essential_eval_rlsac@*": 77.0,
    "essential_eval_seed@*": 70.2, "essential_train@*": 95.0, "essential_train_seed@*": 88.6,
    "essential_tune@*": 24.2, "essential_tune_rlsac@*": 180.0, "essential_tune_seed@*": 163.2,
    "eval_lines_generalisation@*": 47.3, "eval_lines_generalisation_seed@*": 38.5, "eval_lines_ngransac@*": 23.6,
    "eval_lines_ngransac_seed@*": 23.0, "eval_lines_oracle@*": 22.3, "eval_lines_ours@*": 39.2,
    "eval_lines_ours_seed@*": 41.2, "eval_lines_ransac@*": 20.7, "figures": 25.0, "fold_data@*": 2.5,
    "fold_data_points@*": 2.4, "fold_eval@*": 15.5, "fold_eval_ablation@*": 104.7,
    "fold_eval_ablation_seed@*": 143.3, "fold_eval_fast@*": 27.4, "fold_eval_fast_seed@*": 28.8,
    "fold_eval_lo@*": 125.9, "fold_eval_lo_seed@*": 116.1, "fold_eval_lomethod@*": 58.6, "fold_eval_model@*": 77.2,
    "fold_eval_points_method@*": 41.4, "fold_eval_points_model@*": 119.5, "fold_eval_prob@*": 97.5,
    "fold_eval_prob_seed@*": 98.2, "fold_eval_seed@*": 61.4, "fold_select@*": 183.9, "fold_select_seed@*": 184.3,
    "fold_train@*": 111.9, "fold_train_ablation@*": 95.8, "fold_train_ablation_seed@*": 96.4,
    "fold_train_points@*": 83.4, "fold_train_seed@*": 97.1, "fold_tune@*": 18.4, "fold_tune_ablation@*": 83.5,
    "fold_tune_ablation_seed@*": 109.2, "fold_tune_fast@*": 135.9, "fold_tune_fast_seed@*": 100.8,
    "fold_tune_lo@*": 80.0, "fold_tune_lo_seed@*": 84.9, "fold_tune_lomethod@*": 86.5, "fold_tune_model@*": 52.2,
    "fold_tune_points_method@*": 35.2, "fold_tune_points_model@*": 66.8, "fold_tune_prob@*": 61.8,
    "fold_tune_prob_seed@*": 58.8, "fold_tune_seed@*": 60.9, "import_scenes": 5.9, "lines_data@*": 2.7,
    "select_lines_seed@*": 340.3, "tables": 30.0, "train_lines@*": 405.6, "train_lines_ngransac@*": 53.6,
    "train_lines_ngransac_seed@*": 56.4, "train_lines_seed@*": 401.4,
}
# What `rlsac pipeline` (the direct runner) adds to each stage's own time on the paper profile: 10 echo stages with
# the lock padded to its 1244 entries (1.39 MB), one worker: 0.063 s a stage, against 11.5 s through `dvc repro -s`
# (benchmarks/pipeline_overhead.py --stages 10 --pad 1244 --repeat 1; the 2-core machine, otherwise idle, issue #50).
# --overhead measure measures it again.
DIRECT_OVERHEAD_S = 0.063


def load_dag(repo: str | os.PathLike) -> dict[str, list[str]]:
    """{stage address: the addresses it depends on} of every stage with a command (DVC's graph; nothing hashed)."""
    from dvc.repo import Repo

    from rlsac.runners.plan import _address

    r = Repo(str(repo))
    try:
        graph, root = r.index.graph, Path(r.root_dir)
        runnable = [s for s in graph.nodes if getattr(s, "cmd", None)]
        keep = set(runnable)
        return {_address(s, root): sorted(_address(d, root) for d in graph.successors(s) if d in keep)
                for s in runnable}
    finally:
        r.close()


def time_of(address: str, table: dict[str, float]) -> float | None:
    """A stage's seconds from ``table``: its exact address, else the first matching fnmatch pattern; None for
    neither."""
    if address in table:
        return float(table[address])
    hit = next((p for p in table if fnmatch.fnmatchcase(address, p)), None)
    return None if hit is None else float(table[hit])


def stage_times(deps: dict[str, list[str]], table: dict[str, float]) -> dict[str, float]:
    """Each stage's seconds from ``table`` (exact address, else the first matching fnmatch pattern)."""
    out, missing = {}, []
    for a in deps:
        t = time_of(a, table)
        if t is None:
            missing.append(a)
        else:
            out[a] = t
    if missing:
        raise SystemExit(f"error: no time for {len(missing)} stage(s), e.g. {missing[0]}")
    return out


def tails(deps: dict[str, list[str]], times: dict[str, float]) -> dict[str, float]:
    """Each stage's longest path to the end of the pipeline, itself included (what ``rlsac pipeline`` starts first:
    rlsac.runners.priority.bottom_levels)."""
    from rlsac.runners.priority import bottom_levels

    return bottom_levels(deps, times)


def critical_path(deps: dict[str, list[str]], times: dict[str, float]) -> tuple[float, list[str]]:
    """(seconds, stages) of the longest chain of dependent stages."""
    tail = tails(deps, times)
    if not tail:
        return 0.0, []
    dependents: dict[str, list[str]] = {a: [] for a in deps}
    for a, ds in deps.items():
        for d in ds:
            dependents[d].append(a)
    a = max(sorted(tail), key=lambda s: tail[s])
    path = [a]
    while dependents[a]:
        a = max(sorted(dependents[a]), key=lambda s: tail[s])
        path.append(a)
    return tail[path[0]], path


def list_schedule(deps: dict[str, list[str]], times: dict[str, float], workers: int) -> float:
    """Wall time of list scheduling on ``workers`` workers, longest-path-first."""
    tail = tails(deps, times)
    waiting = {a: set(ds) for a, ds in deps.items()}
    dependents: dict[str, list[str]] = {a: [] for a in deps}
    for a, ds in deps.items():
        for d in ds:
            dependents[d].append(a)
    ready = [(-tail[a], a) for a, ds in waiting.items() if not ds]
    heapq.heapify(ready)
    running: list[tuple[float, str]] = []  # (end time, stage)
    now = 0.0
    while ready or running:
        while ready and len(running) < workers:
            _, a = heapq.heappop(ready)
            heapq.heappush(running, (now + times[a], a))
        now, a = heapq.heappop(running)
        for b in dependents[a]:
            waiting[b].discard(a)
            if not waiting[b]:
                heapq.heappush(ready, (-tail[b], b))
    return now


def projection(deps: dict[str, list[str]], times: dict[str, float], workers: list[int]) -> dict:
    cp, path = critical_path(deps, times)
    return {"n_stages": len(deps), "total_s": sum(times.values()), "critical_path_s": cp, "critical_path": path,
            "wall_s": {n: list_schedule(deps, times, n) for n in workers}}


def group_of(address: str) -> str:
    """A stage's group: its foreach name (``fold_eval@hard-castle-rlsac`` -> ``fold_eval``), else itself."""
    return address.split("@", 1)[0]


def mlflow_times(uri: str, deps: dict[str, list[str]], repo: str | os.PathLike | None = None) -> dict[str, float]:
    """{address: seconds} of the stages of ``deps`` that a pipeline run of the MLflow store ``uri`` timed (its metric
    ``stage_s/<address>``, logged as the stage ended); of several runs, the latest's. ``repo``: only the runs of that
    DVC repository (rlsac.runners.priority.logged_stage_times, which ``rlsac pipeline`` orders its stages by)."""
    from mlflow.tracking import MlflowClient

    from rlsac.runners.priority import logged_stage_times

    if MlflowClient(uri).get_experiment_by_name("pipeline") is None:
        raise SystemExit(f"error: {uri}: no pipeline runs (experiment 'pipeline')")
    return logged_stage_times(uri, list(deps), repo)


LOG_OUTLIER = 5.0  # a log span this many times its group's median spans two runs of the stage, not one


def log_times(log_dir: str | os.PathLike, deps: dict[str, list[str]]) -> dict[str, float]:
    """{address: seconds} of the stages of ``deps`` with a log ``<address>.log`` under ``log_dir``: from the log's
    birth (the stage started) to its last write (it ended), spans over ``LOG_OUTLIER`` times their group's median
    left out. SystemExit when the file system does not report birth times."""
    import subprocess

    files = {a: Path(log_dir) / (a + ".log") for a in deps}
    files = {a: f for a, f in files.items() if f.is_file()}
    if not files:
        return {}
    r = subprocess.run(["stat", "-c", "%W %Y", *map(str, files.values())], capture_output=True, text=True)
    lines = r.stdout.splitlines()
    if r.returncode or len(lines) != len(files):
        raise SystemExit(f"error: {log_dir}: stat failed: {r.stderr.strip()[:200]}")
    spans = {}
    for a, line in zip(files, lines, strict=True):
        born, written = (int(x) for x in line.split())
        if born <= 0:
            raise SystemExit(f"error: {log_dir}: the file system reports no birth time (needed by --from-logs)")
        spans[a] = float(written - born)
    groups: dict[str, list[float]] = {}
    for a, t in spans.items():
        groups.setdefault(group_of(a), []).append(t)
    median = {g: sorted(v)[len(v) // 2] for g, v in groups.items()}
    return {a: t for a, t in spans.items() if t <= LOG_OUTLIER * max(median[group_of(a)], 1.0)}


def fill_by_group(deps: dict[str, list[str]], measured: dict[str, float],
                  fallback: dict[str, float] | None = None) -> dict[str, float]:
    """Every stage's time: its measured one, else its group's mean, else (a group with no measured stage, e.g. one
    that ran before stage times were logged as they ended) ``fallback``'s (``stage_times``); SystemExit when such a
    group has no fallback."""
    groups: dict[str, list[float]] = {}
    for a, t in measured.items():
        groups.setdefault(group_of(a), []).append(t)
    unmeasured = {a: deps[a] for a in deps if group_of(a) not in groups}
    if unmeasured and fallback is None:
        first = sorted({group_of(a) for a in unmeasured})
        raise SystemExit(f"error: no measured stage in {len(first)} group(s), e.g. {first[0]} (--fallback-recorded "
                         "takes RECORDED's times for them)")
    out = stage_times(unmeasured, fallback) if unmeasured else {}
    out.update({a: measured[a] if a in measured else sum(groups[group_of(a)]) / len(groups[group_of(a)])
                for a in deps if a not in out})
    return out


def group_table(deps: dict[str, list[str]], measured: dict[str, float]) -> str:
    """Markdown: per group of the DAG, its stages, how many were measured, and their total, mean and range (s)."""
    rows = []
    for g in sorted({group_of(a) for a in deps}):
        stages = [a for a in deps if group_of(a) == g]
        t = [measured[a] for a in stages if a in measured]
        cells = (f"{sum(t):.0f} | {sum(t) / len(t):.1f} | {min(t):.1f}-{max(t):.1f}" if t else "– | – | –")
        rows.append(f"| `{g}` | {len(stages)} | {len(t)} | {cells} |")
    return ("| group | stages | measured | total (s) | mean (s) | range (s) |\n| --- | --- | --- | --- | --- | --- |\n"
            + "\n".join(rows))


def timed_only(deps: dict[str, list[str]], table: dict[str, float]) -> tuple[dict[str, list[str]], dict[str, int]]:
    """``deps`` without the stages ``table`` has no time for (nor the edges to them). -> (deps, {group: n left out})."""
    keep = {a for a in deps if time_of(a, table) is not None}
    left: dict[str, int] = {}
    for a in deps:
        if a not in keep:
            left[group_of(a)] = left.get(group_of(a), 0) + 1
    return {a: [d for d in ds if d in keep] for a, ds in deps.items() if a in keep}, left


def with_overhead(times: dict[str, float], overhead: float, less: float = 0.0) -> dict[str, float]:
    """Each stage's time less the runner work it already holds (floored at 0), plus ``overhead``."""
    return {a: max(t - less, 0.0) + overhead for a, t in times.items()}


def measure_overhead() -> float:
    """The direct runner's seconds per stage on the paper profile's lock size, measured now (one worker)."""
    from pipeline_overhead import measure

    return measure(10, 1244, workers=1, repeat=1, runners=("direct",), report=lambda line: None)["per_stage"]["direct"]


def _seconds(flag: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise SystemExit(f"error: {flag}: {text!r} is neither a number of seconds nor 'measure'") from None
    if v < 0:
        raise SystemExit(f"error: {flag}: must be at least 0")
    return v


def _hours(s: float) -> str:
    return f"{s:.0f} s ({s / 3600:.2f} h)"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repo", default=".", help="The DVC repository whose DAG is used [default: .].")
    ap.add_argument("--times", help="pipeline.json of an rlsac pipeline run, or {stage or pattern: seconds} "
                                    "[default: RECORDED, the README's recorded stage times].")
    ap.add_argument("--from-mlflow", metavar="URI", help="The stage times the rlsac pipeline runs of this MLflow "
                                                         "store logged (e.g. sqlite:///mlflow.db).")
    ap.add_argument("--from-logs", metavar="DIR", help="With --from-mlflow: the stages no run logged take their "
                                                       "stage log's span (e.g. logs/pipeline).")
    ap.add_argument("--groups", action="store_true", help="Also print the stage time per group (Markdown).")
    ap.add_argument("--fallback-recorded", action="store_true", help="With --from-mlflow: a group with no measured "
                                                                     "stage takes RECORDED's times.")
    ap.add_argument("--workers", default="1,2,8,32", help="Comma-separated worker counts [default: 1,2,8,32].")
    ap.add_argument("--overhead", default=str(DIRECT_OVERHEAD_S),
                    help="Seconds added to every stage: the runner's own work per stage, or 'measure' (the direct "
                         "runner on the paper profile's lock size, benchmarks/pipeline_overhead.py) "
                         f"[default: {DIRECT_OVERHEAD_S}, measured].")
    ap.add_argument("--less", type=float, default=0.0,
                    help="Seconds taken off every stage's time first (floored at 0): the runner work the times "
                         "already hold, e.g. `dvc repro -s`'s for times taken with --runner dvc [default: 0].")
    ap.add_argument("--only-timed", action="store_true",
                    help="Leave out the stages that have no time (named, per group) instead of stopping.")
    ap.add_argument("--json", action="store_true", help="Print the result as JSON.")
    args = ap.parse_args(argv)
    given = None if args.overhead == "measure" else _seconds("--overhead", args.overhead)
    if args.less < 0:
        raise SystemExit("error: --less: must be at least 0")
    workers = [int(n) for n in args.workers.split(",")]
    if any(n < 1 for n in workers):
        raise SystemExit("error: --workers: every count must be at least 1")
    if args.from_logs and not args.from_mlflow:
        raise SystemExit("error: --from-logs fills in what --from-mlflow lacks: give both")
    if args.times and args.from_mlflow:
        raise SystemExit("error: --times and --from-mlflow are two sources of times: give one")
    table = RECORDED
    deps = None
    measured = None
    if args.from_mlflow:
        deps = load_dag(args.repo)
        measured = mlflow_times(args.from_mlflow, deps, args.repo)
        if args.from_logs:
            measured = {**log_times(args.from_logs, deps), **measured}
        table = fill_by_group(deps, measured, RECORDED if args.fallback_recorded else None)
    elif args.times:
        data = json.loads(Path(args.times).read_text())
        if "results" in data and "deps" in data:  # an rlsac pipeline artifact: the stages it ran
            table = {a: r["seconds"] for a, r in data["results"].items() if r.get("seconds") is not None}
            deps = {a: [d for d in ds if d in table] for a, ds in data["deps"].items() if a in table}
        else:
            table = data
    if deps is None:
        deps = load_dag(args.repo)
    left_out = {}
    if args.only_timed:
        deps, left_out = timed_only(deps, table)
    times = stage_times(deps, table)
    overhead = measure_overhead() if given is None else given  # after every check: measuring starts Ray
    p = projection(deps, with_overhead(times, overhead, args.less), workers)
    p.update(overhead_s=overhead, less_s=args.less, left_out=left_out)
    if measured is not None:
        p["measured"] = len(measured)
    if args.json:
        json.dump(p, sys.stdout, indent=1)
        print()
        return
    print(f"{p['n_stages']} stages; total stage time {_hours(p['total_s'])}; "
          f"critical path {_hours(p['critical_path_s'])}: {' -> '.join(p['critical_path'])}")
    if left_out:
        print(f"left out (no time): {sum(left_out.values())} stages: "
              + ", ".join(f"{g} {n}" for g, n in sorted(left_out.items())))
    print(f"each stage: its time{f' less {args.less:g} s (floored at 0)' if args.less else ''} plus {overhead:.2f} s "
          f"of runner overhead ({'measured now' if args.overhead == 'measure' else 'given'})")
    if measured is not None:
        fell_back = sorted({group_of(a) for a in deps} - {group_of(a) for a in measured})
        print(f"measured {len(measured)} of {p['n_stages']} stages; the others at their group's mean"
              + (f", groups with none measured at RECORDED's times: {', '.join(fell_back)}" if fell_back else ""))
    for n, s in p["wall_s"].items():
        print(f"{n:>3} workers: wall {_hours(s)}")
    if args.groups:
        print("\n" + group_table(deps, measured if measured is not None else stage_times(deps, table)))


if __name__ == "__main__":
    main()
