"""Table 2 (folds): the leave-one-building-out benchmark, pooled and per building, with paired intervals.

Reads what ``rlsac folds`` wrote (never data/ itself):
    <eval_root>/folds/<regime>/<fold>/<method>/i<iterations>/{summary.json,errors.csv}
    <records>/<regime>/<fold>.json   the data stage's record (pairs, drops, inlier-ratio distribution)
Writes <out_dir>/table2_folds.{md,csv,tex} (pooled and per-building mAA@10° R / t at every budget, the paired
difference of every method to the reference RLSAC model, and RLSAC - uniform per fold) and
<out_dir>/folds_iterations.csv (pooled mAA per regime, method and budget: the iterations figure).

Pooling concatenates the per-pair errors of all folds (every pair of the substitute is a test pair exactly
once), so a pooled mAA rests on all pairs and one pair moves it by 1/n. Intervals: percentile bootstrap over
pairs, paired (the same pairs for both methods), 2000 resamples, seed 0.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rlsac.evaluation.methods import METHODS
from rlsac.evaluation.results import check_distinct, collect, load_records, pair_key, seed_errors, seed_runs  # noqa: F401
from rlsac.io import atomic_path, write_text
from rlsac.layout.protocol import LIMIT, N_BOOT  # mAA@10 deg, the bootstrap's draws
from rlsac.maths.metrics import mAA, paired_bootstrap_maa

# row labels: each registered method's (rlsac.evaluation.methods), the fold models' (RLSAC variants of folds.models)
# here; rows follow ROW_ORDER, then any other method or model alphabetically
MODEL_NAMES = {"rlsac": "RLSAC (paper recipe and algorithm)",
               "rlsac-nodesc": "RLSAC without descriptors (Table 3 a)",
               "rlsac-trainmax": "RLSAC, max sampling in training (Table 3 b)",
               "rlsac-prob": "RLSAC, probabilistic sampling in testing (Table 3 b)",
               "rlsac-trainmax-prob": "RLSAC, max in training, probabilistic in testing (Table 3 b)",
               "rlsac-nosnn": "RLSAC without the SNN ratio (not in the paper)",
               "rlsac-scale": "RLSAC at scale",
               "rlsac-lo": "RLSAC + LO (not in the paper)",
               "rlsac-fast": "RLSAC-fast: k sets per step, confidence stop, tuned (not in the paper)"}
ROW_ORDER = ("uniform", "ransac", "opencv_ransac", "usac-nolo", "magsac-nolo", "prosac-nolo", "guided", "rlsac",
             "rlsac-scale", "rlsac-nosnn", "rlsac-fast", "ngransac", "ransac-lo", "uniform-lo", "guided-lo", "rlsac-lo",
             "ngransac-lo",
             "usac", "usac_accurate", "magsac", "prosac", "degensac", "poselib")
# the like-for-like arms of issue #26: which machinery follows the sampler (a row not named is "no LO")
ARMS = {"ransac-lo": "same LO", "uniform-lo": "same LO", "guided-lo": "same LO", "rlsac-lo": "same LO",
        "ngransac-lo": "same LO", "usac": "OpenCV LO+polish", "usac_accurate": "OpenCV LO+polish",
        "magsac": "OpenCV LO+polish", "prosac": "OpenCV LO+polish", "degensac": "library LO+polish",
        "poselib": "library LO+polish"}
# rows whose library reports no hypothesis count: the table gives their stopping rule's bound (†)
OPENCV_ROWS = ("opencv_ransac", "usac", "usac_accurate", "magsac", "prosac", "usac-nolo", "magsac-nolo", "prosac-nolo",
               "degensac")


def arm(method: str) -> str:
    return ARMS.get(method, "no LO")
NAMES = {**{m: spec.label for m, spec in METHODS.items()}, **MODEL_NAMES}
REFERENCE = "rlsac"  # paired differences are taken against the paper-recipe RLSAC
# Table 2's rows shown wherever the reference is, "–" until their results exist (a row added before its runs)
EXPECTED = ("rlsac-scale",)
# the rows whose recipe the table's head states in a line of its own (rows not in the paper, named briefly)
LEGEND = ("RLSAC at scale (`rlsac-scale`, not in the paper; five training seeds like RLSAC): the scale study's recipe: "
          "10000 steps (33x), episodes redrawn from each pair's 1000 lowest-SNN matches with the images swapped, last "
          "actor, oneDNN kernels (`kernels: onednn`: the same losses as the study's, other last bits); "
          "reports/scale.md.\n")
CONTROLS = ("uniform", "guided")  # the learned sampler against uniform sets, and against a hand-made SNN-guided one


def _paired(a: pd.DataFrame, b: pd.DataFrame, col: str) -> tuple[float, float, float] | None:
    """mAA(a) - mAA(b) on the pairs both have, aligned by (fold, scene, pair)."""
    m = pd.merge(a.assign(k=pair_key(a))[["k", col]], b.assign(k=pair_key(b))[["k", col]], on="k",
                 suffixes=("_a", "_b"))
    if m.empty:
        return None
    return paired_bootstrap_maa(m[f"{col}_a"].to_numpy(), m[f"{col}_b"].to_numpy(), LIMIT, n_boot=N_BOOT, seed=0)


def _ci(t: tuple[float, float, float] | None) -> str:
    return "–" if t is None else f"{t[0]:+.3f} [{t[1]:+.3f}, {t[2]:+.3f}]"


def _order(methods) -> list[str]:
    known = [m for m in ROW_ORDER if m in methods]
    return known + sorted(set(methods) - set(known))


def data_table(recs: dict[tuple[str, str], dict]) -> pd.DataFrame:
    rows = []
    for (regime, fold), r in sorted(recs.items()):
        for split, s in r["splits"].items():
            q = s.get("gt_inlier_ratio_quantiles", {})
            rows.append({"regime": regime, "fold": fold, "split": split, "pairs": s["pairs"],
                         "dropped": s.get("skipped", 0), "inlier ratio mean": s["mean_gt_inlier_ratio_sampson_2px"],
                         **{k: q.get(k, math.nan) for k in ("q10", "q25", "q50", "q75", "q90")}})
    return pd.DataFrame(rows)


PROTOCOL = ("Every row's inlier threshold (px) and SNN pre-filter, and its own knobs (guided's temperature T, the LO "
            "rows' σ, RLSAC-fast's k and confidence), were chosen on its fold's validation pairs only (pairs of the "
            "training buildings; `reports/tuning/`, the table at the end of each regime), by the CVPR 2020 tutorial's "
            "grids at the tuning budget of params.yaml `tuning`; the test pairs were evaluated once with them. RLSAC, "
            "uniform and guided run the paper's algorithm (one minimal set per step, the whole budget). Arms: *no LO* "
            "(the sampler, scoring and one refit on the inliers: our rows and OpenCV's without LO or polisher), *same "
            "LO* (our samplers with the same local optimisation, rlsac.estimation.lo; not in the paper), *OpenCV "
            "LO+polish* (OpenCV's presets as they ship). `hypotheses`: minimal sets scored per pair, mean over pairs "
            "(the LO rows' non-minimal fits are counted apart, `lo_fits_per_instance` in each cell's summary.json); † "
            "OpenCV does not report its count: the bound of its stopping rule (confidence 0.999) "
            "at the returned inlier ratio. ")
TABLE2_HEAD = ("# Table 2 (folds): fundamental matrix, leave-one-building-out over the six Strecha scenes\n\n"
               "mAA@10° of the rotation (R) and translation (t) errors, pooled over every test pair of all folds and "
               "per test building. Each fold trains on the other buildings (validation: a held-out fifth of their "
               "pairs). `R − rlsac`: paired difference to the paper-recipe RLSAC on the same pairs with its 95% "
               f"interval (percentile bootstrap over pairs, {N_BOOT} resamples; one training seed per model: the "
               "interval does not cover training noise, issue #27). " + PROTOCOL
               + "Generated by `rlsac table --which folds`.\n\n" + LEGEND)
TABLE_E_HEAD = ("# Table E (not in the paper): essential matrix, leave-one-building-out over the six Strecha scenes\n\n"
                "The fold benchmark of Table 2 with calibrated correspondences (K known, the CVPR 2020 tutorial's "
                "essential-matrix track): five-point minimal sets (rlsac.tasks.essential), thresholds in px at "
                "f = 920 px, the best minimal model as the output. mAA@10° of R and t pooled over every test pair and "
                "per test building; `R − rlsac`: paired difference to RLSAC (trained per fold with train.essential, "
                f"the fold recipe) with its 95% interval (percentile bootstrap over pairs, {N_BOOT} resamples). "
                + PROTOCOL + "No USAC_ACCURATE row: OpenCV's findEssentialMat ignores the flag (its errors were "
                "USAC's on every pair; the table builder refuses two rows with identical errors). "
                "Generated by `rlsac table --which essential`.\n")


def build(eval_root: str | Path = "reports/eval", out_dir: str | Path = "reports",
          records: str | Path = "reports/folds/data", sub: str = "folds", stem: str = "table2_folds",
          iterations_stem: str | None = "folds_iterations", head: str = TABLE2_HEAD,
          tuning: str | Path | None = None, expected: tuple[str, ...] | None = None) -> dict[str, Any]:
    """Write <stem>.{md,csv} and <iterations_stem>.csv from <eval_root>/<sub>; -> {"files", "missing"}. ``expected``
    (default: ``EXPECTED`` for Table 2, none for another ``sub``): rows shown in every regime with the reference
    model, "–" where their results are absent (the .md only: the CSVs hold results)."""
    from rlsac.layout.protocol import split_points, split_seed

    everything = collect(eval_root, sub)
    check_distinct(everything, sub)
    # Table 3 (c)'s rows (<row>-n<N>) ran on other data (N points per pair): Table 3 only, never beside Table 2's;
    # the other training seeds' rows (<model>-s<seed>) enter the across-seed section only
    res = {k: v for k, v in everything.items() if split_points(k[1])[1] is None and split_seed(k[1])[1] is None}
    regimes_found = {r for r, _, _ in res}
    recs = {k: v for k, v in load_records(records).items() if k[0] in regimes_found}
    out_dir = Path(out_dir)
    rows, it_rows, md = [], [], []
    regimes = sorted({k[0] for k in res})
    expected = (EXPECTED if sub == "folds" else ()) if expected is None else tuple(expected)
    for regime in regimes:
        found = {k[1] for k in res if k[0] == regime}
        methods = _order(found | (set(expected) if REFERENCE in found else set()))
        budgets = sorted({k[2] for k in res if k[0] == regime})
        folds = sorted({f for k, df in res.items() if k[0] == regime for f in df["fold"].unique()})
        tests = [r["splits"]["test"] for (g, _), r in recs.items() if g == regime]
        ratio = [t["mean_gt_inlier_ratio_sampson_2px"] for t in tests for _ in range(int(t["pairs"]))]  # per pair
        first = _order(found)  # a row with results (an expected one may have none)
        n_test = {f: int((res[(regime, first[0], budgets[-1])]["fold"] == f).sum())
                  for f in folds} if first else {}
        n = sum(n_test.values())
        md.append(f"## Regime `{regime}`" + (f" (mean ground-truth inlier ratio of the test pairs "
                                              f"{np.mean(ratio):.2f})" if ratio else ""))
        md.append(f"{n} test pairs pooled over {len(folds)} folds ({', '.join(f'{f} {n_test[f]}' for f in folds)}): "
                  f"one pair moves a pooled mAA by {1 / max(n, 1):.4f}.\n")
        for it in budgets:
            table = []
            ref = res.get((regime, REFERENCE, it))
            for m in methods:
                df = res.get((regime, m, it))
                if df is None:
                    if m in expected:  # no results yet: shown as absent, written to no CSV
                        table.append({"method": m, "arm": arm(m), "hypotheses": math.nan, "mAA_R": math.nan,
                                      "mAA_t": math.nan, **{f"{f} {c}": math.nan for f in folds for c in "Rt"},
                                      f"R − {REFERENCE}": "–", f"t − {REFERENCE}": "–"})
                    continue
                hyp = df["n_hypotheses"].mean() if "n_hypotheses" in df else math.nan
                row = {"regime": regime, "iterations": it, "method": m, "arm": arm(m), "n": len(df),
                       "mAA_R": mAA(df["err_R"], LIMIT), "mAA_t": mAA(df["err_t"], LIMIT), "hypotheses": hyp}
                for f in folds:
                    d = df[df["fold"] == f]
                    row[f"{f} R"], row[f"{f} t"] = (mAA(d["err_R"], LIMIT), mAA(d["err_t"], LIMIT)) if len(d) \
                        else (math.nan, math.nan)
                for col, name in (("err_R", "R"), ("err_t", "t")):
                    d = _paired(df, ref, col) if ref is not None and m != REFERENCE else None
                    row[f"{name} − {REFERENCE}"] = _ci(d)
                    row[f"d{name}"], row[f"d{name}_lo"], row[f"d{name}_hi"] = d if d else (math.nan,) * 3
                table.append(row)
                rows.append(row)
                it_rows.append({"regime": regime, "method": m, "iterations": it, "mAA_R": row["mAA_R"],
                                "mAA_t": row["mAA_t"], "n_pairs": len(df),
                                **{k: row[k] for k in ("dR", "dR_lo", "dR_hi", "dt", "dt_lo", "dt_hi")}})
            if not any("n" in r for r in table):  # no row with results (an expected row's alone is no table)
                continue
            t = pd.DataFrame(table)
            per_fold = [c for f in folds for c in (f"{f} R", f"{f} t")]
            show = t[["method", "arm", "hypotheses", "mAA_R", "mAA_t", *per_fold, f"R − {REFERENCE}",
                      f"t − {REFERENCE}"]].copy()
            show["hypotheses"] = [("–" if math.isnan(h) else f"{h:.0f}" + ("†" if m in OPENCV_ROWS else ""))
                                  for m, h in zip(t["method"], t["hypotheses"], strict=True)]
            show["method"] = show["method"].map(lambda m: NAMES.get(m, m))
            for c in show.columns:
                if show[c].dtype.kind == "f":
                    show[c] = show[c].map(lambda v: "–" if math.isnan(v) else f"{v:.3f}")
            show = show.rename(columns={"mAA_R": "pooled R", "mAA_t": "pooled t"})
            md.append(f"### {it} iterations\n\n{show.to_markdown(index=False, disable_numparse=True)}\n")
        md.append(_control_section(res, regime, budgets, folds))
        seeds = _seed_section(everything, regime, budgets)
        if seeds:  # a table without models of several seeds (Table E) gets no empty section
            md.append(seeds)
            md.append(_seed_building_section(everything, regime, budgets[-1]))
        if tuning is not None:
            md.append(_tuning_section(Path(tuning), regime, methods, folds))
    if recs:
        dt = data_table(recs)
        md.append("## Prepared data (ground-truth inlier ratio: Sampson distance to the true F < 2 px)\n\n"
                  + dt.to_markdown(index=False, floatfmt=".2f") + "\n")
        imp = next(iter(recs.values())).get("import", {})
        if imp:
            md.append(f"Import (all six scenes): {imp.get('pairs')} image pairs, {imp.get('kept')} kept, "
                      f"{imp.get('dropped')} dropped ({imp.get('drop_rule')}); prepare drops only pairs with fewer "
                      "than 8 correspondences (column `dropped`).\n")
    missing = [] if res else [str(Path(eval_root) / sub)]
    files = []
    if rows:
        write_text(out_dir / f"{stem}.md", head + "\n" + "\n".join(md))
        with atomic_path(out_dir / f"{stem}.csv") as tmp:
            pd.DataFrame(rows).to_csv(tmp, index=False, float_format="%.4f")
        files = [str(out_dir / f"{stem}.md"), str(out_dir / f"{stem}.csv")]
        if sub == "folds":
            files += table3(everything, out_dir, load_records(records))
        if iterations_stem:
            with atomic_path(out_dir / f"{iterations_stem}.csv") as tmp:
                pd.DataFrame(it_rows, columns=["regime", "method", "iterations", "mAA_R", "mAA_t", "n_pairs", "dR",
                                               "dR_lo", "dR_hi", "dt", "dt_lo", "dt_hi"]).to_csv(
                    tmp, index=False, float_format="%.4f")
            files.append(str(out_dir / f"{iterations_stem}.csv"))
    else:
        print(f"{stem}: no results under {Path(eval_root) / sub}; nothing written")
    return {"files": files, "missing": missing}


def _control_section(res, regime: str, budgets, folds) -> str:
    """Each RLSAC model minus each control (uniform sets: the learned sampler alone; SNN-guided sets: what it
    adds beyond ranking matches by their SNN ratio), per fold and pooled, paired over pairs. A model in the same-LO
    arm (``-lo``) is set against the control with the same LO (``uniform-lo``, ``guided-lo``): like for like."""
    models = [m for m in _order({k[1] for k in res if k[0] == regime}) if m.startswith("rlsac")]
    out = []
    for control in CONTROLS:
        rows = []
        for m in models:
            against = f"{control}-lo" if m.endswith("-lo") else control
            for it in budgets:
                a, b = res.get((regime, m, it)), res.get((regime, against, it))
                if a is None or b is None:
                    continue
                row = {"model": NAMES.get(m, m), "control": NAMES.get(against, against), "iterations": it}
                for col, name in (("err_R", "R"), ("err_t", "t")):
                    row[f"pooled {name}"] = _ci(_paired(a, b, col))
                for f in folds:
                    row[f"{f} R / t"] = " / ".join(_ci(_paired(a[a["fold"] == f], b[b["fold"] == f], c))
                                                    for c in ("err_R", "err_t"))
                rows.append(row)
        if rows:
            what = ("the learned sampler alone; same environment, episodes, de-duplication, scoring, refinement, LO "
                    "and budget" if control == "uniform" else "what the policy adds beyond drawing sets by SNN ratio, "
                    "in the same environment")
            out.append(f"### RLSAC − {control} ({what}), paired over pairs, 95% interval\n\n"
                       + pd.DataFrame(rows).to_markdown(index=False, disable_numparse=True) + "\n")
    return "\n".join(out)


# the comparisons of the across-seed section (issue #27): the paper recipe (against its variants with seeds: both
# sides resampled), the controls, then the strongest rows of each arm
SEED_CONTROLS = ("rlsac", "uniform", "guided", "ransac", "prosac", "magsac", "degensac", "poselib")
# a same-LO row is set against the same-LO arm only (like for like, issue #26)
SEED_CONTROLS_LO = ("rlsac-lo", "ransac-lo", "uniform-lo", "guided-lo")


def seed_controls(model: str) -> tuple[str, ...]:
    """The controls of ``model`` in the across-seed section: its own arm's."""
    return SEED_CONTROLS_LO if arm(model) == "same LO" else SEED_CONTROLS


