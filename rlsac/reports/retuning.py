"""The re-tuning term of an interval (issue #47 item 7 b): how much the choice of settings on a few dozen validation
pairs moves a row's test mAA, read from the records of ``rlsac folds --stage retune`` (reports/retune/fundamental/
<regime>/<fold>/<row>.json: each of the draws re-chose the row's settings on a resample of its fold's validation
pairs, and every chosen setting was tested).

The tables' intervals resample test pairs (and training seeds) with each row's settings fixed. A claim sets two
rows against each other, each tuned on its own, so re-tuning both moves their difference by about Z95·√2·sd (95%),
sd the spread of one row's test mAA over the draws. ``halfwidth`` takes the largest sd measured (over the rows,
budgets and metrics re-tuned: conservative for the rows not re-tuned, among them the learned ones, whose grids run
the network at every point), and ``widen`` adds it to an interval in quadrature. The claims (rlsac.reports.claims,
rlsac.reports.paper_report) read it here; reports/tuning_budget.md shows where it comes from. ``rlsac table``
computes it once per build and hands it to each of those builders (their ``retuning`` argument); a builder called on
its own (default ``COMPUTE``) computes it itself (``resolve``).

Reads result files only, never a runner.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from rlsac.errors import RlsacError

Z95 = 1.96  # a normal 95% half-width in sd; the re-tuning spread is near normal for rows with many settings chosen
METRICS = (("err_R", "R"), ("err_t", "t"))


class Compute(Enum):
    """The type of ``COMPUTE``, a builder's default ``retuning``: read the re-tuning records itself."""

    COMPUTE = "compute"


COMPUTE = Compute.COMPUTE


def load_retune(out_dir: Path, regime: str, row: str) -> list[dict[str, Any]]:
    """The re-tuning records of ``row`` in ``regime``, one per fold (fold order), each checked for the fields the
    report reads: one choice per draw, test errors for every chosen setting at every budget."""
    from rlsac.results import read_retune_record

    recs = []
    for path in sorted((out_dir / "retune" / "fundamental" / regime).glob(f"*/{row}.json")):
        rec = read_retune_record(path)
        recs.append({**rec, "path": str(path)})
    return recs


def spread(recs: list[dict[str, Any]], it: int, col: str, limit: float, *, bootstrap: bool = True
           ) -> dict[str, Any]:
    """The test mAA (column ``col``) each draw's re-chosen settings give, the folds pooled (each fold its own choice
    in that draw; every fold must have made as many draws) -> {full, mean, sd, lo, hi, half} where ``full`` is the
    choice on all validation pairs (the tables' setting) and ``half`` the half-width of its own 95% bootstrap interval
    over the test pairs, resampled within each test building as the tables do; ``bootstrap=False`` leaves ``half``
    out (and its bootstrap undrawn: the other fields do not depend on it)."""
    from rlsac.metrics import accuracy_per_instance, stratified_draws
    from rlsac.protocol import N_BOOT

    draws = {len(r["choices"]) for r in recs}
    if len(draws) != 1:
        raise RlsacError(f"re-tuning records with different numbers of draws {sorted(draws)}: "
                         + ", ".join(r["path"] for r in recs))
    acc = [{int(i): accuracy_per_instance(np.asarray(e[col], np.float64), limit) for i, e in r["test"][str(it)].items()}
           for r in recs]
    full = np.concatenate([a[r["full"]] for a, r in zip(acc, recs, strict=True)])
    per = np.array([np.concatenate([a[r["choices"][b]] for a, r in zip(acc, recs, strict=True)]).mean()
                    for b in range(draws.pop())])
    sd = float(per.std(ddof=1)) if per.size > 1 else 0.0
    out = {"full": float(full.mean()), "mean": float(per.mean()), "sd": sd,
           "lo": float(np.percentile(per, 2.5)), "hi": float(np.percentile(per, 97.5))}
    if bootstrap:
        strata = np.concatenate([[i] * len(r["test_scenes"]) for i, r in enumerate(recs)])
        boot = full[stratified_draws(np.random.default_rng(0), strata, N_BOOT)].mean(axis=1)
        lo, hi = np.percentile(boot, [2.5, 97.5])
        out["half"] = float((hi - lo) / 2)
    return out


def halfwidth(out_dir: str | Path) -> dict[str, Any] | None:
    """The re-tuning half-width of a difference of two rows, from every re-tuning record under <out_dir>/retune:
    {s, sd, row, regime, iterations, metric} with s = Z95·√2·sd and sd the largest re-tuned sd
    (rows x budgets x metrics, the folds pooled); None when there is no record (the term is then left out, and the
    reports say so)."""
    from rlsac.protocol import LIMIT

    root = Path(out_dir) / "retune" / "fundamental"
    best = None
    for regime_dir in sorted(p for p in root.glob("*") if p.is_dir()):
        rows = sorted({p.stem for p in regime_dir.glob("*/*.json")})
        for row in rows:
            recs = load_retune(Path(out_dir), regime_dir.name, row)
            budgets = sorted(set.intersection(*(set(r["test"]) for r in recs)), key=int)
            for it in budgets:
                for col, name in METRICS:
                    sd = spread(recs, int(it), col, LIMIT, bootstrap=False)["sd"]
                    if best is None or sd > best["sd"]:
                        best = {"sd": sd, "row": row, "regime": regime_dir.name, "iterations": int(it), "metric": name}
    if best is None:
        return None
    return {**best, "s": float(Z95 * np.sqrt(2) * best["sd"])}


def resolve(retuning: dict[str, Any] | None | Compute, out_dir: str | Path) -> dict[str, Any] | None:
    """A builder's ``retuning`` argument: ``halfwidth(out_dir)`` for ``COMPUTE`` (the builder called on its own),
    else the term as given (computed once by ``rlsac table`` for every builder of the build; None for no record)."""
    return halfwidth(out_dir) if retuning is COMPUTE else retuning


def widen(stats: dict[str, float], s: float) -> dict[str, float]:
    """An interval {diff, lo, hi, ...} widened on each side by ``s`` in quadrature: lo − √((diff − lo)² + s²),
    hi + √((hi − diff)² + s²) (two independent sources of error; the point estimate stays)."""
    d = stats["diff"]
    return {**stats, "lo": d - float(np.hypot(d - stats["lo"], s)), "hi": d + float(np.hypot(stats["hi"] - d, s))}
