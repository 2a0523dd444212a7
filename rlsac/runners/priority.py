"""Which ready stage first: each stage's bottom level (the longest expected chain after it), from the
stage times earlier pipeline runs logged to MLflow (list scheduling's critical-path rule)."""

from __future__ import annotations

import os
import re
from pathlib import Path

from rlsac.errors import RlsacError


def bottom_levels(deps: dict[str, list[str]], seconds: dict[str, float]) -> dict[str, float]:
    """{address: its bottom level}: the expected seconds of the longest chain from the stage (itself included) to
    the end of the plan. ``deps``: {address: the addresses it needs} (those outside ``deps`` are ignored);
    ``seconds``: each stage's expected time (a stage absent from it counts 1). Starting the ready stage with the
    highest bottom level first is list scheduling's critical-path rule: a long chain is not left waiting behind
    many short independent stages (issue #50, item 4)."""
    dependents: dict[str, list[str]] = {a: [] for a in deps}
    for a, ds in deps.items():
        for d in ds:
            if d in dependents:
                dependents[d].append(a)
    level: dict[str, float] = {}
    for a in reversed(_dependencies_first(deps)):
        level[a] = seconds.get(a, 1.0) + max((level[b] for b in dependents[a]), default=0.0)
    return level


def _dependencies_first(deps: dict[str, list[str]]) -> list[str]:
    """The addresses of ``deps``, each after those it needs (iterative: a chain of thousands of stages)."""
    done: set[str] = set()
    out: list[str] = []
    for start in sorted(deps):
        stack = [(start, iter(sorted(deps[start])))]
        while stack:
            a, needs = stack[-1]
            d = next((d for d in needs if d in deps and d not in done), None)
            if d is not None:
                if any(d == s for s, _ in stack):
                    raise RlsacError(f"the pipeline has a cycle through {d}")
                stack.append((d, iter(sorted(deps[d]))))
                continue
            stack.pop()
            if a not in done:
                done.add(a)
                out.append(a)
    return out


def expected_seconds(addresses: list[str], measured: dict[str, float]) -> dict[str, float]:
    """Each stage's expected seconds: its measured time (an earlier run's, ``logged_stage_times``), else its
    group's mean (a new seed of a group that ran before costs about what its siblings did), else 1."""
    groups: dict[str, list[float]] = {}
    for a, t in measured.items():
        groups.setdefault(a.split("@", 1)[0], []).append(t)
    mean = {g: sum(ts) / len(ts) for g, ts in groups.items()}
    return {a: measured.get(a, mean.get(a.split("@", 1)[0], 1.0)) for a in addresses}


def logged_stage_times(uri: str, addresses: list[str], repo: str | os.PathLike | None = None) -> dict[str, float]:
    """{address: seconds} of the stages of ``addresses`` that a pipeline run of the MLflow store ``uri`` timed
    (its metric ``stage_s/<address>``, logged as the stage ended); of several runs, the latest's; {} when the store
    has no pipeline run. ``repo``: only the runs of that DVC repository (their param ``repo``; the quick profile's
    stages have the same names)."""
    from rlsac.tracking import client as open_client

    client = open_client(uri)
    exp = client.get_experiment_by_name("pipeline")
    if exp is None:
        return {}
    names = {stage_metric(a): a for a in addresses}
    out: dict[str, float] = {}
    runs = client.search_runs([exp.experiment_id], order_by=["attributes.start_time ASC"], max_results=50000)
    root = None if repo is None else str(Path(repo).resolve())
    for run in runs:  # oldest first: a later run's time of a stage replaces an earlier one's
        if root is not None and run.data.params.get("repo") != root:
            continue
        out.update({names[k]: float(v) for k, v in run.data.metrics.items() if k in names})
    return out


def _priorities(plan: dict, track: bool) -> dict[str, float]:
    """Each stage to run -> its bottom level, from the stage times earlier pipeline runs of this repository logged
    to the tracking store (none with --no-tracking: then every stage counts 1, the longest chain of stages first)."""
    from rlsac.tracking import DEFAULT_URI

    measured = {}
    if track and plan["todo"]:
        try:  # an order, not a result: a store that cannot answer (busy, old schema) leaves every stage at 1
            measured = logged_stage_times(os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI), plan["todo"],
                                          plan["root"])
        except Exception as e:  # noqa: BLE001 (MLflow's and the HTTP client's errors alike)
            print(f"pipeline: no stage times from the tracking store ({type(e).__name__}); every stage counts 1")
    todo = set(plan["todo"])
    deps = {a: [d for d in plan["deps"][a] if d in todo] for a in plan["todo"]}
    return bottom_levels(deps, expected_seconds(plan["todo"], measured))


def stage_metric(stage: str) -> str:
    """The MLflow metric of a stage's wall time (stage wall times go to MLflow only, never into committed files):
    ``stage_s/<address>``, the characters MLflow refuses replaced by ``_``."""
    return "stage_s/" + re.sub(r"[^\w.\- /]", "_", stage)