def seed_comparison(res, seeded: dict[str, list[str]], regime: str, model: str, control: str, it: int, col: str,
                    building: str | None = None) -> tuple[dict[str, float], int] | None:
    """``model`` − ``control`` in column ``col`` at ``it`` iterations, each row over its training seeds (``seeded``:
    ``seed_runs``; a row without other seeds is one run), on the pairs every run has (``building``: only that test
    building's) -> (metrics.seed_bootstrap_maa's result, the number of pairs), or None when a run or common pairs
    are missing."""
    from rlsac.maths.metrics import seed_bootstrap_maa

    got = seed_errors(res, seeded, regime, model, control, it, col, building)
    if got is None:
        return None
    a, b, fold = got
    return seed_bootstrap_maa(a, b, LIMIT, strata=fold, n_boot=N_BOOT, seed=0), a.shape[1]


def _seed_cells(s: dict) -> tuple[str, str, str]:
    """The cells of one seed-aware comparison (metrics.seed_bootstrap_maa's dict): the model's seed mean ± SD, the
    difference of seed means with its 95% interval, P(improvement)."""
    return (f"{s['mean_a']:.3f} ± {s['sd_a']:.3f}", _ci((s["diff"], s["lo"], s["hi"])), f"{s['p_improve']:.2f}")


