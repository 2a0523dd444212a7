"""reports/selection.{md,csv}: checkpoint selection measured (issue #27, item 3), from the records of the
fold_select stages (rlsac.experiments.selection): <root>/<regime>/<fold>/<run>.json and .csv, one per training run.

For each model of folds.select_models, over its training seeds and the folds:
  * kept vs last: the actor the selection rule kept against the run's final actor, pooled over the folds, with a 95%
    interval that resamples training seeds (the same seeds for both: two checkpoints of one run) and test pairs within
    their building (rlsac.maths.metrics.seed_bootstrap_maa, paired_seeds);
  * the candidates: actors whose validation score lies within the record's tie of the kept one's (validation cannot
    tell them apart): their test spread (best - worst mAA of a run's candidates) and how often the kept one is the
    candidate with the best test mAA.
The CSV lists every run: kept, last and candidate steps, each validated actor's validation inlier ratio and test mAA.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rlsac.errors import RlsacError
from rlsac.evaluation.results import read_errors
from rlsac.io import atomic_path, write_text
from rlsac.layout.protocol import LIMIT, LINE_LIMIT_DEG, N_BOOT  # mAA@10 deg, Table 1's limit, the bootstrap's draws

METRICS = ("R", "t")


def _record(path: Path, need: set[str], keys: tuple[str, ...], errors: tuple[str, ...], what: str
            ) -> tuple[dict[str, Any], pd.DataFrame]:
    """A selection record ``path`` (.json) and its per-step errors (the .csv beside it, read by
    rlsac.evaluation.results: a
    NaN or text error is an error naming the file) -> (record, errors)."""
    from rlsac.evaluation.results import read_mapping

    csv = path.with_suffix(".csv")
    rec = read_mapping(path, "selection record")  # not JSON, not a mapping, a NaN anywhere: an error naming it
    if not need <= set(rec):
        raise RlsacError(f"{path}: not a {what}")
    if not csv.is_file():
        raise RlsacError(f"{path}: not a readable selection record (no {csv.name})")
    frame = read_errors(csv, errors, per_instance=False)
    if not set(keys) <= set(frame.columns):
        raise RlsacError(f"{path}: not a {what}")
    return rec, frame


def read_runs(root: str | Path) -> list[dict[str, Any]]:
    """Every run's record with its per-pair errors (``errors``: the CSV as a frame), sorted by regime, fold, run."""
    from rlsac.layout.protocol import split_seed

    out = []
    for path in sorted(Path(root).glob("*/*/*.json")):
        rec, errors = _record(path, {"regime", "fold", "model", "kept_step", "last_step", "steps", "candidates",
                                     "history", "iterations"}, ("step", "iterations"), ("err_R", "err_t"),
                              "selection record of rlsac.experiments.selection")
        base, seed = split_seed(rec["model"])
        out.append({**rec, "base": base, "seed": 0 if seed is None else seed, "errors": errors})
    return out


def _errors(run: dict[str, Any], step: int, it: int, col: str) -> np.ndarray:
    e = run["errors"]
    return e.loc[(e["step"] == step) & (e["iterations"] == it), col].to_numpy(np.float64)


def _accuracy(err: np.ndarray, limit: float = LIMIT) -> float:
    from rlsac.maths.metrics import mAA

    return float(mAA(err, limit))


def _tied(runs: list[dict[str, Any]], accuracy) -> tuple[list[float], int]:
    """Over the runs whose validation cannot tell several actors apart (more than one candidate): the test spread
    (best - worst ``accuracy(run, step)`` among the candidates) of each, and how many kept the best of them."""
    spread, kept_best = [], 0
    for r in runs:
        got = {s: accuracy(r, s) for s in r["candidates"]}
        if len(got) > 1:
            spread.append(max(got.values()) - min(got.values()))
            kept_best += got[r["kept_step"]] == max(got.values())
    return spread, kept_best


def run_table(runs: list[dict[str, Any]]) -> pd.DataFrame:
    """One row per (run, validated step): its validation inlier ratio and mAA, whether it is kept / last / a
    candidate, and its test mAA of R and t at every budget."""
    rows = []
    for r in sorted(runs, key=lambda r: (r["base"], r["seed"], r["regime"], r["fold"])):
        val = {int(h["step"]): h for h in r["history"]}
        for step in r["steps"]:
            row = {"model": r["base"], "seed": r["seed"], "regime": r["regime"], "fold": r["fold"], "step": step,
                   "kept": step == r["kept_step"], "last": step == r["last_step"],
                   "candidate": step in r["candidates"],
                   "val inlier ratio": round(float(val.get(step, {}).get("charts/val_inlier_ratio", np.nan)), 4),
                   "val mAA": round(float(val.get(step, {}).get("charts/val_mAA", np.nan)), 4)}
            for it in r["iterations"]:
                for m in METRICS:
                    row[f"test mAA_{m} @{it}"] = round(_accuracy(_errors(r, step, it, f"err_{m}")), 4)
            rows.append(row)
    return pd.DataFrame(rows)


