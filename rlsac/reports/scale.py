"""reports/scale.md, scale.csv and scale_curve.png: the training-scale study (issue #46) from its result files.

Reads the study's evaluations (reports/eval/scale/<fold>/<arm>-s<seed>/step<k>/i<it>/), the controls' evaluations on
the same test pairs (reports/eval/folds/<regime>/<fold>/<control>/i<it>/), each run's validation curve (the history in
its kept checkpoint) and the learner's positive control (reports/positive_control.json); nothing is run here.
Comparisons are paired on the test pairs and resample training seeds as well as pairs
(rlsac.maths.metrics.seed_bootstrap_maa).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rlsac.errors import RlsacError
from rlsac.evaluation.results import read_errors
from rlsac.io import atomic_path
from rlsac.layout import scale_layout as lay
from rlsac.maths.metrics import mAA, seed_bootstrap_maa

CONTROLS = ("uniform", "guided")  # the sampler-free control and the hand-made SNN sampler (the tables' rows)
ARM_LABEL = {"fixed": "today's pairs (the record's episodes)", "redraw": "+ redraw from the pool and swap",
             "pretrain": "+ synthetic pretraining, then redraw's episodes",
             "prefilter": "redraw's episodes pre-filtered as at test (a ratio of the tuning grid per episode)"}
# what each arm adds to: the arm-against-arm table
BASE_ARM = {"redraw": "fixed", "pretrain": "redraw", "prefilter": "redraw"}
LIMIT = 10.0  # mAA@10 deg, Table 2's


def _errors(path: Path, keys: pd.Index | None) -> tuple[np.ndarray, np.ndarray, pd.Index]:
    """An evaluation folder's errors (rlsac.evaluation.results' refusing reader: finite, one row per counted pair) ->
    err_R, err_t and the pairs' keys, which must be ``keys`` where given (the same test pairs in the same order)."""
    df = read_errors(path / "errors.csv", ("err_R", "err_t"))
    if df is None or not {"scene", "pair"} <= set(df.columns):
        raise RlsacError(f"{path}: no errors.csv with the pairs' scene and pair columns")
    idx = pd.Index(df["scene"] + "/" + df["pair"])
    if keys is not None and not idx.equals(keys):
        raise RlsacError(f"{path}: not the same test pairs, in the same order, as the other evaluations")
    return df["err_R"].to_numpy(np.float64), df["err_t"].to_numpy(np.float64), idx


def _budgets(s: dict[str, Any]) -> list[int]:
    """Every budget of the study: the one every actor is tested at, and the last actor's (0 = none)."""
    return sorted({s["iterations"], s["final_iterations"]} - {0})


def collect(s: dict[str, Any], eval_root: Path = Path("reports/eval")) -> dict[str, Any]:
    """Every evaluation of the study and of its controls -> errors per (arm, step, budget) as (seeds, pairs)."""
    fold, regime = s["fold"], s["regime"]
    keys, strata, out, missing = None, None, {"runs": {}, "controls": {}}, []
    for it in _budgets(s):
        for c in CONTROLS:
            d = eval_root / "folds" / regime / fold / c / f"i{it}"
            if not (d / "errors.csv").is_file():
                missing.append(str(d))
                continue
            r, t, keys = _errors(d, keys)
            out["controls"][(c, it)] = (r[None], t[None])
            strata = np.array([k.split("/")[0] for k in keys])
        for arm in s["arms"]:
            for k in (lay.arm_steps(s, arm) if it == s["iterations"] else lay.arm_final_steps(s, arm)):
                rs, ts = [], []
                for seed in s["seeds"]:
                    d = Path(eval_root) / lay.eval_dir(fold, it, arm, seed, k).relative_to("reports/eval")
                    if not (d / "errors.csv").is_file():
                        missing.append(str(d))
                        continue
                    r, t, keys = _errors(d, keys)
                    rs.append(r)
                    ts.append(t)
                if rs:
                    out["runs"][(arm, k, it)] = (np.stack(rs), np.stack(ts))
    out["strata"], out["missing"] = strata, missing
    return out