def _seed_controls_at(res, seeded: dict[str, list[str]], regime: str, model: str, it: int) -> list[str]:
    """The controls a model with several seeds is set against at ``it`` iterations in the across-seed sections: its
    arm's (``seed_controls``) with results for every seed; none for a Table 3 variant (set against the full model in
    Table 3's own section) or when a seed of the model lacks results."""
    if model in set(TABLE3_ROWS.values()) - {REFERENCE} or any(res.get((regime, m, it)) is None
                                                                for m in seeded[model]):
        return []
    return [c for c in seed_controls(model) if c != model
            and all(res.get((regime, m, it)) is not None for m in seeded.get(c, [c]))]


def _seed_labels(seeded: dict[str, list[str]], model: str, control: str) -> dict[str, str]:
    """The model and control cells of an across-seed row: each row's name and, with several, its number of seeds."""
    n = len(seeded.get(control, [control]))
    return {"model": f"{NAMES.get(model, model)} ({len(seeded[model])} seeds)",
            "control": NAMES.get(control, control) + (f" ({n} seeds)" if n > 1 else "")}


def _seed_section(res, regime: str, budgets) -> str:
    """Issue #27: every model trained with several seeds against each control at every budget: the seed mean and
    seed-to-seed SD of its pooled mAA, the difference of seed means with a 95% interval that resamples seeds and pairs
    (pairs within their test building), and the probability of improvement (metrics.seed_bootstrap_maa)."""
    rows = []
    seeded = seed_runs(res, regime)
    for model in seeded:
        for it in budgets:
            for control in _seed_controls_at(res, seeded, regime, model, it):
                row = {"iterations": it, **_seed_labels(seeded, model, control)}
                several = len(seeded.get(control, [control])) > 1
                for col, name in (("err_R", "R"), ("err_t", "t")):
                    got = seed_comparison(res, seeded, regime, model, control, it, col)
                    if got is None:
                        continue
                    s = got[0]
                    mean_sd, diff, p_improve = _seed_cells(s)
                    row[f"model {name} (mean ± SD)"] = mean_sd
                    row[f"control {name}"] = f"{s['mean_b']:.3f}" + (f" ± {s['sd_b']:.3f}" if several else "")
                    row[f"{name}: model − control"] = diff
                    row[f"P(improve) {name}"] = p_improve
                rows.append(row)
    if not rows:
        return ""
    return ("### Across training seeds (issue #27): seed means, paired with each control, seeds and pairs resampled\n\n"
            "The rows above show each model's first seed (the shipped checkpoint). Here every training seed of a "
            "model counts: `mean ± SD` over seeds of the pooled mAA@10°; `model − control`: difference of the seed "
            f"means with a 95% hierarchical bootstrap interval ({N_BOOT} draws: the seeds with replacement, then the "
            "test pairs within each building, the same pairs for both rows); `P(improve)`: the probability that a "
            "random seed beats the control on a random test building (ties one half). Each seed's settings were "
            "tuned on its fold's validation pairs like the first seed's.\n\n"
            + pd.DataFrame(rows).to_markdown(index=False, disable_numparse=True) + "\n")


