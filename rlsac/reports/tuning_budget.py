"""reports/tuning_budget.{md,csv} (issue #47 item 7): two sources of variance the tables' intervals leave out.

(a) Tuned at the test budget. The rows of params ``tuning_budget.methods`` tuned again at ``tuning_budget.iterations``
    (records reports/tuning_at<N>/fundamental/, results reports/eval/folds_at<N>/) against the tables' cells at that
    budget (tuned at ``tuning.iterations``): per row and regime, pooled over the folds, the paired difference in
    mAA_R / mAA_t with a 95% bootstrap interval over the test pairs resampled within each test building (the tables'
    bootstrap, rlsac.maths.metrics.seed_bootstrap_maa with one run a side), and how many folds chose other settings.
(b) Re-tuning variance. The records of ``rlsac folds --stage retune`` (reports/retune/fundamental/<regime>/<fold>/):
    each draw re-chose a row's settings on a resample of its fold's validation pairs; a draw's test mAA pools the four
    folds' test pairs, each fold with that draw's choice. Its sd and 95% range, beside the half-width of the tables'
    95% interval of the row's mAA and the claims' tie margin (rlsac.reports.claims.TIE_MARGIN).

Reads result files only (rlsac.evaluation.results), never a runner.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rlsac.io import atomic_path, write_text
from rlsac.reports.retuning import COMPUTE, Z95, Compute, Selection, halfwidth, load_retune, resolve, spread


def _cells(root: Path, regime: str, row: str, it: int) -> pd.DataFrame | None:
    """A row's per-pair errors at ``it`` pooled over the folds under ``root`` (<eval_root>/<sub>), with ``fold``;
    None when no fold has the cell."""
    from rlsac.evaluation.results import read_errors

    frames = []
    for fold_dir in sorted(p for p in (root / regime).glob("*") if p.is_dir()):
        df = read_errors(fold_dir / row / f"i{it}" / "errors.csv", ("err_R", "err_t"))
        if df is not None:
            frames.append(df.assign(fold=fold_dir.name))
    return pd.concat(frames, ignore_index=True) if frames else None


def _ci(d: dict[str, float]) -> str:
    return f"{d['diff']:+.3f} [{d['lo']:+.3f}, {d['hi']:+.3f}]"


def _budget_row(c: dict[str, Any], eval_root: Path, out_dir: Path, regime: str, label: str, names: list[str]
                ) -> dict[str, Any] | str:
    """Part (a) for one row over its training seeds ``names`` (a library row: one name): tuned@N against the tables'
    cell, paired on the same test pairs, the seeds resampled too (rlsac.maths.metrics.seed_bootstrap_maa) -> the
    report's row, or the reason it is missing."""
    from rlsac.evaluation.results import pair_key, read_record
    from rlsac.layout.protocol import LIMIT, N_BOOT, at_suffix
    from rlsac.maths.metrics import seed_bootstrap_maa

    it, at_runs, base_runs = c["iterations"], [], []
    changed = total = 0
    for name in names:
        base = _cells(eval_root / "folds", regime, name, it)
        at = _cells(eval_root / f"folds{at_suffix(it)}", regime, name, it)
        if base is None or at is None:
            return f"{regime}/{name}"
        a, b = at.set_index(pair_key(at)), base.set_index(pair_key(base))
        if set(a.index) != set(b.index):  # a fold present one way only: the comparison would not be paired
            return f"{regime}/{name} (folds differ)"
        if at_runs and list(a.index) != list(at_runs[0].index):
            return f"{regime}/{name} (pairs differ between seeds)"
        at_runs.append(a)
        base_runs.append(b.loc[a.index])
        for f in sorted(set(a["fold"])):
            recs = [read_record(out_dir / f"tuning{s}" / "fundamental" / regime / f / f"{name}.json")
                    for s in ("", at_suffix(it))]
            changed += int(None not in recs and recs[0]["chosen"] != recs[1]["chosen"])
            total += 1
    first = at_runs[0]
    row = {"regime": regime, "row": label, "pairs": len(first), "folds re-chosen": f"{changed}/{total}"}
    for col, name in (("err_R", "R"), ("err_t", "t")):
        s = seed_bootstrap_maa(np.stack([r[col].to_numpy() for r in at_runs]),
                               np.stack([r[col].to_numpy() for r in base_runs]), LIMIT,
                               strata=first["fold"].to_numpy(), n_boot=N_BOOT, seed=0)
        row[f"mAA_{name} tuned@{c['tuned_at_tables']}"] = f"{s['mean_b']:.3f}"
        row[f"mAA_{name} tuned@{it}"] = f"{s['mean_a']:.3f}"
        row[f"{name}: @{it} − @{c['tuned_at_tables']} [95%]"] = _ci(s)
        row[f"_{name}"] = s
    return row