def same_as_record(s: dict[str, Any], root: Path = Path(".")) -> str:
    """Whether the fixed arm's seed-0 actor at the record's length is the record's Table 2 model, tensor for tensor
    (it should be: same data, seed and code; the run only goes on longer)."""
    import torch

    record = root / "checkpoints" / "folds" / s["regime"] / s["fold"] / "rlsac.pt"
    if "fixed" not in s["arms"] or 0 not in s["seeds"] or not record.is_file():
        return ""
    rec = _checkpoint(record, "step", "actor")
    snap = root / lay.snapshot(s["fold"], "fixed", 0, int(rec["step"]))
    if not snap.is_file():
        return ""
    ours = _checkpoint(snap, "actor")["actor"]
    same = set(ours) == set(rec["actor"]) and all(torch.equal(ours[k], rec["actor"][k]) for k in ours)
    return (f" The fixed arm's seed-0 actor at step {rec['step']} {'is' if same else 'is NOT'} the record's Table 2 "
            f"model of this fold ({record}), tensor for tensor: the curve starts at the record.")


def _checkpoint(path: Path, *need: str) -> dict[str, Any]:
    """A checkpoint the report reads (rlsac.io.load_torch: a truncated or foreign file is an error naming it, issue
    #64's RuntimeError traceback), with the keys ``need`` (a whole ``step``, an ``actor`` of tensors) and a history
    of validations whose step is a whole number and whose metrics are finite numbers."""
    import torch

    from rlsac.io import load_torch

    ckpt = load_torch(path)
    if "step" in need and not (isinstance(ckpt.get("step"), int) and not isinstance(ckpt["step"], bool)):
        raise RlsacError(f"{path}: its 'step' is {ckpt.get('step')!r}, not a training step")
    if "actor" in need and not (isinstance(ckpt.get("actor"), dict)
                                and all(torch.is_tensor(v) for v in ckpt["actor"].values())):
        raise RlsacError(f"{path}: no actor weights ('actor' is not a mapping of tensors)")
    hist = ckpt.get("history", [])
    for i, h in enumerate(hist if isinstance(hist, list) else [None]):
        bad = (not isinstance(h, dict) or not isinstance(h.get("step"), int)
               or any(k.startswith("charts/") and not (isinstance(v, (int, float)) and not isinstance(v, bool)
                                                       and math.isfinite(v)) for k, v in h.items()))
        if bad:
            raise RlsacError(f"{path}: history[{i}] is not a validation (a whole step, finite metrics): "
                             f"{str(h)[:80]}")
    return ckpt


def validation_curves(s: dict[str, Any], root: Path = Path(".")) -> pd.DataFrame:
    """Each run's validation history (its kept checkpoint's): one row per (arm, seed, step)."""
    rows = []
    for arm in s["arms"]:
        for seed in s["seeds"]:
            path = root / lay.run_dir(s["fold"], arm, seed) / "final.pt"
            if not path.is_file():
                continue
            for h in _checkpoint(path).get("history", []):
                rows.append({"arm": arm, "seed": seed, "step": int(h["step"]),
                             "val_mAA": float(h.get("charts/val_mAA", math.nan)),
                             "val_inlier_ratio": float(h.get("charts/val_inlier_ratio", math.nan))})
    return pd.DataFrame(rows)


