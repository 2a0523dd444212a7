"""The line generator's calibration landscape (issue #27): mAA and median error together, and the oracle's ceiling.

For every generator setting of a grid (``LineDataConf`` overrides: noise model, band, line, extent, ...), our
150-iteration RANSAC and the oracle (total least squares on the true inliers) run on the same instances at the
paper's outlier rates. A setting *matches* the paper's RANSAC row when at every rate its mAA lies within
``maa_tol`` and its median error within ``median_tol`` of the paper's; ``joint`` is the worst of those gaps
over the rates, each divided by its tolerance (a setting matches iff joint <= 1). The oracle's mAA at 0.7 is the
ceiling of any sampler followed by the same refinement: Table 1 can show the paper's gains only where it exceeds
the paper's Ours (0.824 at 0.7). ``consensus`` is RANSAC's own output would be had it drawn the
true line itself: the refinement on the points within the threshold of the true line (true inliers beyond the
threshold left out, outliers inside it taken in), a reference rather than a bound.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any

import numpy as np
import pandas as pd
import torch

from rlsac import config
from rlsac.data.lines import LineDataConf
from rlsac.errors import RlsacError

# Table 1 of the paper: outlier rate -> (mAA@0.5 deg, median error in deg)
PAPER_RANSAC = {0.1: (0.870, 0.049), 0.2: (0.863, 0.052), 0.3: (0.850, 0.056), 0.4: (0.829, 0.061),
                0.5: (0.796, 0.071), 0.6: (0.746, 0.087), 0.7: (0.608, 0.135)}
PAPER_OURS = {0.1: (0.875, 0.047), 0.2: (0.874, 0.049), 0.3: (0.872, 0.048), 0.4: (0.865, 0.050),
              0.5: (0.858, 0.052), 0.6: (0.845, 0.056), 0.7: (0.824, 0.062)}
PAPER_OURS_05 = {0.1: (0.849, 0.053), 0.2: (0.850, 0.055), 0.3: (0.854, 0.053), 0.4: (0.858, 0.052),
                 0.5: (0.858, 0.052), 0.6: (0.864, 0.050), 0.7: (0.849, 0.054)}
SHOWN_RATES = (0.1, 0.5, 0.7)


def expand(grid: dict[str, list] | list[dict[str, list]]) -> list[dict[str, Any]]:
    """A grid (field -> values, or a list of such grids, each expanded on its own) -> the settings, in order,
    each a dict of ``LineDataConf`` overrides; every setting is checked (config.build) before anything runs."""
    grids = [grid] if isinstance(grid, dict) else list(grid)
    settings: list[dict[str, Any]] = []
    for g in grids:
        if not g:
            raise RlsacError("a landscape grid names no field")
        keys = list(g)
        for values in itertools.product(*(list(g[k]) for k in keys)):
            s = dict(zip(keys, values, strict=True))
            if "outlier_rate" in s or "seed" in s or "n_instances" in s:
                raise RlsacError("a landscape grid sets outlier_rate, seed and n_instances itself; "
                                 f"leave them out of the grid ({s})")
            config.build(LineDataConf, s, "landscape")
            if s not in settings:
                settings.append(s)
    return settings


def evaluate_setting(setting: dict[str, Any], rates=tuple(PAPER_RANSAC), n_instances: int = 500,
                     seeds=(123,), iterations: int = 150, device: str = "cpu", batch_size: int = 256) -> pd.DataFrame:
    """One setting -> one row per rate: RANSAC's, the oracle's and the true line's consensus (``consensus``) mAA and
    median (deg), means over ``seeds`` (data seed = RANSAC's torch seed, as in ``rlsac calibrate-lines``)."""
    from rlsac.data import lines
    from rlsac.estimation.baselines import oracle, ransac
    from rlsac.evaluation.evaluate import run_method
    from rlsac.tasks import get_task

    task = get_task("line")
    rows = []
    for rate in rates:
        methods = {"ransac": lambda b, g: ransac(task, b, iterations, g), "oracle": lambda b, g: oracle(task, b),
                   "consensus": lambda b, g: true_consensus(task, b)}
        vals: dict[str, list[float]] = {f"{k}_{m}": [] for m in methods for k in ("mAA", "median")}
        for seed in seeds:
            conf = config.build(LineDataConf, {**setting, "outlier_rate": float(rate), "n_instances": n_instances,
                                               "seed": int(seed)}, "landscape")
            data = lines.generate(conf)
            for name, est in methods.items():
                errors, _ = run_method(task, est, data, lines.to_batch, n_instances, seed, device, batch_size,
                                       desc=f"{name} o{rate:g} s{seed}")
                s = task.summarize(errors)
                vals[f"mAA_{name}"].append(s["mAA"])
                vals[f"median_{name}"].append(s["median_deg"])
        rows.append({"outlier_rate": float(rate), **{k: float(np.mean(v)) for k, v in vals.items()}})
    t = pd.DataFrame(rows)
    paper = np.array([PAPER_RANSAC.get(r, (np.nan, np.nan)) for r in t["outlier_rate"]])
    t["mAA_gap"] = t["mAA_ransac"] - paper[:, 0]
    t["median_gap"] = t["median_ransac"] - paper[:, 1]
    return t


def true_consensus(task, batch: dict) -> dict:
    """RANSAC's output (``rlsac.estimation.baselines.finalize``) for the ground-truth line as its best hypothesis."""
    from rlsac.estimation.baselines import finalize

    coords = batch["coords"]
    hyp = torch.as_tensor(np.asarray(batch["line"]), dtype=coords.dtype, device=coords.device)
    return finalize(task, coords, batch["mask"], hyp, torch.ones(len(hyp), dtype=torch.bool, device=coords.device))


def joint_gap(maa_gap, median_gap, maa_tol: float, median_tol: float) -> float:
    """The worst |gap| over the rates, mAA and median each divided by its tolerance: <= 1 iff both match at every
    rate."""
    return float(max(np.max(np.abs(maa_gap)) / maa_tol, np.max(np.abs(median_gap)) / median_tol))


def summarize(setting: dict[str, Any], per_rate: pd.DataFrame, maa_tol: float, median_tol: float,
              low_rates: float = 0.5) -> dict:
    """One setting's per-rate table -> its landscape row: the setting, mean and worst |gap| of mAA and median over
    the rates, ``joint`` (``joint_gap``: <= 1 iff the setting matches) and ``joint_low`` (the same over the rates
    up to ``low_rates``), RANSAC at SHOWN_RATES, the oracle and the consensus at the highest rate (the ceiling) and
    the oracle's median at the highest rate over its median at the lowest, and RANSAC's median over the oracle's
    at the lowest rate."""
    t = per_rate.set_index("outlier_rate")
    a, m = t["mAA_gap"].abs(), t["median_gap"].abs()
    top = t.index.max()
    low = t.index <= low_rates + 1e-9
    row = {**setting, "mean_mAA_gap": a.mean(), "max_mAA_gap": a.max(), "mean_median_gap": m.mean(),
           "max_median_gap": m.max(), "joint": joint_gap(a, m, maa_tol, median_tol),
           "joint_low": joint_gap(a[low], m[low], maa_tol, median_tol) if low.any() else np.nan}
    for r in SHOWN_RATES:
        if r in t.index:
            row[f"mAA_{r:g}"], row[f"median_{r:g}"] = t.loc[r, "mAA_ransac"], t.loc[r, "median_ransac"]
    row[f"oracle_mAA_{top:g}"], row[f"oracle_median_{top:g}"] = t.loc[top, "mAA_oracle"], t.loc[top, "median_oracle"]
    row[f"consensus_mAA_{top:g}"] = t.loc[top, "mAA_consensus"]
    first = t.index.min()
    row["oracle_median_ratio"] = t.loc[top, "median_oracle"] / t.loc[first, "median_oracle"]
    row[f"ransac_over_oracle_median_{first:g}"] = t.loc[first, "median_ransac"] / t.loc[first, "median_oracle"]
    row["matches"] = bool(row["joint"] <= 1.0)
    return row


def landscape(settings: list[dict[str, Any]], maa_tol: float = 0.03, median_tol: float = 0.01,
              progress=None, **kw) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Every setting through ``evaluate_setting(**kw)`` -> (summary: one row per setting, sorted by joint;
    per_rate: one row per setting and rate, with the setting's index ``setting``)."""
    if maa_tol <= 0 or median_tol <= 0:
        raise RlsacError(f"tolerances must be > 0 (maa_tol={maa_tol}, median_tol={median_tol})")
    rows, tables = [], []
    for i, s in enumerate(settings):
        t = evaluate_setting(s, **kw)
        rows.append({"setting": i, "name": describe(s), **summarize(s, t, maa_tol, median_tol)})
        tables.append(t.assign(setting=i, **{k: str(v) for k, v in s.items()}))
        if progress:
            progress(i, s, rows[-1])
    summary = pd.DataFrame(rows).sort_values(["joint", "setting"], kind="stable").reset_index(drop=True)
    return summary, pd.concat(tables, ignore_index=True)


def describe(setting: dict[str, Any]) -> str:
    """Settings as the report names them: non-default fields only, e.g. ``noise=gaussian band=0.04``."""
    defaults = dataclasses.asdict(LineDataConf())
    shown = [f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in setting.items() if defaults.get(k) != v]
    return " ".join(shown) or "default"


def confirm(setting: dict[str, Any], n_instances: int = 1000, seed: int = 123, n_seeds: int = 4,
            maa_tol: float = 0.03, median_tol: float = 0.01, out_dir: str | None = None, **kw) -> dict:
    """One setting through ``rlsac calibrate-lines``' protocol (rlsac.commands.calibrate_lines, no params file,
    nothing tracked; its report goes to a temporary folder unless ``out_dir``) -> {"setting", "table" (its
    per-rate table), "joint", "joint_low" (rates up to 0.5), "n_seeds", "n_instances"}."""
    import tempfile
    from pathlib import Path

    from rlsac.commands import calibrate_lines

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(out_dir or tmp) / f"calibration_{'_'.join(f'{k}-{v}' for k, v in setting.items())}"
        s = calibrate_lines({**setting, "n_instances": n_instances, "seed": seed, "n_seeds": n_seeds,
                             "out": str(out), **kw}, track=False, params_path=None)
    t = s["table"]
    lo = t["outlier_rate"] <= 0.5 + 1e-9
    return {"setting": setting, "table": t, "n_seeds": n_seeds, "n_instances": n_instances,
            "joint": joint_gap(t["mAA_diff"], t["median_diff"], maa_tol, median_tol),
            "joint_low": joint_gap(t["mAA_diff"][lo], t["median_diff"][lo], maa_tol, median_tol)}


COLUMNS = {"name": "setting", "joint": "joint", "joint_low": "joint ≤0.5", "mean_mAA_gap": "mean |ΔmAA|",
           "max_mAA_gap": "max |ΔmAA|", "mean_median_gap": "mean |Δmed|", "max_median_gap": "max |Δmed|",
           "mAA_0.1": "mAA 0.1", "median_0.1": "med 0.1", "mAA_0.5": "mAA 0.5", "median_0.5": "med 0.5",
           "mAA_0.7": "mAA 0.7", "median_0.7": "med 0.7", "oracle_mAA_0.7": "oracle mAA 0.7",
           "oracle_median_0.7": "oracle med 0.7", "consensus_mAA_0.7": "consensus mAA 0.7",
           "oracle_median_ratio": "oracle med 0.7/0.1"}


def to_confirm(summary: pd.DataFrame, n_joint: int = 2, n_low: int = 2) -> list[int]:
    """The settings (``setting`` indices) to confirm: the best ``n_joint`` by joint, then the best ``n_low`` by
    joint over the low rates not already chosen."""
    chosen = [int(i) for i in summary.sort_values(["joint", "setting"])["setting"].head(n_joint)]
    for i in summary.sort_values(["joint_low", "setting"])["setting"]:
        if len(chosen) >= n_joint + n_low:
            break
        if int(i) not in chosen:
            chosen.append(int(i))
    return chosen


def landscape_markdown(summary: pd.DataFrame, confirmed: list[dict], meta: dict[str, Any]) -> str:
    """The report: protocol and criterion, what matching the paper at low rates leaves for the ceiling, the best
    settings, the highest ceilings, the confirmation runs and the conclusion, then the whole landscape.
    summary: ``landscape``'s; confirmed: ``confirm``'s; meta: command, n_instances, seeds, maa_tol, median_tol,
    iterations, grid (text)."""
    T_a, T_m = meta["maa_tol"], meta["median_tol"]
    low, top = min(PAPER_RANSAC), max(PAPER_RANSAC)
    (p_maa_low, p_med_low), (ours_maa, ours_med), (o5_maa, o5_med) = PAPER_RANSAC[low], PAPER_OURS[top], \
        PAPER_OURS_05[top]
    s = summary
    shown = s[[c for c in COLUMNS if c in s]].rename(columns=COLUMNS)

    def table(rows: pd.DataFrame) -> str:
        return shown.loc[rows.index].to_markdown(index=False, floatfmt=".3f")

    ratio = s["oracle_median_ratio"]
    near = s[(s[f"median_{low:g}"] - p_med_low).abs() <= T_m]  # RANSAC's median at the lowest rate matches
    lowmatch = s[s["joint_low"] <= 1].sort_values("oracle_mAA_0.7", ascending=False)
    ceiling_ok = s[s["oracle_mAA_0.7"] > ours_maa]
    n_match = int(s["matches"].sum())
    out = [
        "# Line generator calibration landscape: mAA and median error together, and the oracle's ceiling",
        "",
        f"Generated by `{meta['command']}`; do not edit by hand. Issue #27, item 0 (\"Table 1's ceiling\"). "
        "Nothing here changes the default generator.",
        "",
        "## Protocol",
        "",
        "Every generator setting (`rlsac.data.lines.LineDataConf` overrides; everything else at its default: N = 100 "
        "points, 10 x 10 picture, round(N(1 − ρ)) inliers, outliers uniform over the picture) is run at the paper's "
        f"outlier rates {', '.join(f'{r:g}' for r in PAPER_RANSAC)} on {meta['n_instances']} instances per rate and "
        f"data seed (seeds {', '.join(str(x) for x in meta['seeds'])}; the numbers are means over the seeds) with our "
        f"RANSAC (`rlsac.estimation.baselines.ransac`, {meta['iterations']} iterations, threshold 0.1, total least "
        "squares on the inliers of the best hypothesis), the **oracle** (total least squares on the true inliers: the "
        "ceiling of any sampler followed by the same refinement) and the **consensus** reference (RANSAC's output had "
        "it drawn the true line: total least squares on the points within 0.1 of it). Error: angle to the true "
        "line (deg); mAA@0.5° over 10 thresholds, as `rlsac calibrate-lines`.",
        "",
        "Knobs: `noise=uniform` displaces each inlier perpendicularly by U(−band, band) (the default, band = "
        "0.0825), `noise=gaussian` by N(0, band²) (band is the sd); `line=point_angle` (default: a uniform point and "
        "direction), `two_points` (through two uniform points), `angle_offset` (uniform direction and offset: more "
        "short corner chords); `extent=segment` puts the inliers on the segment between the two points (with "
        "`two_points` only: for the other lines that segment is 1 long).",
        "",
        f"Grid: {meta['grid']} ({len(s)} settings).",
        "",
        f"**Criterion.** A setting *matches* the paper's RANSAC row when at every rate |mAA − paper| ≤ {T_a:g} (the "
        f"README's tolerance) and |median − paper| ≤ {T_m:g}° (a fifth of the paper's smallest median, "
        f"{p_med_low:g}°). `joint` is the worst of these gaps over the seven rates, each divided by its tolerance: a "
        f"setting matches iff joint ≤ 1; `joint ≤0.5` is the same over the rates 0.1–0.5. The ceiling question: is "
        f"the oracle's mAA at {top:g} above the paper's Ours ({ours_maa:.3f}; Ours-0.5: {o5_maa:.3f})?",
        "",
        "## Matching the paper's RANSAC at the low rates caps the oracle",
        "",
        f"{n_match} of {len(s)} settings match at every rate; {len(lowmatch)} match at 0.1–0.5"
        + (f", and their oracle at {top:g} is at most {lowmatch['oracle_mAA_0.7'].max():.3f} (< {ours_maa:.3f}):"
           if len(lowmatch) else "."),
        "",
    ]
    if len(lowmatch):
        out += [table(lowmatch), ""]
    out += [
        f"The reason is the paper's protocol itself. With N fixed, the oracle fits round(N(1 − ρ)) points: at {top:g} "
        f"a third of those at {low:g}, with the same noise, so its errors grow by about sqrt(3) = 1.73; over the "
        f"{len(s)} settings its median at {top:g} is {ratio.min():.2f}–{ratio.max():.2f} times its median at {low:g}. "
        f"At {low:g} RANSAC finds the true consensus, so wherever its median is the paper's {p_med_low:g}° (± {T_m:g}; "
        f"{len(near)} settings) the oracle's median at {top:g} is "
        + (f"{near['oracle_median_0.7'].min():.3f}–{near['oracle_median_0.7'].max():.3f}° and its mAA "
           f"{near['oracle_mAA_0.7'].min():.3f}–{near['oracle_mAA_0.7'].max():.3f}"
           if len(near) else "–")
        + f". The paper's Ours reports a median of {ours_med:.3f}° at {top:g} and Ours-0.5 {o5_med:.3f}°, "
        f"{ours_med / PAPER_OURS[low][1]:.2f} and {o5_med / PAPER_OURS_05[low][1]:.2f} times their medians at "
        f"{low:g}: below what total least squares on the true inliers reaches on any of these generators. Extra "
        f"outliers in the band (a knob not tried here) would change RANSAC, not the oracle, and so cannot lift the "
        f"ceiling.",
        "",
        "## Best settings by the joint criterion",
        "",
        table(s.head(10)),
        "",
        f"## Highest ceilings (oracle mAA at {top:g})",
        "",
        table(s.sort_values("oracle_mAA_0.7", ascending=False).head(8)),
        "",
    ]
    if len(ceiling_ok):
        excess = ceiling_ok[f"mAA_{low:g}"] - p_maa_low
        out += [f"{len(ceiling_ok)} settings have an oracle above {ours_maa:.3f} at {top:g}; every one of them misses "
                f"the paper's RANSAC already at 0.1–0.5 (joint ≤0.5 at least {ceiling_ok['joint_low'].min():.2f}; its "
                f"RANSAC mAA at {low:g} is {excess.min():+.3f} to {excess.max():+.3f} off the paper's "
                f"{p_maa_low:.3f}): these generators are easier than the paper's RANSAC row says.", ""]
    if confirmed:
        out += ["## Confirmation with `rlsac calibrate-lines`' protocol",
                "",
                "The best settings by `joint` and by `joint ≤0.5`, run again with `rlsac.commands.calibrate_lines` "
                "(the setting as LineDataConf overrides, no params file):",
                ""]
        for c in confirmed:
            t = c["table"]
            out += [f"### {describe(c['setting'])}: joint {c['joint']:.2f}, joint ≤0.5 {c['joint_low']:.2f} "
                    f"({c['n_instances']} instances × {c['n_seeds']} seeds)",
                    "",
                    t[["outlier_rate", "mAA_ours", "mAA_paper", "mAA_diff", "median_ours", "median_paper",
                       "median_diff", "mAA_oracle", "median_oracle"]].rename(
                        columns={"mAA_ours": "mAA RANSAC", "median_ours": "med RANSAC"}).to_markdown(
                        index=False, floatfmt=".3f"),
                    ""]
    out += ["## Conclusion", "", conclusion(s, confirmed, T_a, T_m), "", "## The whole landscape", "",
            table(s), ""]
    return "\n".join(out)


def conclusion(summary: pd.DataFrame, confirmed: list[dict], maa_tol: float, median_tol: float) -> str:
    """The report's verdict, from the confirmation runs (the landscape's best rows where there are none)."""
    top = max(PAPER_RANSAC)
    ours = PAPER_OURS[top][0]
    ok = [c for c in confirmed if c["joint"] <= 1]
    if ok:
        c = min(ok, key=lambda c: c["joint"])
        ceiling = c["table"].set_index("outlier_rate").loc[top, "mAA_oracle"]
        return (f"Setting `{describe(c['setting'])}` matches the paper's RANSAC row in both mAA (within {maa_tol:g}) "
                f"and median (within {median_tol:g}°) at every rate, and its oracle at {top:g} is {ceiling:.3f} "
                f"({'>' if ceiling > ours else '≤'} the paper's Ours, {ours:.3f}).")
    if confirmed:
        parts = []
        for c in sorted(confirmed, key=lambda c: c["joint"]):
            t = c["table"].set_index("outlier_rate")
            worst = t["mAA_diff"].abs().idxmax()
            parts.append(f"`{describe(c['setting'])}` (joint {c['joint']:.2f}; matches at 0.1–0.5: "
                         f"{'yes' if c['joint_low'] <= 1 else 'no'}; largest mAA gap {t.loc[worst, 'mAA_diff']:+.3f} "
                         f"at {worst:g}, largest median gap {t['median_diff'].abs().max():.3f}°; oracle at {top:g} "
                         f"{t.loc[top, 'mAA_oracle']:.3f})")
    else:
        parts = [f"`{r['name']}` (joint {r['joint']:.2f}, oracle at {top:g} {r['oracle_mAA_0.7']:.3f})"
                 for _, r in summary.head(3).iterrows()]
    low_ok = summary[summary["joint_low"] <= 1]
    high = summary[summary["oracle_mAA_0.7"] > ours]
    ceiling_text = (f"and every setting whose oracle exceeds the paper's Ours ({ours:.3f}; {len(high)} of "
                    f"{len(summary)}) misses the paper's RANSAC already at 0.1–0.5 (joint ≤0.5 at least "
                    f"{high['joint_low'].min():.2f})"
                    if len(high) else f"and no setting's oracle exceeds the paper's Ours ({ours:.3f})")
    return (f"No setting matches both mAA (within {maa_tol:g}) and median (within {median_tol:g}°) at every rate. "
            f"The closest are {'; '.join(parts)}. What no setting reproduces is the paper's collapse of RANSAC "
            f"between 0.5 and {top:g}: where a setting matches at 0.1–0.5 its RANSAC stays too good at {top:g}, and "
            f"where it matches at {top:g} it is too poor below. The ceiling: "
            + (f"the settings that match at 0.1–0.5 have an oracle at {top:g} of at most "
               f"{low_ok['oracle_mAA_0.7'].max():.3f}, " if len(low_ok) else "")
            + ceiling_text + ". So on a generator calibrated to the paper's RANSAC, Table 1 cannot reach "
            f"the paper's Ours at {top:g}; it should state the oracle bound (on the default generator, "
            f"reports/calibration_lines.md) beside the paper's numbers.")