def _groups(c: dict[str, Any]) -> list[tuple[str, str, list[str]]]:
    """Part (a)'s rows: (regime, label, the names of its cells: one, or a learned model's training seeds)."""
    groups = [(r, m, [m]) for r in c["regimes"] for m in c["methods"]]
    models = [n for n in c["learned"] if not re.fullmatch(r".+-s\d+", n) or n.rsplit("-s", 1)[0] not in c["learned"]]
    for r in c["learned_regimes"]:
        for m in models:
            names = [n for n in c["learned"] if n == m or (n.rsplit("-s", 1)[0] == m and n != m)]
            label = f"{m} (threshold)" if len(names) == 1 else f"{m} ({len(names)} seeds, threshold)"
            groups.append((r, label, names))
    return groups


def check_inputs(params: dict[str, Any], eval_root: str | Path = "reports/eval", out_dir: str | Path = "reports"
                 ) -> None:
    """Every file the report reads, read once through rlsac.evaluation.results' refusing readers: ``rlsac table --which
    tuning-budget`` calls it before its run (issue #64: a NaN or truncated input failed inside the run, FAILED):
    each row's cells both ways, their folds' tuning records, the re-tuning records."""
    from rlsac.evaluation import retune, tune
    from rlsac.evaluation.results import read_record
    from rlsac.layout.protocol import at_suffix

    c = {**retune.conf(params), "tuned_at_tables": tune.conf(params)["iterations"]}
    eval_root, out_dir, it = Path(eval_root), Path(out_dir), c["iterations"]
    for regime, _, names in _groups(c):
        for name in names:
            for sub in ("folds", f"folds{at_suffix(it)}"):
                cells = _cells(eval_root / sub, regime, name, it)
                for f in sorted(set(cells["fold"])) if cells is not None else ():
                    for s in ("", at_suffix(it)):
                        read_record(out_dir / f"tuning{s}" / "fundamental" / regime / f / f"{name}.json")
    for regime, m in retuned(c):
        load_retune(out_dir, regime, m)


