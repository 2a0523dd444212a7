"""reports/learner.md, learner.csv and learner_ladder.png: where the learner stops (issue #61).

Reads the ladder's run records (experiments/ladder/<rung>/s<seed>.json: a run's curve and per-pair test errors) and
each rung's controls (…/controls.json: uniform, guided and oracle sets in the same environment); nothing is run
here (rlsac.experiments.ladder makes them). Comparisons are paired on each rung's test pairs and resample training
seeds, then pairs (rlsac.maths.metrics.seed_bootstrap_maa); pi(inliers) intervals the same way.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from rlsac.errors import RlsacError
from rlsac.evaluation.results import read_mapping
from rlsac.io import atomic_path
from rlsac.layout.ladder_layout import CLAIMS, ROOT, TIE_MARGIN
from rlsac.layout.protocol import N_BOOT
from rlsac.maths.metrics import mAA, seed_bootstrap_maa, stratified_draws

LIMIT = 10.0  # mAA@10 deg, Table 2's
SAMPLERS = ("uniform", "guided", "oracle")
PI_CLOSE, MAA_CLOSE = 0.05, 0.01  # item 1: "within 0.05 of guided's pi(inliers), within 0.01 of its mAA_R"


def _finite_list(v: Any, path: Path, what: str, n: int | None = None) -> np.ndarray:
    a = np.asarray(v, dtype=object)
    if a.ndim != 1 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in a):
        raise RlsacError(f"{path}: {what} is not a list of numbers")
    a = a.astype(np.float64)
    if not np.isfinite(a).all() or (a < 0).any():
        raise RlsacError(f"{path}: {what} holds a NaN, an infinity or a negative value")
    if n is not None and a.size != n:
        raise RlsacError(f"{path}: {what} has {a.size} pairs, not the rung's {n}")
    return a


def _measurement(m: Any, path: Path, what: str, n: int | None) -> dict[str, np.ndarray]:
    if not isinstance(m, dict) or set(m) != {"err_R", "err_t", "pi_inliers"}:
        raise RlsacError(f"{path}: {what} needs err_R, err_t and pi_inliers")
    out = {k: _finite_list(m[k], path, f"{what}.{k}", n) for k in ("err_R", "err_t", "pi_inliers")}
    n = n if n is not None else out["err_R"].size
    for k, v in out.items():
        if v.size != n:
            raise RlsacError(f"{path}: {what}.{k} has {v.size} pairs, not {n}")
    return out


def read_json(path: Path) -> dict:
    """A ladder record (rlsac.evaluation.results.read_mapping: JSON, a mapping, every number finite)."""
    return read_mapping(path, "ladder record")


def load(c: dict[str, Any], order: list[str], root: Path = ROOT,
         controls_of: dict[str, str] | None = None) -> dict[str, dict]:
    """Every rung's controls and finished runs, checked -> {rung: {"controls": {sampler: {budget: arrays}},
    "runs": {seed: record with arrays}}} (a rung without controls is left out; missing runs are pending)."""
    budgets = [str(i) for i in c["iterations"]]
    controls_of = controls_of or {}  # a rung measured against another rung's controls (Rung.controls)
    out: dict[str, dict] = {}
    for rung in order:
        cpath = root / controls_of.get(rung, rung) / "controls.json"
        if not cpath.is_file():
            continue
        ctl = read_json(cpath)
        n = None
        controls = {}
        for s in SAMPLERS:
            per = (ctl.get("samplers") or {}).get(s)
            if not isinstance(per, dict) or any(b not in per for b in budgets):
                raise RlsacError(f"{cpath}: sampler {s} lacks a budget of {budgets}")
            controls[s] = {b: _measurement(per[b], cpath, f"{s}@{b}", n) for b in budgets}
            n = controls[s][budgets[0]]["err_R"].size
        runs = {}
        for seed in c["seeds"]:
            rpath = root / rung / f"s{seed}.json"
            if not rpath.is_file():
                continue
            r = read_json(rpath)
            if not isinstance(r.get("final"), dict) or not isinstance(r.get("curve"), list):
                raise RlsacError(f"{rpath}: a ladder run needs final and curve")
            final = {b: _measurement(r["final"].get(b), rpath, f"final@{b}", n) for b in budgets}
            for row in r["curve"]:
                for k in ("step", "mAA_R", "mAA_t", "pi_inliers"):
                    v = row.get(k) if isinstance(row, dict) else None
                    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                        raise RlsacError(f"{rpath}: curve row {row!r}: {k} is not a finite number")
            runs[int(seed)] = {"final": final, "curve": r["curve"], "why": r.get("why", "")}
        out[rung] = {"controls": controls, "runs": runs, "threshold": ctl.get("threshold")}
    return out


def mean_interval(a: np.ndarray, b: np.ndarray, n_boot: int = N_BOOT, seed: int = 0) -> tuple[float, float, float]:
    """mean(a) - mean(b) of per-pair values, a (S_a, M) seeds x pairs, b (S_b, M): seeds then pairs resampled, the
    pairs paired -> (difference, low, high)."""
    rng = np.random.default_rng(seed)
    idx = stratified_draws(rng, np.zeros(a.shape[1], dtype=np.int64), n_boot)
    pa, pb = a[:, idx].mean(axis=2), b[:, idx].mean(axis=2)
    cols = np.arange(n_boot)[:, None]
    boot = pa[rng.integers(0, len(a), (n_boot, len(a))), cols].mean(1) - \
        pb[rng.integers(0, len(b), (n_boot, len(b))), cols].mean(1)
    return float(a.mean() - b.mean()), float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


def rung_rows(rung: str, d: dict, budgets: list[str]) -> list[dict[str, Any]]:
    """One row per (budget, sampler), RLSAC's a seed mean, and RLSAC - each control with its interval."""
    rows = []
    seeds = sorted(d["runs"])
    for b in budgets:
        for s in SAMPLERS:
            m = d["controls"][s][b]
            rows.append({"rung": rung, "budget": int(b), "sampler": s, "seeds": 0,
                         "pi_inliers": float(m["pi_inliers"].mean()), "mAA_R": mAA(m["err_R"], LIMIT),
                         "mAA_t": mAA(m["err_t"], LIMIT)})
        if not seeds:
            continue
        runs = [d["runs"][k]["final"][b] for k in seeds]
        row = {"rung": rung, "budget": int(b), "sampler": "rlsac", "seeds": len(seeds),
               "pi_inliers": float(np.mean([r["pi_inliers"].mean() for r in runs])),
               "mAA_R": float(np.mean([mAA(r["err_R"], LIMIT) for r in runs])),
               "mAA_t": float(np.mean([mAA(r["err_t"], LIMIT) for r in runs]))}
        for s in SAMPLERS:
            ctl = d["controls"][s][b]
            for k in ("R", "t"):
                got = seed_bootstrap_maa(np.stack([r[f"err_{k}"] for r in runs]), ctl[f"err_{k}"][None], LIMIT)
                row[f"d_{s}_{k}"] = (got["diff"], got["lo"], got["hi"])
            row[f"d_{s}_pi"] = mean_interval(np.stack([r["pi_inliers"] for r in runs]), ctl["pi_inliers"][None])
        rows.append(row)
    return rows