def _seed_building_section(res, regime: str, it: int) -> str:
    """Issue #29: the across-seed comparisons of ``_seed_section`` at ``it`` iterations (the largest budget) within
    each test building: the seeds and that building's pairs resampled (metrics.seed_bootstrap_maa on its pairs)."""
    rows = []
    seeded = seed_runs(res, regime)
    buildings = sorted({f for m in seeded if (regime, m, it) in res for f in res[(regime, m, it)]["fold"].unique()})
    n_pairs = {}
    for model in seeded:
        for control in _seed_controls_at(res, seeded, regime, model, it):
            row = _seed_labels(seeded, model, control)
            for b in buildings:
                for col, name in (("err_R", "R"), ("err_t", "t")):
                    got = seed_comparison(res, seeded, regime, model, control, it, col, building=b)
                    row[f"{b} {name}"] = "–" if got is None else _seed_cells(got[0])[1]
                    if got is not None:
                        n_pairs[b] = got[1]
            rows.append(row)
    if not rows:
        return ""
    sizes = ", ".join(f"{b} {n_pairs[b]}" for b in buildings if b in n_pairs)
    return (f"### Across training seeds, per test building ({it} iterations)\n\n"
            "The comparisons above within one test building: `model − control` in mAA@10° of the building's pairs, "
            f"with a 95% interval ({N_BOOT} draws: the seeds with replacement, then that building's pairs). Pairs per "
            f"building: {sizes}; one pair moves a building's mAA by 1/its pairs, so the small buildings' intervals "
            "are wide.\n\n" + pd.DataFrame(rows).to_markdown(index=False, disable_numparse=True) + "\n")