def budget_rows(c: dict[str, Any], eval_root: Path, out_dir: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """Part (a): one row per (regime, method) with results both ways, then each learned model of
    ``tuning_budget.learned`` over its training seeds (threshold alone, rlsac.experiments.folds.threshold_only);
    -> (rows, missing cells)."""
    rows, missing = [], []
    for regime, label, names in _groups(c):
        got = _budget_row(c, eval_root, out_dir, regime, label, names)
        (missing.append(got) if isinstance(got, str) else rows.append(got))
    return rows, missing


def retuned(c: dict[str, Any]) -> list[tuple[str, str]]:
    """(regime, row) of every re-tuning record the report reads: the main regime's rows, then the second regime's
    (``retune_also``, issue #62)."""
    also = c.get("retune_also") or {}
    return [(c["retune_regime"], m) for m in c["retune_methods"]] + [(also["regime"], m)
                                                                       for m in also.get("methods", [])]


def retune_rows(c: dict[str, Any], out_dir: Path) -> tuple[list[dict[str, Any]], list[str]]:
    """Part (b): one row per (row, budget) with re-tuning records for every fold; -> (rows, missing rows)."""
    from rlsac.layout.protocol import LIMIT

    rows, missing = [], []
    for regime, m in retuned(c):
        recs = load_retune(out_dir, regime, m)
        if not recs:
            missing.append(f"{regime}/{m} (re-tuning)")
            continue
        for it in c["retune_iterations"]:
            if any(str(it) not in r["test"] for r in recs):
                missing.append(f"{regime}/{m} at {it} (re-tuning)")
                continue
            row = {"regime": regime, "row": m, "iterations": it, "folds": len(recs),
                   "draws": len(recs[0]["choices"]),
                   # the rule replayed on all validation pairs must give the tables' record (same errors, same rule)
                   "all pairs = tables' record":
                       f"{sum(r.get('record_chosen') == r['settings'][r['full']] for r in recs)}/{len(recs)}",
                   "settings chosen": " / ".join(str(len(set(r["choices"]))) for r in recs),
                   "draws ≠ tables' choice":
                       f"{np.mean([np.mean(np.array(r['choices']) != r['full']) for r in recs]):.2f}"}
            for col, name in (("err_R", "R"), ("err_t", "t")):
                s = spread(recs, it, col, LIMIT)
                row[f"mAA_{name}: tables"] = f"{s['full']:.3f}"
                row[f"mAA_{name}: re-tuned sd [95% range]"] = f"{s['sd']:.3f} [{s['lo']:.3f}, {s['hi']:.3f}]"
                row[f"mAA_{name}: tables' ±"] = f"{s['half']:.3f}"
                row[f"_{name}"] = s
            rows.append(row)
    return rows, missing


def decision(rows: list[dict[str, Any]], margin: float, term: dict[str, Any] | None) -> str:
    """The generated reading of part (b): the spread re-tuning gives a row (``term``: rlsac.reports.retuning.
    halfwidth, None for no record) against the tie margin, and where the claims now carry it (issue #62)."""
    if term is None or not rows:
        return "No re-tuning records: nothing to decide, and no interval carries a selection term.\n"
    sds = [r[f"_{n}"]["sd"] for r in rows for n in ("R", "t")]
    return (
        f"**Decision.** The re-tuning sd of one row ranges {min(sds):.3f}-{max(sds):.3f} (mean {np.mean(sds):.3f}; "
        f"the largest: {term['regime']}/{term['row']}, mAA_{term['metric']} at {term['iterations']} iterations), so "
        f"one term for every claim (its largest, {Z95}·√2·sd = ±{term['s']:.3f}, {term['s'] / margin:.0%} of the tie "
        f"margin ±{margin}) would be too wide for some comparisons and absent from none. Since issue #62 the claims "
        "carry the selection term per comparison instead: claims.md and paper.md draw a nested, paired bootstrap in "
        "which every draw takes one of these records' validation resamples, re-chooses each re-tuned row's setting "
        "on it, then resamples seeds and test pairs (rlsac.maths.metrics.contrast_bootstrap); a row with fixed "
        "settings gets no term, a learned row's per-seed tuning is counted once (in its seed spread), and a tuned row "
        "without a record is marked *not measured* there. paper.md lists the verdicts that moved.\n")


def build(params: dict[str, Any], eval_root: str | Path = "reports/eval", out_dir: str | Path = "reports",
          retuning: Selection | None | Compute = COMPUTE) -> dict[str, Any]:
    """Write <out_dir>/tuning_budget.{md,csv}; -> {"files", "missing"}. ``retuning``: the re-tuning records
    (rlsac.reports.retuning.Selection of ``out_dir``, None for none), read here by default."""
    from rlsac.evaluation import retune, tune
    from rlsac.layout.protocol import N_BOOT
    from rlsac.reports.claims import TIE_MARGIN

    c = {**retune.conf(params), "tuned_at_tables": tune.conf(params)["iterations"]}
    eval_root, out_dir = Path(eval_root), Path(out_dir)
    a_rows, a_missing = budget_rows(c, eval_root, out_dir)
    b_rows, b_missing = retune_rows(c, out_dir)
    it, t0 = c["iterations"], c["tuned_at_tables"]
    head = (
        "# Two sources of variance the tables' intervals leave out (issue #47 item 7)\n\n"
        "Generated by `rlsac table --which tuning-budget` from reports/eval/folds, reports/eval/folds_at"
        f"{it}, reports/tuning*, reports/retune (no number here is typed by hand). mAA@10°, pooled over the folds.\n\n")
    sec_a = (
        f"## (a) Tuned at the test budget\n\nThe tables tune every row at {t0} iterations and test it at {it} too; the "
        f"CVPR 2020 tutorial tunes at the budget it tests at. Each row here was tuned again on the same validation "
        f"pairs, grid and rule at {it} iterations (reports/tuning_at{it}/) and tested at {it} "
        f"(reports/eval/folds_at{it}/). Difference = tuned@{it} − the tables' cell, paired on the same test pairs, "
        f"95% interval: {N_BOOT} bootstrap draws of the pairs within each test building. `folds re-chosen`: folds "
        "whose chosen settings differ. A learned row (`threshold`: params tuning_budget.learned) re-chooses its "
        "threshold alone at the tables' pre-filter (its grid runs the network at every point), over its training "
        "seeds, which the interval resamples too; `folds re-chosen` counts its seeds x folds.\n\n")
    df_a = pd.DataFrame([{k: v for k, v in r.items() if not k.startswith("_")} for r in a_rows])
    if a_rows:
        moved = [r for r in a_rows if any(r[f"_{n}"]["lo"] > 0 or r[f"_{n}"]["hi"] < 0 for n in ("R", "t"))]
        big = max(a_rows, key=lambda r: max(abs(r["_R"]["diff"]), abs(r["_t"]["diff"])))
        sec_a += df_a.to_markdown(index=False, disable_numparse=True) + (
            f"\n\n{len(moved)} of {len(a_rows)} rows move with an interval that excludes 0"
            + (f" ({', '.join(r['regime'] + '/' + r['row'] for r in moved)})" if moved else "")
            + f"; the largest move: {big['regime']}/{big['row']}, R {big['_R']['diff']:+.3f}, "
              f"t {big['_t']['diff']:+.3f}.\n")
    sec_b = (
        "\n## (b) Re-tuning variance\n\nThe intervals resample test pairs with each row's settings fixed, but the "
        "settings were chosen on a few dozen validation pairs per fold. Each row's choice was replayed with the "
        f"tuning's rule (rlsac.evaluation.tune.search, at {t0} iterations) on {c['retune_draws']} bootstrap resamples "
        "of its fold's validation pairs (stratified by scene), and every chosen setting tested. `re-tuned sd [95% "
        "range]`: the test mAA the draws' choices give (the folds pooled, each with its draw's choice); `tables`: "
        "the choice on all validation pairs (the tables' cell); `tables' ±`: the half-width of that cell's own 95% "
        "interval over test pairs; `all pairs = tables' record`: folds where the rule on all validation pairs gives "
        "the tables' record (it must); `settings chosen`: distinct choices per fold; `draws ≠ tables' choice`: the "
        "share of draws (mean over folds) that chose another setting. The claims' tie margin is "
        f"±{TIE_MARGIN}.\n\n")
    df_b = pd.DataFrame([{k: v for k, v in r.items() if not k.startswith("_")} for r in b_rows])
    if b_rows:
        sec_b += df_b.to_markdown(index=False, disable_numparse=True) + "\n\n"
    sec_b += decision(b_rows, TIE_MARGIN, halfwidth(out_dir) if resolve(retuning, out_dir) is not None else None)
    missing = a_missing + b_missing
    tail = ("\nNot compared (results absent): " + "; ".join(missing) + ".\n") if missing else ""
    write_text(out_dir / "tuning_budget.md", head + sec_a + sec_b + tail)
    csv = pd.concat([df_a.assign(part="a"), df_b.assign(part="b")], ignore_index=True) if b_rows or a_rows \
        else pd.DataFrame(columns=["part"])
    with atomic_path(out_dir / "tuning_budget.csv") as tmp:
        csv.to_csv(tmp, index=False)
    return {"files": [str(out_dir / "tuning_budget.md"), str(out_dir / "tuning_budget.csv")], "missing": missing}