def _first(curve: list[dict], key: str, level: float) -> int | None:
    """The first step of ``curve`` where ``key`` reaches ``level`` (None: never)."""
    return next((row["step"] for row in curve if row[key] >= level), None)


def convergence(d: dict, budget: str) -> list[dict[str, Any]]:
    """Item 1, per seed of a control rung: the first curve step where pi(inliers) is within PI_CLOSE of the guided
    sampler's and mAA_R within MAA_CLOSE of guided's (curve and controls on the same test pairs), the peak pi and the
    drift after it (last - peak)."""
    g = d["controls"]["guided"][budget]
    g_pi, g_r = float(g["pi_inliers"].mean()), mAA(g["err_R"], LIMIT)
    out = []
    for seed, r in sorted(d["runs"].items()):
        cv = r["curve"]
        peak = max(cv, key=lambda row: row["pi_inliers"])
        out.append({"seed": seed, "guided_pi": g_pi, "guided_mAA_R": g_r,
                    "pi_step": _first(cv, "pi_inliers", g_pi - PI_CLOSE),
                    "maa_step": _first(cv, "mAA_R", g_r - MAA_CLOSE),
                    "peak_pi": peak["pi_inliers"], "peak_step": peak["step"], "last_pi": cv[-1]["pi_inliers"],
                    "drift": cv[-1]["pi_inliers"] - peak["pi_inliers"], "alpha_peak": peak.get("alpha"),
                    "alpha_last": cv[-1].get("alpha")})
    return out