SHORT = {"guide_temperature": "T", "lo_sigma_scale": "σ", "sets_per_step": "k", "confidence": "conf",
         "refit_output": "refit"}


def _tuning_section(root: Path, regime: str, methods: list[str], folds: list[str]) -> str:
    """Per row and fold: the settings chosen on that fold's validation pairs (rlsac.evaluation.tune records under
    ``root``/<regime>/<fold>/<row>.json) and their validation mAA."""
    from rlsac.evaluation.results import read_record

    rows = []
    for m in methods:
        row = {"method": NAMES.get(m, m)}
        for f in folds:
            path = root / regime / f / f"{m}.json"
            rec = read_record(path)  # a corrupt record is an error naming it; an absent one is "–"
            if rec is None:
                row[f] = "–"
                continue
            c = rec["chosen"]
            parts = [f"{c.get('threshold_px', math.nan):g} px",
                     "no filter" if c.get("prefilter", 1.0) == 1.0 else f"SNN<{c['prefilter']:g}"]
            parts += [f"{SHORT.get(k, k)}={v if isinstance(v, bool) else f'{v:g}'}" for k, v in c.items()
                      if k not in ("threshold_px", "prefilter")]
            row[f] = f"{', '.join(parts)} (val {rec.get('val', {}).get('mAA', math.nan):.3f})"
        rows.append(row)
    if not rows:
        return ""
    return ("### Settings chosen on each fold's validation pairs (rlsac.evaluation.tune; validation mAA@10° of max(R, "
            "t) at the tuning budget)\n\n" + pd.DataFrame(rows).to_markdown(index=False, disable_numparse=True) + "\n")