def seed_sd(values: list[float]) -> float:
    """The sample sd of the seeds' values (ddof=1, as the other reports); 0 for one seed."""
    return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def comparisons(s: dict[str, Any], got: dict[str, Any]) -> pd.DataFrame:
    """RLSAC (seeds) - each control per (arm, step, budget), R and t, with seed-aware intervals."""
    rows = []
    for (arm, k, it), (r, t) in sorted(got["runs"].items()):
        row = {"arm": arm, "step": k, "iterations": it, "seeds": r.shape[0],
               "mAA_R": float(np.mean([mAA(x, LIMIT) for x in r])), "mAA_t": float(np.mean([mAA(x, LIMIT) for x in t])),
               # the seed sd with ddof=1, as every other report's (rlsac.maths.metrics.seed_bootstrap_maa); 0 for one
               # seed
               "sd_R": seed_sd([mAA(x, LIMIT) for x in r]), "sd_t": seed_sd([mAA(x, LIMIT) for x in t])}
        for c in CONTROLS:
            if (c, it) not in got["controls"]:
                continue
            cr, ct = got["controls"][(c, it)]
            row[f"{c}_R"], row[f"{c}_t"] = mAA(cr[0], LIMIT), mAA(ct[0], LIMIT)
            for m, a, b in (("R", r, cr), ("t", t, ct)):
                d = seed_bootstrap_maa(a, b, LIMIT, strata=got["strata"])
                row[f"vs_{c}_{m}"], row[f"vs_{c}_{m}_lo"], row[f"vs_{c}_{m}_hi"] = d["diff"], d["lo"], d["hi"]
        base = got["runs"].get((BASE_ARM.get(arm), k, it))
        if base is not None:  # the arm against the one it adds to: different runs, so the seeds are not paired
            for m, a, b in (("R", r, base[0]), ("t", t, base[1])):
                d = seed_bootstrap_maa(a, b, LIMIT, strata=got["strata"])
                row[f"vs_base_{m}"], row[f"vs_base_{m}_lo"], row[f"vs_base_{m}_hi"] = d["diff"], d["lo"], d["hi"]
        rows.append(row)
    return pd.DataFrame(rows)


def deployed_validation(s: dict[str, Any], eval_root: Path = Path("reports/eval")) -> pd.DataFrame:
    """Every kept actor on the fold's validation pairs with the test's settings (stage scale_validate): one row per
    (arm, seed, step) with its mAA (the tuning's criterion: mAA@10 deg of max(err_R, err_t)); ``attrs["missing"]``
    the folders not there yet."""
    rows, keys, missing = [], None, []
    for arm in s["arms"]:
        for seed in s["seeds"]:
            for k in lay.arm_steps(s, arm):
                d = Path(eval_root) / lay.val_dir(s["fold"], s["iterations"], arm, seed, k).relative_to("reports/eval")
                if not (d / "errors.csv").is_file():
                    missing.append(str(d))
                    continue
                r, t, keys = _errors(d, keys)  # the same validation pairs for every actor
                rows.append({"arm": arm, "seed": seed, "step": k, "val_mAA": mAA(np.fmax(r, t), LIMIT)})
    out = pd.DataFrame(rows, columns=["arm", "seed", "step", "val_mAA"])
    out.attrs["missing"] = missing
    return out


def choose(s: dict[str, Any], curves: pd.DataFrame, deployed: pd.DataFrame | None = None) -> dict[str, Any] | None:
    """The recipe to carry forward, on validation only: the (arm, step) of the best seed-mean validation mAA, at the
    test's settings (``deployed``) where every kept actor has been validated so, else the training's own validation
    (its reward threshold, no pre-filter)."""
    full = deployed is not None and not deployed.empty and not deployed.attrs.get("missing")
    src, basis = (deployed, "test settings") if full else (curves, "training validation")
    if src.empty:
        return None
    at = src[src["step"].isin(s["steps"])].groupby(["arm", "step"])["val_mAA"].mean()
    if at.empty:
        return None
    (arm, step), best = at.idxmax(), float(at.max())
    return {"arm": arm, "step": int(step), "val_mAA": best, "table": at.reset_index(), "basis": basis}


def _section(path: Path, what: str, render) -> list[str]:
    """``render`` (the JSON mapping in ``path``) -> lines; [] when the file is absent. A corrupt file is one error
    naming it (issue #49: a JSONDecodeError or KeyError traceback)."""
    from rlsac.evaluation.results import read_mapping

    d = read_mapping(path, what)
    if d is None:
        return []
    try:
        return render(d)
    except (KeyError, TypeError, ValueError, IndexError, StopIteration, AttributeError) as e:
        raise RlsacError(f"{path}: not a {what} ({e.__class__.__name__}: {' '.join(str(e).split())[:80]}); re-run "
                         "the stage that wrote it") from None