def _arrays(data: dict[str, dict], side: tuple[str, str], budget: str, key: str) -> np.ndarray | None:
    """(S, M) per-pair values of one side of a claim: a rung's learned runs (S seeds) or one of its controls (S = 1);
    None while the rung or its runs are pending."""
    rung, sampler = side
    d = data.get(rung)
    if d is None:
        return None
    if sampler != "rlsac":
        return d["controls"][sampler][budget][key][None]
    if not d["runs"]:
        return None
    return np.stack([d["runs"][k]["final"][budget][key] for k in sorted(d["runs"])])


def judge(claim, data: dict[str, dict]) -> dict[str, Any]:
    """A claim's difference, interval and verdict: supported (better / worse: the interval on that side of 0; tie:
    inside +-TIE_MARGIN), not supported (the interval on the other side, or a tie's excluding 0), else inconclusive;
    pending while a side's runs are missing; not measured where params ladder.iterations lacks the claim's budget."""
    key = {"R": "err_R", "t": "err_t", "pi": "pi_inliers"}[claim.metric]
    if any(r in data and str(claim.budget) not in data[r]["controls"]["uniform"] for r in (claim.a[0], claim.b[0])):
        return {"verdict": "not measured", "diff": None, "seeds": 0}  # a profile without the claim's budget
    a, b = (_arrays(data, side, str(claim.budget), key) for side in (claim.a, claim.b))
    if a is None or b is None:
        return {"verdict": "pending", "diff": None, "seeds": 0}
    if a.shape[1] != b.shape[1]:
        raise RlsacError(f"claim {claim.text!r}: its two sides were measured on different pairs")
    if claim.metric == "pi":
        d, lo, hi = mean_interval(a, b)
    else:
        got = seed_bootstrap_maa(a, b, LIMIT)
        d, lo, hi = got["diff"], got["lo"], got["hi"]
    if claim.expect == "tie":
        verdict = "supported" if -TIE_MARGIN <= lo and hi <= TIE_MARGIN else \
            "not supported" if lo > 0 or hi < 0 else "inconclusive"
    else:
        sign = 1 if claim.expect == "better" else -1
        verdict = "supported" if min(sign * lo, sign * hi) > 0 else \
            "not supported" if max(sign * lo, sign * hi) < 0 else "inconclusive"
    return {"verdict": verdict, "diff": (d, lo, hi), "seeds": max(len(a), len(b))}


def _ci(t: tuple[float, float, float]) -> str:
    return f"{t[0]:+.3f} [{t[1]:+.3f}, {t[2]:+.3f}]"


def _claim_row(cl, data: dict[str, dict]) -> str:
    j = judge(cl, data)
    diff = _ci(j["diff"]) if j["diff"] is not None else "–"
    name = {"R": "mAA_R", "t": "mAA_t", "pi": "π(inliers)"}[cl.metric]
    return (f"| {cl.text} | {cl.a[0]} {cl.a[1]} − {cl.b[0]} {cl.b[1]} | {name} @ {cl.budget} | {cl.expect} | "
            f"{j['seeds']} | {diff} | {j['verdict']} |")