# Table 3 on the folds (issue #26): the paper's ablations as fold rows, each tuned per fold like every row. Paper
# variant -> our row; (c)'s rows ran on the fold data prepared with N points per pair (folds.points)
TABLE3_ROWS = {"no_descriptors": "rlsac-nodesc", "full": "rlsac", "train_max-test_max": "rlsac-trainmax",
               "train_max-test_prob": "rlsac-trainmax-prob", "train_prob-test_prob": "rlsac-prob",
               "n100": "rlsac-n100", "n200": "rlsac-n200", "n300": "rlsac-n300"}
TABLE3_REGIME = "hard"
FULL_POINTS = 150  # the full model's N (fundamental.n_points, the paper's)


def _test_inlier_ratio(recs: dict[tuple[str, str], dict], data_regime: str) -> float:
    """Mean ground-truth inlier ratio over the test pairs of every fold of ``data_regime`` (data stage records)."""
    tests = [r["splits"]["test"] for (g, _), r in recs.items() if g == data_regime]
    n = sum(int(t["pairs"]) for t in tests)
    return sum(t["mean_gt_inlier_ratio_sampson_2px"] * int(t["pairs"]) for t in tests) / n if n else math.nan


def _n_study(res: dict[tuple[str, str, int], pd.DataFrame], it: int, recs: dict[tuple[str, str], dict]) -> str:
    """Table 3 (c) against the uniform control on the same data: for every N, RLSAC trained and tested with N points
    per pair, uniform minimal sets on those points, and their paired difference (the policy's share; the data change
    with N for both)."""
    from rlsac.layout.protocol import points_name, split_points

    control = CONTROLS[0]
    ns = {n for r, m, i in res if r == TABLE3_REGIME and i == it
          for base, n in [split_points(m)] if base == REFERENCE and n is not None}
    if not ns:
        return ""
    rows = []
    for n in sorted({*ns, FULL_POINTS}):
        full = n == FULL_POINTS
        m, c = (REFERENCE, control) if full else (points_name(REFERENCE, n), points_name(control, n))
        a, b = res.get((TABLE3_REGIME, m, it)), res.get((TABLE3_REGIME, c, it))
        if a is None:
            continue
        row = {"N": f"{n}" + (" (full)" if full else ""), "rows": f"{m} / {c}",
               "test inlier ratio": _test_inlier_ratio(recs, TABLE3_REGIME if full else f"{TABLE3_REGIME}-n{n}"),
               "RLSAC R / t": f"{mAA(a['err_R'], LIMIT):.3f} / {mAA(a['err_t'], LIMIT):.3f}",
               "uniform R / t": "–" if b is None else f"{mAA(b['err_R'], LIMIT):.3f} / {mAA(b['err_t'], LIMIT):.3f}"}
        for col, name in (("err_R", "R"), ("err_t", "t")):
            row[f"RLSAC − uniform {name}"] = _ci(_paired(a, b, col) if b is not None else None)
        rows.append(row)
    t = pd.DataFrame(rows)
    t["test inlier ratio"] = t["test inlier ratio"].map(lambda v: "–" if math.isnan(v) else f"{v:.2f}")
    return (f"#### (c) against the uniform control on the same data ({it} iterations)\n\n"
            + t.to_markdown(index=False, disable_numparse=True) + "\n")