def summary(runs: list[dict[str, Any]]) -> pd.DataFrame:
    """Per model and budget: kept vs last (seed-aware paired interval) and the candidates' test spread."""
    from rlsac.maths.metrics import seed_bootstrap_maa

    rows = []
    for base in sorted({r["base"] for r in runs}):
        mine = [r for r in runs if r["base"] == base]
        seeds = sorted({r["seed"] for r in mine})
        folds = sorted({r["fold"] for r in mine})
        complete = [s for s in seeds if {r["fold"] for r in mine if r["seed"] == s} == set(folds)]
        for it in sorted({i for r in mine for i in r["iterations"]}):
            for m in METRICS:
                col = f"err_{m}"
                row: dict[str, Any] = {"model": base, "iterations": it, "metric": f"mAA_{m}", "seeds": len(complete),
                                       "runs": len(mine),
                                       "kept = last": f"{sum(r['kept_step'] == r['last_step'] for r in mine)}"
                                                      f"/{len(mine)}"}
                kept, last, strata = [], [], None
                for s in complete:  # each seed's pairs of every fold, in one order
                    rs = sorted((r for r in mine if r["seed"] == s), key=lambda r: r["fold"])
                    per_run = [_errors(r, r["kept_step"], it, col) for r in rs]
                    kept.append(np.concatenate(per_run))
                    last.append(np.concatenate([_errors(r, r["last_step"], it, col) for r in rs]))
                    strata = np.concatenate([[r["fold"]] * len(e) for r, e in zip(rs, per_run, strict=True)])
                if complete:
                    st = seed_bootstrap_maa(np.stack(kept), np.stack(last), LIMIT, strata=strata, n_boot=N_BOOT,
                                            seed=0, paired_seeds=True)
                    row["kept (mean ± SD)"] = f"{st['mean_a']:.3f} ± {st['sd_a']:.3f}"
                    row["last (mean ± SD)"] = f"{st['mean_b']:.3f} ± {st['sd_b']:.3f}"
                    row["kept − last [95%]"] = f"{st['diff']:+.3f} [{st['lo']:+.3f}, {st['hi']:+.3f}]"
                spread, kept_best = _tied(mine, lambda r, s, it=it, col=col: _accuracy(_errors(r, s, it, col)))
                row["tied runs"] = len(spread)
                row["tied spread (mean / max)"] = f"{np.mean(spread):.3f} / {np.max(spread):.3f}" if spread else "–"
                row["kept best of tied"] = f"{kept_best}/{len(spread)}" if spread else "–"
                rows.append(row)
    return pd.DataFrame(rows)


HEAD = """# Checkpoint selection measured (issue #27, item 3)

Generated by `rlsac table` from reports/selection/ (stages `fold_select*`, rlsac.experiments.selection). A fold model's
training validates its actor every `val_every` steps on 40 validation pairs of its training buildings and keeps the one
with the best mean inlier ratio of the final hypotheses (the paper's unsupervised signal). The stages replay each
training run (same options and seed; each replay gave the kept actor bit for bit, or the stage would have failed) and
test every validated actor on the fold's test pairs, in the model regime, with the settings tuned for the kept actor.

* **kept − last**: the kept actor against the run's final one, mAA@10° pooled over the folds; `mean ± SD` over
  training seeds; the interval resamples the seeds (the same for both: two checkpoints of one run) and the test pairs
  within their building ({n_boot} draws). One unit of mAA is one test pair's accuracy over {pairs} pairs per seed.
* **tied**: runs where another validated actor's validation inlier ratio lies within the tie ({tie}) of the kept
  one's, so that validation cannot tell them apart; `spread`: best − worst test mAA among those actors, and how often
  the kept one is the best of them on test.
"""


RULES = {"inlier_ratio": "best validation inlier ratio (the paper's unsupervised signal)",
         "val_mAA": "best validation mAA (ground truth; not the paper's)", "last": "the final actor"}


def shipped(ckpt_root: str | Path) -> pd.DataFrame:
    """Every checkpoint under ``ckpt_root`` (training states left out): how its actor was kept -> one row each."""
    from rlsac.rl.checkpoint import kind_of, read

    rows = []
    for path in sorted(p for p in Path(ckpt_root).rglob("*.pt") if not p.name.endswith(".state.pt")):
        ck = read(path)
        hist = ck.get("history") or []
        rule = ck.get("selection")
        rows.append({"checkpoint": str(path), "kind": kind_of(ck), "kept by": RULES.get(rule, rule) if rule else
                     "not recorded (written before the checkpoint format kept it)", "kept step": ck.get("step"),
                     "validated steps": " ".join(str(h.get("step")) for h in hist) or "–"})
    return pd.DataFrame(rows)