def check_inputs(params: dict[str, Any], out_dir: str | Path = "reports", eval_root: str | Path = "reports/eval",
                 root: str | Path = ".") -> None:
    """Every file the report reads, read once through its refusing reader: ``rlsac table --which scale`` calls it
    before its run (issue #64: a NaN, truncated or corrupt input failed inside the run, which ended FAILED): the
    records its sections render, the evaluations' errors, the runs' checkpoints."""
    s, out_dir = lay.protocol(params), Path(out_dir)
    _pairs_line(s, out_dir)
    _section(out_dir / "positive_control.json", "positive control record", _positive_control)
    _synthetic_fit(out_dir / "synthetic_fit.json")
    collect(s, Path(eval_root))
    deployed_validation(s, Path(eval_root))
    validation_curves(s, Path(root))
    same_as_record(s, Path(root))


def _pairs_line(s: dict, out_dir: Path, min_matches: int | None = None) -> str:
    """How many training pairs the fold has: its data record (rlsac folds --stage data)."""
    def render(rec: dict) -> list[str]:
        splits = rec["splits"]
        return [f" The fold's training buildings give {splits['train']['pairs']} training and "
                f"{splits['val']['pairs']} validation pairs: every pair the import keeps (at least {min_matches} SNN < "
                "0.8 matches), so more real pairs cannot come from these buildings; the pool multiplies the inputs per "
                "pair, not the pairs."]

    return "".join(_section(out_dir / "folds" / "data" / s["regime"] / f"{s['fold']}.json", "data record", render))


def _cell(row, key: str) -> str:
    if f"{key}_lo" not in row or pd.isna(row.get(key)):
        return "–"
    return f"{row[key]:+.3f} [{row[key + '_lo']:+.3f}, {row[key + '_hi']:+.3f}]"


def build(params: dict[str, Any], eval_root: str | Path = "reports/eval", out_dir: str | Path = "reports",
          root: str | Path = ".") -> dict[str, Any]:
    s = lay.protocol(params)
    out_dir = Path(out_dir)
    got = collect(s, Path(eval_root))
    comp = comparisons(s, got)
    curves = validation_curves(s, Path(root))
    deployed = deployed_validation(s, Path(eval_root))
    got["missing"] += deployed.attrs.get("missing", [])
    chosen = choose(s, curves, deployed)
    files = [str(out_dir / "scale.md"), str(out_dir / "scale.csv")]
    with atomic_path(files[1]) as tmp:
        comp.round(6).to_csv(tmp, index=False)
    with atomic_path(files[0]) as tmp:
        tmp.write_text(markdown(s, comp, curves, chosen, got["missing"], Path(out_dir), same_as_record(s, Path(root)),
                                (params.get("fundamental") or {}).get("min_matches"), deployed))
    files += figure(s, comp, out_dir)  # beside scale.md: reports/figures/ is the figures stage's own output
    return {"files": files, "missing": got["missing"]}