def markdown(c: dict, data: dict[str, dict], order: list[str], why: dict[str, str], rows: list[dict]) -> str:
    budgets = [int(i) for i in c["iterations"]]
    seeds = ", ".join(map(str, c["seeds"]))
    lines = [
        "# Where the learner stops (issue #61)", "",
        "Generated by `rlsac table --which learner` (stage `learner_report`) from the ladder's runs (`rlsac scale "
        "--stage ladder`, rlsac.experiments.ladder; params.yaml `ladder`). Each rung changes one thing on the way "
        f"from the positive control to the {c['fold']} fold's real pairs; every run trains the fold recipe "
        f"({c['steps']} steps, 16 episodes per step, batch 32) with training seeds {seeds}. All samplers of a rung "
        "run in the same environment (episodes, de-duplication, scoring, refinement, budget): uniform sets, guided "
        "sets (SNN softmax, T = 0.1), the **oracle** (sets drawn from the ground-truth inliers only: the ceiling of "
        "sampling) and RLSAC's policy. π(inliers): a sampler's probability mass on the ground-truth inliers (the "
        "policy's at its first step; uniform's is the inlier ratio). mAA_R / mAA_t: mAA@10° of the rotation / "
        "translation error. Differences are RLSAC − control on the same test pairs, 95% intervals resampling training "
        "seeds, then pairs. Synthetic rungs are measured at the task's threshold (2 px), real rungs at the "
        f"{c['settings_from']} control's threshold tuned on the fold's validation pairs; the SNN pre-filter is off "
        "except in rung 4 (Table 2's environment). A rung with fewer seeds than listed is still running: its row "
        "says how many.", "",
        "## Claims written before the runs finished", "",
        "Written in rlsac.layout.ladder_layout.CLAIMS when one run (rung 3, seed 0) and its controls were in; each is "
        "judged here on the runs there are now (a − b on the same test pairs; tie: the interval inside ±"
        f"{TIE_MARGIN}).", "", "| claim | a − b | metric @ budget | expect | seeds | difference [95%] | verdict |",
        "|" + " --- |" * 7,
        *[_claim_row(cl, data) for cl in CLAIMS], "",
        f"## The ladder at {c['curve_iterations']} hypotheses", "",
        "| rung | what changes | seeds | π uniform | π guided | π RLSAC | π oracle | mAA_R uniform | guided | RLSAC | "
        "oracle | RLSAC − uniform, mAA_R | RLSAC − guided, mAA_R |", "|" + " --- |" * 13]
    at = c["curve_iterations"] if c["curve_iterations"] in budgets else budgets[len(budgets) // 2]
    for rung in order:
        if rung not in data:
            lines.append(f"| {rung} | {why[rung]} | 0 | pending |" + " |" * 9)
            continue
        by = {r["sampler"]: r for r in rows if r["rung"] == rung and r["budget"] == at}
        rl = by.get("rlsac")

        def cell(s: str, k: str, by: dict = by) -> str:
            return f"{by[s][k]:.3f}" if s in by else "–"
        lines.append(f"| {rung} | {why[rung]} | {rl['seeds'] if rl else 0} | {cell('uniform', 'pi_inliers')} | "
                     f"{cell('guided', 'pi_inliers')} | {cell('rlsac', 'pi_inliers')} | {cell('oracle', 'pi_inliers')}"
                     f" | {cell('uniform', 'mAA_R')} | {cell('guided', 'mAA_R')} | {cell('rlsac', 'mAA_R')} | "
                     f"{cell('oracle', 'mAA_R')} | {_ci(rl['d_uniform_R']) if rl else '–'} | "
                     f"{_ci(rl['d_guided_R']) if rl else '–'} |")
    lines += [""]
    for rung in order:
        if rung not in data:
            continue
        d = data[rung]
        lines += [f"## {rung}: {why[rung]}", "",
                  f"Test pairs: {d['controls']['uniform'][str(budgets[0])]['err_R'].size}; threshold "
                  f"{d['threshold']} (the task's residual unit); seeds done: "
                  f"{', '.join(map(str, sorted(d['runs']))) or 'none yet'}.", "",
                  "| budget | sampler | π(inliers) | mAA_R | mAA_t | RLSAC − it, π | RLSAC − it, mAA_R | "
                  "RLSAC − it, mAA_t |", "|" + " --- |" * 8]
        rl_rows = {r["budget"]: r for r in rows if r["rung"] == rung and r["sampler"] == "rlsac"}
        for r in rows:
            if r["rung"] != rung:
                continue
            name = "RLSAC (seed mean)" if r["sampler"] == "rlsac" else r["sampler"]
            rl = rl_rows.get(r["budget"])
            diffs = ["–"] * 3 if r["sampler"] == "rlsac" or rl is None else \
                [_ci(rl[f"d_{r['sampler']}_{k}"]) for k in ("pi", "R", "t")]
            lines.append(f"| {r['budget']} | {name} | {r['pi_inliers']:.3f} | {r['mAA_R']:.3f} | {r['mAA_t']:.3f} | "
                         + " | ".join(diffs) + " |")
        if rung.startswith(("control-", "entropy")) and d["runs"]:
            lines += ["", f"Convergence (curve on the test pairs at {c['curve_iterations']} hypotheses, every "
                      f"{c['every']} steps): the first step where π(inliers) is within {PI_CLOSE} of guided's and "
                      f"mAA_R within {MAA_CLOSE} of guided's; the peak π and the drift after it (last − peak).", "",
                      "| seed | π step | mAA_R step | peak π (step) | last π | drift | α at the peak → last |",
                      "|" + " --- |" * 7]
            for v in convergence(d, str(c["curve_iterations"])):
                lines.append(f"| {v['seed']} | {v['pi_step'] if v['pi_step'] is not None else 'not reached'} | "
                             f"{v['maa_step'] if v['maa_step'] is not None else 'not reached'} | {v['peak_pi']:.3f} "
                             f"({v['peak_step']}) | {v['last_pi']:.3f} | {v['drift']:+.3f} | "
                             + (f"{v['alpha_peak']:.4f} → {v['alpha_last']:.4f} |" if v["alpha_last"] is not None
                                else "– |"))
        lines += [""]
    return "\n".join(lines)


def figure(c: dict, data: dict[str, dict], order: list[str], why: dict[str, str], path: Path) -> None:
    """pi(inliers) and mAA_R against training steps, one panel per rung (each seed a thin line; the synthetic rungs'
    guided level, measured on the same pairs, dotted), one legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    have = [r for r in order if r in data and data[r]["runs"]]
    if not have:
        return
    cols = min(4, len(have))
    rows_n = math.ceil(len(have) / cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(max(3.6 * cols, 8.0), 3.2 * rows_n + 0.6), squeeze=False,
                             sharey=True)
    for ax, rung in zip(axes.ravel(), have, strict=False):
        d = data[rung]
        for seed, r in sorted(d["runs"].items()):
            st = [row["step"] for row in r["curve"]]
            ax.plot(st, [row["pi_inliers"] for row in r["curve"]], color="C0", lw=1, alpha=0.8,
                    label="RLSAC π(inliers)" if seed == min(d["runs"]) else None)
            ax.plot(st, [row["mAA_R"] for row in r["curve"]], color="C1", lw=1, ls="--", alpha=0.8,
                    label="RLSAC mAA_R" if seed == min(d["runs"]) else None)
        if rung.startswith(("control", "rung0", "rung1", "rung2", "entropy")):  # curve pairs = the controls' test pairs
            g = d["controls"]["guided"][str(c["curve_iterations"])]
            ax.axhline(float(g["pi_inliers"].mean()), color="C0", ls=":", lw=1, label="guided π(inliers)")
            ax.axhline(mAA(g["err_R"], LIMIT), color="C1", ls=":", lw=1, label="guided mAA_R")
        # the rung's name, then what it changes wrapped to the panel's width (long lines ran into the next panel)
        ax.set_title(f"{rung}\n" + "\n".join(textwrap.wrap(why[rung], 52)), fontsize=7.5)
        ax.set_xlabel("training step", fontsize=8)
        ax.set_ylim(0, 1.02)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(have):]:
        ax.set_visible(False)
    handles, labels = [], []
    for ax in axes.ravel():
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(f"Curves at {c['curve_iterations']} hypotheses (real rungs: on the fold's validation pairs)",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)


def build(params: dict, out_dir: Path = Path("reports"), root: Path = ROOT) -> dict[str, Any]:
    """Write reports/learner.md, learner.csv and learner_ladder.png from the ladder's records."""
    import pandas as pd

    from rlsac.layout.ladder_layout import conf, rungs

    c = conf(params)
    all_rungs = rungs(c)
    order, why = list(all_rungs), {k: v.why for k, v in all_rungs.items()}
    data = load(c, order, root, {k: v.controls for k, v in all_rungs.items()})
    rows = [row for rung in order if rung in data for row in rung_rows(rung, data[rung], [str(i) for i in
                                                                                         c["iterations"]])]
    flat = [{k: (v if not isinstance(v, tuple) else round(v[0], 4)) for k, v in r.items()} for r in rows]
    for r, f in zip(rows, flat, strict=True):
        for k, v in r.items():
            if isinstance(v, tuple):
                f[f"{k}_lo"], f[f"{k}_hi"] = round(v[1], 4), round(v[2], 4)
    md, csv, png = out_dir / "learner.md", out_dir / "learner.csv", out_dir / "learner_ladder.png"
    with atomic_path(md) as tmp:
        tmp.write_text(markdown(c, data, order, why, rows))
    with atomic_path(csv) as tmp:
        pd.DataFrame(flat).round(4).to_csv(tmp, index=False)
    figure(c, data, order, why, png)
    pending = [f"{r}/s{s}" for r in order for s in c["seeds"] if r not in data or s not in data[r]["runs"]]
    return {"files": [str(md), str(csv), str(png)], "missing": pending}