def check_inputs(root: str | Path = "reports/selection", ckpt_root: str | Path | None = None) -> None:
    """Every file ``build`` reads, read once through its refusing reader: ``rlsac table`` calls it before its run
    (issue #64: a corrupt record or a truncated checkpoint failed inside the run, which ended FAILED)."""
    read_runs(root)
    read_line_runs(Path(root) / LINES)
    if ckpt_root is not None:
        shipped(ckpt_root)


def build(root: str | Path = "reports/selection", out_dir: str | Path = "reports",
          ckpt_root: str | Path | None = None) -> dict[str, Any]:
    """Write <out_dir>/selection.{md,csv} from the fold records under ``root`` and <out_dir>/selection_lines.csv from
    the line records under ``root``/lines (and, with ``ckpt_root``, how every shipped checkpoint was kept) ->
    {"files"} (none without records)."""
    runs, line_runs = read_runs(root), read_line_runs(Path(root) / LINES)
    if not runs and not line_runs:
        print(f"selection: no records under {root}; nothing written")
        return {"files": []}
    out_dir = Path(out_dir)
    md, files = "" if runs else "# Checkpoint selection measured (issue #27, item 3)\n", []
    if runs:
        per_run, summ = run_table(runs), summary(runs)
        models = {(r["base"], r["seed"]) for r in runs}
        pairs = sorted({int(sum(len(_errors(r, r["kept_step"], r["iterations"][0], "err_R")) for r in runs
                                if r["base"] == b and r["seed"] == s)) for b, s in models})
        ties = sorted({float(r.get("tie", np.nan)) for r in runs})
        md = (HEAD.format(n_boot=N_BOOT, pairs=" / ".join(map(str, pairs)), tie=" / ".join(f"{t:g}" for t in ties))
              + "\n## Kept vs last, and the actors validation cannot tell apart\n\n"
              + summ.to_markdown(index=False, disable_numparse=True)
              + "\n\n## Every run (reports/selection.csv)\n\n" + per_run.to_markdown(index=False, disable_numparse=True)
              + "\n")
        csv_path = out_dir / "selection.csv"
        with atomic_path(csv_path) as tmp:
            per_run.to_csv(tmp, index=False)
        files.append(str(csv_path))
    if line_runs:
        line_per_run, line_summ = line_run_table(line_runs), line_summary(line_runs)
        md += (LINE_HEAD.format(n_boot=N_BOOT, n=" / ".join(sorted({str(len(r["errors"]) // len(r["steps"]))
                                                                    for r in line_runs})),
                                tie=" / ".join(sorted({f"{r['tie']:g}" for r in line_runs})))
               + line_summ.to_markdown(index=False, disable_numparse=True)
               + "\n\n### Every line run (reports/selection_lines.csv)\n\n"
               + line_per_run.to_markdown(index=False, disable_numparse=True) + "\n")
        csv_path = out_dir / "selection_lines.csv"
        with atomic_path(csv_path) as tmp:
            line_per_run.to_csv(tmp, index=False)
        files.append(str(csv_path))
    ships = shipped(ckpt_root) if ckpt_root is not None else pd.DataFrame()
    if not ships.empty:
        md += ("\n## How every shipped checkpoint was kept\n\nFrom each file under " + f"`{ckpt_root}/`" + " (its "
               "`selection` and `step`, and the steps its training validated).\n\n"
               + ships.to_markdown(index=False, disable_numparse=True) + "\n")
    md_path = out_dir / "selection.md"
    write_text(md_path, md)
    return {"files": [str(md_path), *files]}


# ------------------------------------------------------------------------- the line models (Table 1; rlsac select)

LINES = "lines"  # <root>/lines/<run>.{json,csv}: the records of `rlsac select` on the line models

LINE_HEAD = """
## Line models (Table 1)

From the records of `rlsac select` (stages `select_lines_seed`, reports/selection/lines/): each run replays a line
model's training (its own options, data and seed; the kept actor came back bit for bit and gave the test mAA of its
committed evaluation, or the stage would have failed) and tests every validated actor on the rate's 1000 test
instances at Table 1's budget. The line models are kept by `train.line.selection`: validation mAA on 200 validation
instances (ground truth; not the paper's signal, which the *inlier-ratio pick* column shows: the actor the
validation inlier ratio would have kept).

* **kept − last**, **inlier-ratio pick − kept**: mAA@0.5° over the test instances; `mean ± SD` over training seeds;
  the interval resamples the seeds (the same for both: checkpoints of one run) and the instances ({n_boot} draws).
  One unit of mAA is one test instance's accuracy over {n} instances per seed.
* **tied**: runs where another validated actor's validation mAA lies within the tie ({tie}: one validation
  instance) of the kept one's; `spread`: best − worst test mAA among them, and how often the kept one is the best.

"""


def read_line_runs(root: str | Path) -> list[dict[str, Any]]:
    """Every `rlsac select` record under ``root`` with its per-instance errors (``errors``), sorted by data and seed."""
    out = []
    for path in sorted(Path(root).glob("*.json")):
        rec, errors = _record(path, {"data", "seed", "kept_step", "last_step", "steps", "candidates", "history",
                                     "inlier_ratio_step", "tie"}, ("step", "instance"), ("err_deg",),
                              "line selection record of rlsac select")
        out.append({**rec, "set": Path(rec["data"]).stem, "errors": errors})
    return sorted(out, key=lambda r: (r["set"], r["seed"]))


def _line_errors(run: dict[str, Any], step: int) -> np.ndarray:
    e = run["errors"]
    return e.loc[e["step"] == step].sort_values("instance")["err_deg"].to_numpy(np.float64)


def line_run_table(runs: list[dict[str, Any]]) -> pd.DataFrame:
    """One row per (line run, validated step): validation mAA and inlier ratio, kept / last / inlier-ratio pick /
    candidate, test mAA."""
    rows = []
    for r in runs:
        val = {int(h["step"]): h for h in r["history"]}
        for step in r["steps"]:
            rows.append({"data": r["set"], "seed": r["seed"], "step": step, "kept": step == r["kept_step"],
                         "last": step == r["last_step"], "inlier-ratio pick": step == r["inlier_ratio_step"],
                         "candidate": step in r["candidates"],
                         "val mAA": round(float(val.get(step, {}).get("charts/val_mAA", np.nan)), 4),
                         "val inlier ratio": round(float(val.get(step, {}).get("charts/val_inlier_ratio", np.nan)), 4),
                         "test mAA": round(_accuracy(_line_errors(r, step), LINE_LIMIT_DEG), 4)})
    return pd.DataFrame(rows)


def line_summary(runs: list[dict[str, Any]]) -> pd.DataFrame:
    """Per test set (outlier rate): kept vs last and the inlier-ratio pick vs kept over the seeds (seed-aware paired
    intervals), and the tied actors' test spread."""
    from rlsac.maths.metrics import seed_bootstrap_maa

    rows = []
    for name in sorted({r["set"] for r in runs}):
        mine = [r for r in runs if r["set"] == name]
        kept = np.stack([_line_errors(r, r["kept_step"]) for r in mine])
        last = np.stack([_line_errors(r, r["last_step"]) for r in mine])
        pick = np.stack([_line_errors(r, r["inlier_ratio_step"]) for r in mine])
        kl = seed_bootstrap_maa(kept, last, LINE_LIMIT_DEG, n_boot=N_BOOT, seed=0, paired_seeds=True)
        pk = seed_bootstrap_maa(pick, kept, LINE_LIMIT_DEG, n_boot=N_BOOT, seed=0, paired_seeds=True)
        spread, kept_best = _tied(mine, lambda r, s: _accuracy(_line_errors(r, s), LINE_LIMIT_DEG))
        rows.append({"data": name, "seeds": " ".join(str(r["seed"]) for r in mine),
                     "kept = last": f"{sum(r['kept_step'] == r['last_step'] for r in mine)}/{len(mine)}",
                     "kept (mean ± SD)": f"{kl['mean_a']:.3f} ± {kl['sd_a']:.3f}",
                     "last (mean ± SD)": f"{kl['mean_b']:.3f} ± {kl['sd_b']:.3f}",
                     "kept − last [95%]": f"{kl['diff']:+.3f} [{kl['lo']:+.3f}, {kl['hi']:+.3f}]",
                     "inlier-ratio pick = kept": f"{sum(r['inlier_ratio_step'] == r['kept_step'] for r in mine)}"
                                                f"/{len(mine)}",
                     "pick − kept [95%]": f"{pk['diff']:+.3f} [{pk['lo']:+.3f}, {pk['hi']:+.3f}]",
                     "tied runs": len(spread),
                     "tied spread (mean / max)": f"{np.mean(spread):.3f} / {np.max(spread):.3f}" if spread else "–",
                     "kept best of tied": f"{kept_best}/{len(spread)}" if spread else "–"})
    return pd.DataFrame(rows)