def markdown(s: dict, comp: pd.DataFrame, curves: pd.DataFrame, chosen: dict | None, missing: list[str],
             out_dir: Path, record_line: str = "", min_matches: int | None = None,
             deployed: pd.DataFrame | None = None) -> str:
    arms = ", ".join(f"`{a}` = {ARM_LABEL[a]}" for a in s["arms"])
    lines = [
        "# Is RLSAC starved? The training-scale study (issue #46)", "",
        "Generated by `rlsac table --which scale` (stage `scale_report`) from the study's evaluations; the study is "
        "`rlsac scale` (stages `scale_pool`, `scale_synthetic`, `scale_train`, `scale_validate`, `scale_eval`).", "",
        f"**Protocol.** Fold `{s['fold']}` of the leave-one-building-out benchmark, {s['regime']} regime (the "
        "building's test pairs, never seen before the evaluation). The fold recipe of Table 2's RLSAC "
        "(`folds.train.rlsac`: 16 episodes per step, one SAC update of 32 transitions per step after the first 300 "
        "transitions) run to "
        f"{max(s['steps'])} steps, its actor kept at steps {', '.join(map(str, s['steps']))} (with a constant learning "
        "rate, the actor after k steps is that of a k-step run)" + _legs_line(s) + "; training seeds "
        f"{', '.join(map(str, s['seeds']))}. Arms: {arms}. Every actor is tested with the inlier threshold and SNN "
        f"pre-filter tuned on the fold's validation pairs for the `{s['settings_from']}` control: checkpoints now "
        "carry the residual scale the policy was trained with (`state_scales`), so the evaluation threshold no longer "
        "changes what the policy sees, and one tuned setting scores sampler and control alike (RLSAC − uniform is the "
        "sampler alone). Intervals: 95%, resampling training seeds, then the test pairs within each scene "
        "(`rlsac.maths.metrics.seed_bootstrap_maa`).", "",
        "**Scale against the paper's.** The paper trains 100 epochs on 12 scenes of about 100k pairs each (about 10^8 "
        "pair-episodes). The record's fold recipe is 300 steps x 16 episodes (4,800 episodes, about 280 updates) on "
        "the fold's training pairs; this study goes to " + f"{max(s['steps']) // min(s['steps'])}x the steps and, "
        "in the redraw arm, gives every episode a fresh draw of 150 of a pair's 1000 lowest-SNN matches with the "
        "images swapped at random, so an input "
        "essentially never repeats." + _pretrain_line(s) + _pairs_line(s, out_dir, min_matches) + record_line, ""]
    if not comp.empty:
        lines += ["## Test pairs: RLSAC against the controls", "",
                  "| arm | steps | budget | RLSAC mAA_R | RLSAC mAA_t | − uniform R | − uniform t | − guided R | "
                  "− guided t |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for _, r in comp.iterrows():
            lines.append(f"| {r['arm']} | {r['step']} | {r['iterations']} | {r['mAA_R']:.3f} ± {r['sd_R']:.3f} | "
                         f"{r['mAA_t']:.3f} ± {r['sd_t']:.3f} | {_cell(r, 'vs_uniform_R')} | "
                         f"{_cell(r, 'vs_uniform_t')} | {_cell(r, 'vs_guided_R')} | {_cell(r, 'vs_guided_t')} |")
        ctrl = comp.drop_duplicates("iterations")
        lines += ["", "Controls (same test pairs, each with its own validation-tuned settings): " + "; ".join(
            f"{int(r['iterations'])} hypotheses: uniform R {r.get('uniform_R', math.nan):.3f} / t "
            f"{r.get('uniform_t', math.nan):.3f}, guided R {r.get('guided_R', math.nan):.3f} / t "
            f"{r.get('guided_t', math.nan):.3f}" for _, r in ctrl.iterrows()) + ". RLSAC: seed mean ± seed sd.", ""]
    if not comp.empty and "vs_base_R" in comp:
        lines += ["## Each arm against the one it adds to (test pairs)", "",
                  "| arm | − arm | steps | budget | Δ mAA_R | Δ mAA_t |", "| --- | --- | --- | --- | --- | --- |"]
        for _, r in comp[comp["vs_base_R"].notna()].iterrows():
            lines.append(f"| {r['arm']} | {BASE_ARM[r['arm']]} | {r['step']} | {r['iterations']} | "
                         f"{_cell(r, 'vs_base_R')} | {_cell(r, 'vs_base_t')} |")
        lines += ["", "Same test pairs; the two arms' runs are different runs, so seeds are resampled independently.",
                  ""]
    dep = deployed if deployed is not None else pd.DataFrame(columns=["arm", "seed", "step", "val_mAA"])
    if not curves.empty or not dep.empty:
        lines += ["## Validation (the fold's validation pairs; what chooses the recipe)", "",
                  "The training's own validation (its reward threshold, no pre-filter), and every kept actor again at "
                  f"the test's settings (the `{s['settings_from']}` control's tuned threshold and pre-filter, "
                  f"{s['iterations']} hypotheses, mAA of max(err_R, err_t) as the tuning scores; stage "
                  "`scale_validate`): the second chooses where it is complete.", "",
                  "| arm | step | val mAA, training (seed mean) | val inlier ratio (seed mean) | "
                  "val mAA, test settings (seed mean) |", "| --- | --- | --- | --- | --- |"]
        cols = ["arm", "step", "val_mAA", "val_inlier_ratio"]
        g = (curves.groupby(["arm", "step"])[cols[2:]].mean().reset_index() if not curves.empty
             else pd.DataFrame(columns=cols))
        d = dep.groupby(["arm", "step"])["val_mAA"].mean().rename("deployed").reset_index()
        g = g.merge(d, on=["arm", "step"], how="outer") if not d.empty else g.assign(deployed=math.nan)
        g = g[g["step"].isin(s["steps"])].sort_values(["arm", "step"], key=lambda c: c.map(
            {a: i for i, a in enumerate(s["arms"])}) if c.name == "arm" else c)
        num = lambda v: "–" if pd.isna(v) else f"{v:.3f}"  # noqa: E731
        for _, r in g.iterrows():
            lines.append(f"| {r['arm']} | {int(r['step'])} | {num(r['val_mAA'])} | {num(r['val_inlier_ratio'])} | "
                         f"{num(r['deployed'])} |")
        if chosen is not None:
            t = chosen["table"].sort_values("val_mAA", ascending=False)
            nxt = (f"; the next best, arm `{t.iloc[1]['arm']}` at {int(t.iloc[1]['step'])} steps, "
                   f"{t.iloc[1]['val_mAA']:.3f}; every cell lies within {t['val_mAA'].min():.3f}-"
                   f"{t['val_mAA'].max():.3f}" if len(t) > 1 else "")
            lines += ["", f"Chosen on validation (best seed-mean validation mAA, {chosen['basis']}): arm "
                          f"`{chosen['arm']}` at {chosen['step']} steps (val mAA {chosen['val_mAA']:.3f}{nxt}).", ""]
    if not comp.empty:
        lines += _verdict(comp)
    lines += _section(out_dir / "positive_control.json", "positive control record", _positive_control)
    lines += _synthetic_fit(out_dir / "synthetic_fit.json")
    lines += _gpu_line()
    lines += ["## Figure", "", "![mAA against training steps](scale_curve.png)", ""]
    if missing:
        lines += [f"Not yet run ({len(missing)} evaluation folders absent): " + ", ".join(sorted(missing)[:6])
                  + (" ..." if len(missing) > 6 else ""), ""]
    return "\n".join(lines)


def _legs_line(s: dict) -> str:
    stops = "".join(f"; arm `{a}` stops at {k} steps (scale.arm_steps)" for a, k in s["arm_steps"].items()
                    if k < s["steps"][-1])
    if len(s["legs"]) < 2:
        return stops
    return stops + (f"; the runs go in legs ending at steps {', '.join(map(str, s['legs']))}: each leg resumes the "
                     "last one's saved state (agent, optimisers, replay buffer, generator) and starts new episodes at "
                     "its first step (scale.legs)")


def _pretrain_line(s: dict) -> str:
    if "pretrain" not in s["arms"]:
        return ""
    pre = s["pretrain"]
    return (f" The pretrain arm first trains {pre['steps']} steps on {pre['pairs']} synthetic pairs drawn with the "
            "statistics fitted to the fold's training pairs (below; each episode a pair's points, the images swapped "
            "at random, validated on the fold's validation pairs), then the redraw arm's recipe from those networks "
            "with fresh optimisers and an empty replay buffer (`train.init`); its steps count the real pairs' steps "
            f"only (so each of its points has {pre['steps']} more updates than the other arms' at the same step).")


def _synthetic_fit(path: Path) -> list[str]:
    """The synthetic generator's fitted statistics beside the real ones (stage synthetic_fit)."""
    return _section(path, "synthetic fit record", _synthetic_rows)


def _synthetic_rows(d: dict) -> list[str]:
    rows = ["## The synthetic generator, fitted to the fold's training pairs (stage synthetic_fit, "
            "reports/synthetic_fit.json)", "",
            "The pretrain arm's pairs (stage scale_synthetic): `rlsac.data.synthetic_pairs` with `snn=\"fitted\"` "
            "draws each "
            "pair's inlier ratio, the SNN ratio of inliers and of outliers, and the outliers' image positions from "
            f"what the {d['real']['pairs']} training pairs of fold `{d['fold']}` ({d['regime']} regime, inliers by "
            "the training reward's threshold) show; the inliers' positions come from a random scene's geometry, and "
            f"the descriptor channels are noise. Measured the same way on {d['synthetic']['pairs']} synthetic pairs:",
            "",
            "| statistic | real | synthetic |", "| --- | --- | --- |"]
    rows += [f"| {r['statistic']} | {r['real']:.3f} | {r['synthetic']:.3f} |" for r in d["comparison"]]
    return rows + [""]


def _gpu_line() -> list[str]:
    """Where the update's cost is measured and what a GPU would add (no timing here: a benchmark's, not a stage's)."""
    return ["## What a GPU would add", "",
            "The runs use the record's products on one CPU core each. docs/speed.md gives the SAC update's cost and "
            "the faster products' (benchmarks/sac_update.py, reports/speed_training.json), short of the 5x the issue "
            "asks; reports/device.md measured the fundamental-matrix recipe's training several times faster on a GPU "
            "than on one CPU core, which would bring the 30k point, longer pretraining and a four-fold, five-seed row "
            "at this scale within a session. No GPU was lent to the session that made this study.", ""]


def _where(lo: float, hi: float) -> str:
    return "above" if lo > 0 else "below" if hi < 0 else "not distinguishable from"


def _verdict(comp: pd.DataFrame) -> list[str]:
    """What the curve says, in words computed from the numbers above: the change from the first to the last step and
    where the last step stands against each control."""
    out = ["## What the curve says", ""]
    for (arm, it), g in comp.groupby(["arm", "iterations"]):
        g = g.sort_values("step")
        a, b = g.iloc[0], g.iloc[-1]
        parts = [f"**{arm}, {it} hypotheses:** from {a['step']} to {b['step']} steps RLSAC's mAA_R moves "
                 f"{b['mAA_R'] - a['mAA_R']:+.3f} and mAA_t {b['mAA_t'] - a['mAA_t']:+.3f} (seed means)"
                 if len(g) > 1 else f"**{arm}, {it} hypotheses** (the last actor only)"]
        for c in CONTROLS:
            if f"vs_{c}_R_lo" in b and not pd.isna(b[f"vs_{c}_R_lo"]):
                parts.append(f"at {b['step']} steps it is {_where(b[f'vs_{c}_R_lo'], b[f'vs_{c}_R_hi'])} {c} in R "
                             f"({b[f'vs_{c}_R']:+.3f} [{b[f'vs_{c}_R_lo']:+.3f}, {b[f'vs_{c}_R_hi']:+.3f}]) and "
                             f"{_where(b[f'vs_{c}_t_lo'], b[f'vs_{c}_t_hi'])} it in t ({b[f'vs_{c}_t']:+.3f} "
                             f"[{b[f'vs_{c}_t_lo']:+.3f}, {b[f'vs_{c}_t_hi']:+.3f}])")
        out += ["; ".join(parts) + ".", ""]
    return out


def _positive_control(pc: dict) -> list[str]:
    rows = ["## The learner's positive control (stage positive_control, reports/positive_control.md)", "",
            "Synthetic pairs whose SNN channel separates the true inliers by construction; π(inliers) is the policy's "
            "probability mass on them at its first step.", "", "| sampler | π(inliers) | mAA_R | mAA_t |",
            "| --- | --- | --- | --- |"]
    for r in pc["results"]:
        for name, v in r["controls"].items():
            rows.append(f"| {name}, inlier ratio {r['inlier_ratio']} | {v['pi_inliers']:.3f} | {v['mAA_R']:.3f} | "
                        f"{v['mAA_t']:.3f} |")
        last = [c["rows"][-1] for c in r["curves"]]
        mean = {k: float(np.mean([x[k] for x in last])) for k in ("pi_inliers", "mAA_R", "mAA_t")}
        rows.append(f"| **RLSAC after {last[0]['step']} steps ({last[0]['updates']} updates), inlier ratio "
                    f"{r['inlier_ratio']}** ({len(last)} seeds, mean) | {mean['pi_inliers']:.3f} | {mean['mAA_R']:.3f} "
                    f"| {mean['mAA_t']:.3f} |")
    rows.append("")
    for r in pc["results"]:
        rows.append(_reached(r))
    return rows + [""]


def _reached(r: dict) -> str:
    """When the seed-mean policy mass on the inliers first comes within 0.05 of the guided sampler's, in words."""
    guided = next(v["pi_inliers"] for k, v in r["controls"].items() if k.startswith("guided"))
    n = len(r["curves"][0]["rows"])
    for i in range(n):
        pi = float(np.mean([c["rows"][i]["pi_inliers"] for c in r["curves"]]))
        if pi >= guided - 0.05:
            row = r["curves"][0]["rows"][i]
            return (f"- Inlier ratio {r['inlier_ratio']}: the policy's mass on the inliers reaches the guided "
                    f"sampler's ({guided:.3f}) within 0.05 at step {row['step']} (about {row['updates']} updates): "
                    "the learner finds the separating input when uniform sets succeed often enough to show it.")
    last = r["curves"][0]["rows"][-1]
    pi = float(np.mean([c["rows"][-1]["pi_inliers"] for c in r["curves"]]))
    return (f"- Inlier ratio {r['inlier_ratio']}: after {last['step']} steps (about {last['updates']} updates) the "
            f"policy's mass on the inliers is {pi:.3f} against the guided sampler's {guided:.3f} and uniform's "
            f"{r['inlier_ratio']}. Not a plateau: this run stops early on its curve; run to 3000 steps (the ladder's "
            "control rungs, reports/learner.md) the same learner reaches the guided sampler at every inlier ratio.")


def figure(s: dict, comp: pd.DataFrame, out_dir: Path) -> list[str]:
    """scale_curve.{png,pdf}: mAA against training steps per arm (a band over seeds), the controls as lines."""
    import matplotlib.pyplot as plt

    from rlsac.reports.figfile import save

    its = _budgets(s)
    fig, axes = plt.subplots(len(its), 2, figsize=(10, 3.6 * len(its)), squeeze=False)
    colours = {"fixed": "tab:blue", "redraw": "tab:orange", "pretrain": "tab:green", "prefilter": "tab:purple"}
    for i, it in enumerate(its):
        for j, m in enumerate(("R", "t")):
            ax = axes[i][j]
            sub = comp[comp["iterations"] == it] if not comp.empty else comp
            for arm in s["arms"]:
                a = sub[sub["arm"] == arm].sort_values("step") if not sub.empty else sub
                if a.empty:
                    continue
                y, sd = a[f"mAA_{m}"].to_numpy(), a[f"sd_{m}"].to_numpy()
                extra = f" (+{s['pretrain']['steps']} synthetic steps first)" if arm == "pretrain" else ""
                ax.plot(a["step"], y, "o-", color=colours[arm], label=f"RLSAC, {arm}{extra}")
                ax.fill_between(a["step"], y - sd, y + sd, color=colours[arm], alpha=0.2)
            if not sub.empty:
                for c, style in zip(CONTROLS, ("--", ":"), strict=True):
                    if f"{c}_{m}" in sub:
                        ax.axhline(float(sub[f"{c}_{m}"].iloc[0]), color="black", ls=style, label=c)
            ax.set_xscale("log")
            ax.set_xticks(s["steps"], [str(k) for k in s["steps"]])
            ax.minorticks_off()
            ax.set_xlabel("training steps (16 episodes + one SAC update each; log scale)")
            ax.set_ylabel(f"mAA@10° {m}")
            ax.set_title(f"{s['fold']}, {it} hypotheses: mAA {m}")
    handles, labels = {}, []
    for ax in axes.flat:  # one legend for every panel, below them: in a panel it hides points
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in handles:
                handles[lab] = h
                labels.append(lab)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    if labels:
        fig.legend([handles[lab] for lab in labels], labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    return save(fig, out_dir, "scale_curve", dpi=110)
