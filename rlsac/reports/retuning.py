"""The re-tuning term of an interval (issue #47 item 7 b): how much the choice of settings on a few dozen validation
pairs moves a row's test mAA, read from the records of ``rlsac folds --stage retune`` (reports/retune/fundamental/
<regime>/<fold>/<row>.json: each of the draws re-chose the row's settings on a resample of its fold's validation
pairs, and every chosen setting was tested).

The claims (rlsac.reports.claims, rlsac.reports.paper_report) carry it per comparison (issue #62): ``Selection``
reads every record once and gives, for a claim's rows (``contrast``), each re-tuned row's test errors under every
draw's re-chosen setting; rlsac.maths.metrics.contrast_bootstrap draws the nested, paired bootstrap from them. ``rlsac
table`` reads the records once per build and hands them to each builder (their ``retuning`` argument); a builder
called on its own (default ``COMPUTE``) reads them itself (``resolve``). ``halfwidth`` / ``widen`` are the one global
term the claims used before (Z95·√2·the largest sd, added in quadrature): reports/tuning_budget.md reports it, and
paper.md's `before (issue #62)` column re-derives the old verdicts with it.

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


def load_retune(out_dir: Path, regime: str, row: str, task: str = "fundamental") -> list[dict[str, Any]]:
    """The re-tuning records of ``row`` in ``regime``, one per fold (fold order), each checked for the fields the
    report reads: one choice per draw, test errors for every chosen setting at every budget."""
    from rlsac.evaluation.results import read_retune_record

    recs = []
    for path in sorted((out_dir / "retune" / task / regime).glob(f"*/{row}.json")):
        rec = read_retune_record(path)  # finite angles in [0, 180], choices that index the settings (issue #64)
        try:
            n, k = len(rec["test_scenes"]), len(rec["settings"])
            chosen = {rec["full"], *rec["choices"]}
            ok = rec["choices"] and all(isinstance(i, int) and 0 <= i < k for i in chosen) and rec["test"] and all(
                len(per[str(i)][col]) == n for per in rec["test"].values() for i in chosen for col in ("err_R",
                                                                                                       "err_t"))
        except (KeyError, TypeError):
            ok = False
        if not ok:
            raise RlsacError(f"{path}: not a re-tuning record of `rlsac folds --stage retune` (choices, settings and "
                             "test errors of every chosen setting); re-run the command that wrote it, or remove it")
        recs.append({**rec, "path": str(path), "fold": rec.get("fold", path.parent.name)})
    return recs


def spread(recs: list[dict[str, Any]], it: int, col: str, limit: float, *, bootstrap: bool = True
           ) -> dict[str, Any]:
    """The test mAA (column ``col``) each draw's re-chosen settings give, the folds pooled (each fold its own choice
    in that draw; every fold must have made as many draws) -> {full, mean, sd, lo, hi, half} where ``full`` is the
    choice on all validation pairs (the tables' setting) and ``half`` the half-width of its own 95% bootstrap interval
    over the test pairs, resampled within each test building as the tables do; ``bootstrap=False`` leaves ``half``
    out (and its bootstrap undrawn: the other fields do not depend on it)."""
    from rlsac.layout.protocol import N_BOOT
    from rlsac.maths.metrics import accuracy_per_instance, stratified_draws

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
    from rlsac.layout.protocol import LIMIT

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


def resolve(retuning: Selection | None | Compute, out_dir: str | Path) -> Selection | None:
    """A builder's ``retuning`` argument: ``Selection(out_dir)`` for ``COMPUTE`` (the builder called on its own),
    else the records as given (read once by ``rlsac table`` for every builder of the build; None for none)."""
    return Selection(out_dir) if retuning is COMPUTE else retuning


def widen(stats: dict[str, float], s: float) -> dict[str, float]:
    """An interval {diff, lo, hi, ...} widened on each side by ``s`` in quadrature: lo − √((diff − lo)² + s²),
    hi + √((hi − diff)² + s²) (two independent sources of error; the point estimate stays)."""
    d = stats["diff"]
    return {**stats, "lo": d - float(np.hypot(d - stats["lo"], s)), "hi": d + float(np.hypot(stats["hi"] - d, s))}


class Selection:
    """The selection term of a comparison (issue #62): every re-tuning record of ``task`` under <out_dir>/retune,
    by (regime, row), and the tuning records (<out_dir>/tuning/<task>) that say how a row without one got its
    settings. ``contrast`` gives a claim's rows, each with its errors per validation draw where it has a record;
    rlsac.maths.metrics.contrast_bootstrap draws the nested bootstrap from them."""

    def __init__(self, out_dir: str | Path, task: str = "fundamental"):
        self.out_dir, self.task = Path(out_dir), task
        self.records: dict[tuple[str, str], list[dict[str, Any]]] = {}
        root = self.out_dir / "retune" / task
        for regime_dir in sorted(p for p in root.glob("*") if p.is_dir()):
            for row in sorted({p.stem for p in regime_dir.glob("*/*.json")}):
                self.records[(regime_dir.name, row)] = load_retune(self.out_dir, regime_dir.name, row, task)
        self._check_paired()

    def _check_paired(self) -> None:
        """Draw v must be the same validation resample for every row of a fold: same draws, draw seed and pairs."""
        seen: dict[tuple[str, str], tuple] = {}
        for (regime, _), recs in self.records.items():
            for r in recs:
                key = (len(r["choices"]), r.get("draw_seed"), tuple(r.get("val_scenes", ())))
                if seen.setdefault((regime, r["fold"]), key) != key:
                    raise RlsacError(f"{r['path']}: its validation draws are not those of the other re-tuning "
                                     f"records of {regime}/{r['fold']} (draws, draw_seed, val_scenes); re-run "
                                     "`rlsac folds --stage retune` for every row of the fold")

    def how(self, regime: str, row: str, it: int) -> str:
        """How ``row``'s settings are chosen, for the selection term: "re-selected" (a record at ``it``), "learned"
        (a checkpoint, its threshold tuned per training seed: the seed resampling counts that tuning once), "not
        measured" (tuned on validation pairs, no re-tuning record) or "fixed" (no tuning record, or one setting)."""
        recs = self.records.get((regime, row))
        if recs and all(str(it) in r["test"] for r in recs):
            return "re-selected"
        from rlsac.layout.protocol import split_seed

        tuned = sorted((self.out_dir / "tuning" / self.task / regime).glob(f"*/{split_seed(row)[0]}.json"))
        if not tuned:
            return "fixed"
        import json

        rec = json.loads(tuned[0].read_text())
        if rec.get("checkpoint"):
            return "learned"
        return "not measured" if len(rec.get("grid") or ()) > 1 else "fixed"

    def draws(self, regime: str, row: str, it: int, frame, col: str) -> np.ndarray | None:
        """(V, len(frame)) test errors in column ``col`` of ``row``'s evaluated pairs (``frame``,
        rlsac.evaluation.results.
        collect's, in its order), draw v's setting on each fold; None without a record at ``it``. The record's own
        choice on all validation pairs must reproduce ``frame`` (the tables' cell), else the record is stale."""
        if self.how(regime, row, it) != "re-selected":
            return None
        recs = {r["fold"]: r for r in self.records[(regime, row)]}
        out = np.full((len(recs[next(iter(recs))]["choices"]), len(frame)), np.nan)
        for fold, sub in frame.groupby("fold", sort=False):
            r = recs.get(str(fold))
            if r is None:
                return None
            where = {(s, p): i for i, (s, p) in enumerate(zip(r["test_scenes"], r["test_pairs"], strict=True))}
            pos = np.flatnonzero(frame["fold"].to_numpy() == fold)
            at = [where.get((str(s), str(p))) for s, p in zip(sub["scene"], sub["pair"], strict=True)]
            if None in at:
                raise RlsacError(f"{r['path']}: lacks test pairs of reports/eval's {regime}/{fold}/{row}; re-run "
                                 "`rlsac folds --stage retune`")
            per = r["test"][str(it)]
            full = np.asarray(per[str(r["full"])][col], np.float64)[at]
            if not np.allclose(full, sub[col].to_numpy(np.float64), equal_nan=True, atol=1e-5, rtol=1e-5):
                raise RlsacError(f"{r['path']}: its choice on all validation pairs does not give reports/eval's "
                                 f"{regime}/{fold}/{row}/i{it} errors (a stale record); re-run `rlsac folds --stage "
                                 "retune`")
            out[:, pos] = np.stack([np.asarray(per[str(c)][col], np.float64)[at] for c in r["choices"]])
        return out


def contrast(res, seeded: dict[str, list[str]], regime: str, terms: list[tuple[float, str]], it: int, col: str,
             sel: Selection | None) -> dict[str, Any] | None:
    """The rows of a contrast Σ w·row (``terms``), each over its training seeds (``seeded``:
    rlsac.evaluation.results.seed_runs),
    on the pairs every run has -> {"rows": [(w, full (S, M), draws (V, S, M) or None)], "strata" (each pair's test
    building), "how": {row: Selection.how}}, or None when a run or common pairs are missing. ``sel`` None: no
    row re-selected."""
    from rlsac.evaluation.results import pair_key

    runs = {row: seeded.get(row, [row]) for _, row in terms}
    frames = {m: res.get((regime, m, it)) for rs in runs.values() for m in rs}
    if any(f is None for f in frames.values()):
        return None
    keyed = {m: f.assign(k=pair_key(f)).reset_index(drop=True) for m, f in frames.items()}
    common = None
    for f in keyed.values():
        common = f["k"] if common is None else common[common.isin(set(f["k"]))]
    if common is None or common.empty:
        return None
    common = common.drop_duplicates()
    order = {m: f.reset_index().set_index("k").loc[common, "index"].to_numpy() for m, f in keyed.items()}
    rows, how = [], {}
    for w, row in terms:
        full = np.stack([keyed[m][col].to_numpy(np.float64)[order[m]] for m in runs[row]])
        how[row] = "fixed" if sel is None else sel.how(regime, row, it)
        d = None if sel is None or len(runs[row]) > 1 else sel.draws(regime, row, it, frames[row], col)
        rows.append((w, full, None if d is None else d[:, order[row]][:, None, :]))
    first = next(iter(keyed))
    return {"rows": rows, "strata": keyed[first]["fold"].to_numpy()[order[first]], "how": how}