def _table3_seeds(res: dict[tuple[str, str, int], pd.DataFrame], it: int) -> str:
    """Issue #27 on Table 3: every variant with other training seeds against the full model over its seeds: seed mean
    ± SD, the difference of seed means with a 95% interval that resamples seeds and pairs, P(improvement)."""
    from rlsac.reports import paper

    seeded = seed_runs(res, TABLE3_REGIME)
    labels = {TABLE3_ROWS[v]: label for _, label, v, _ in paper.TABLE3 if v in TABLE3_ROWS}
    full = seeded.get(REFERENCE, [REFERENCE])
    rows = []
    for m in dict.fromkeys(TABLE3_ROWS.values()):
        if m == REFERENCE or m not in seeded:
            continue
        row = {"variant": labels.get(m, m), "row": f"{m} ({len(seeded[m])} seeds)",
               "full": f"{REFERENCE} ({len(full)} seed{'s' if len(full) > 1 else ''})"}
        for col, name in (("err_R", "R"), ("err_t", "t")):
            got = seed_comparison(res, seeded, TABLE3_REGIME, m, REFERENCE, it, col)
            if got is None:
                continue
            row[f"{name} (mean ± SD)"], row[f"{name} − full"], row[f"P(improve) {name}"] = _seed_cells(got[0])
        rows.append(row)
    if not rows:
        return ""
    return (f"#### Across training seeds ({it} iterations; issue #27)\n\n"
            "Each variant over all its training seeds against the full model over its own: `mean ± SD` over seeds of "
            f"the pooled mAA@10°, `− full` the difference of seed means with a 95% interval ({N_BOOT} draws: seeds "
            "with replacement, then test pairs within each building, the same pairs for both rows), `P(improve)` the "
            "probability that a random seed of the variant beats one of the full model on a random test building.\n\n"
            + pd.DataFrame(rows).to_markdown(index=False, disable_numparse=True) + "\n")


def table3(res: dict[tuple[str, str, int], pd.DataFrame], out_dir: Path,
           recs: dict[tuple[str, str], dict] | None = None) -> list[str]:
    """Write table3_folds.{md,csv} from the fold results when the hard regime has RLSAC and an ablation row:
    pooled mAA@10° R / t and medians of each variant beside the paper's, and each variant − the full model, paired
    over the same pairs with its 95% interval. -> the files written."""
    from rlsac.reports import paper

    budgets = sorted({it for r, m, it in res if r == TABLE3_REGIME and m == REFERENCE})
    if not budgets or not any((TABLE3_REGIME, TABLE3_ROWS[v], it) in res for v in TABLE3_ROWS if v != "full"
                              for it in budgets):
        return []
    rows, md = [], []
    for it in budgets:
        ref = res[(TABLE3_REGIME, REFERENCE, it)]
        table = []
        for group, label, variant, numbers in paper.TABLE3:
            m = TABLE3_ROWS.get(variant)
            df = res.get((TABLE3_REGIME, m, it)) if m else None
            row = {"iterations": it, "group": group, "variant": label, "row": m or "–",
                   "mAA_R": mAA(df["err_R"], LIMIT) if df is not None else math.nan,
                   "mAA_t": mAA(df["err_t"], LIMIT) if df is not None else math.nan,
                   "median_R": float(np.median(df["err_R"])) if df is not None else math.nan,
                   "median_t": float(np.median(df["err_t"])) if df is not None else math.nan,
                   "paper R / t": f"{numbers[0]:.3f} / {numbers[1]:.3f}"}
            for col, name in (("err_R", "R"), ("err_t", "t")):
                d = _paired(df, ref, col) if df is not None and m != REFERENCE else None
                row[f"{name} − full"] = _ci(d)
            table.append(row)
            rows.append(row)
        t = pd.DataFrame(table)
        for c in ("mAA_R", "mAA_t", "median_R", "median_t"):
            t[c] = t[c].map(lambda v: "–" if math.isnan(v) else f"{v:.3f}")
        md.append(f"### {it} iterations\n\n" + t.drop(columns="iterations").to_markdown(index=False,
                                                                                         disable_numparse=True) + "\n")
        md.append(_n_study(res, it, recs or {}))
        md.append(_table3_seeds(res, it))
    n = len(res[(TABLE3_REGIME, REFERENCE, budgets[-1])])
    head = ("# Table 3 (folds): ablations of RLSAC on the leave-one-building-out benchmark\n\n"
            f"The paper's ablations as rows of Table 2 (folds), `{TABLE3_REGIME}` regime, {n} test pairs pooled over "
            f"the folds (one pair = {1 / max(n, 1):.4f} mAA). Every model is trained per fold with the full model's "
            "recipe and budget (params.yaml `folds.train`); the rows show each model's first training seed, and the "
            "across-seed tables under each budget count all of them; every row's threshold and pre-filter "
            "are tuned on its fold's validation pairs. `− full`: paired difference to the full model (probabilistic "
            f"sampling in training, max in testing, descriptors, N = {FULL_POINTS}) with its 95% interval ({N_BOOT} "
            "bootstrap resamples over pairs). (c): the fold data prepared again with N points per pair (drawn from "
            "the same pool of low-SNN matches; params.yaml `folds.points`), a model trained on each N with the full "
            "recipe: its `− full` compares the same image pairs with other correspondences, so it mixes the data's "
            "change with the policy's; the table under each budget sets every N against uniform minimal sets on the "
            "same points (not in the paper). The paper's numbers (CVPR 2020 tutorial validation set) are beside ours. "
            "Generated by `rlsac table --which folds`.\n")
    write_text(out_dir / "table3_folds.md", head + "\n" + "\n".join(md))
    with atomic_path(out_dir / "table3_folds.csv") as tmp:
        pd.DataFrame(rows).to_csv(tmp, index=False, float_format="%.4f")
    return [str(out_dir / "table3_folds.md"), str(out_dir / "table3_folds.csv")]
