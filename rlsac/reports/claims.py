"""reports/claims.md: every claim the README and reports/folds.md make about RLSAC on the fold benchmarks, each
checked against the results with an interval that covers training seeds where the model has several (issue #27).

The sentences are ours (``CLAIMS``); every number and verdict is computed here from reports/eval:
    <eval_root>/<folds|essential>/<regime>/<fold>/<row>/i<iterations>/errors.csv
A model with rows of other training seeds (<model>-s<seed>, params.yaml folds.seeds) is taken over all its seeds
(rlsac.metrics.seed_bootstrap_maa: seeds, then pairs within their test building); a model with one seed gets the
same bootstrap over pairs only, and the table says so (its verdict cannot speak for training noise).

Verdicts, per metric (mAA@10° of R and of t), from the 95% interval of model − control:
    better   supported: above 0; not supported: below 0; else inconclusive
    worse    supported: below 0; not supported: above 0; else inconclusive
    tie      supported: inside ±TIE_MARGIN (practically equal, even where it excludes 0); not supported:
             excludes 0 and reaches beyond the margin; else inconclusive
A claim is supported when each of its metrics is, not supported when one is not, inconclusive otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from rlsac.io import atomic_path, write_text

# a tie: the whole interval within ±0.03 mAA (18 of the 606 fold test pairs; the paper's Table 3 steps are 0.02-0.06)
TIE_MARGIN = 0.03
KINDS = ("better", "worse", "tie")


@dataclass(frozen=True)
class Claim:
    text: str  # the claim as the README / reports say it
    where: str  # the document that makes it
    sub: str  # folds (Table 2 / 3) | essential (Table E)
    regime: str
    iterations: int
    model: str  # the row the claim is about (its other training seeds are found by name)
    control: str  # the row it is set against
    kind: str  # better | worse | tie (of model against control)
    metrics: tuple[str, ...] = ("R", "t")


CLAIMS: tuple[Claim, ...] = (
    Claim("RLSAC does not beat uniform minimal sets in the same environment (hard regime, 1k iterations)",
          "README, reports/folds.md", "folds", "hard", 1000, "rlsac", "uniform", "tie"),
    Claim("RLSAC ties uniform sets at 100 iterations (hard regime)", "README", "folds", "hard", 100, "rlsac",
          "uniform", "tie"),
    Claim("RLSAC is below uniform sets in the easy regime at 100 iterations", "README", "folds", "easy", 100,
          "rlsac", "uniform", "worse"),
    Claim("RLSAC adds nothing over drawing sets by SNN ratio (guided, hard, 1k)", "reports/folds.md", "folds",
          "hard", 1000, "rlsac", "guided", "tie"),
    Claim("RLSAC is below the SNN-guided sampler at 100 iterations (hard)", "reports/folds.md", "folds", "hard",
          100, "rlsac", "guided", "worse"),
    Claim("OpenCV's PROSAC (as it ships) is ahead of RLSAC (hard, 1k)", "README", "folds", "hard", 1000, "rlsac",
          "prosac", "worse"),
    Claim("OpenCV's MAGSAC++ without LO or polisher is ahead of RLSAC in R (hard, 1k)", "README", "folds", "hard",
          1000, "rlsac", "magsac-nolo", "worse", ("R",)),
    Claim("PoseLib is ahead of RLSAC (hard, 1k)", "README", "folds", "hard", 1000, "rlsac", "poselib", "worse"),
    Claim("With the same LO after every sampler, RLSAC-LO ties uniform-LO (hard, 1k)", "README", "folds", "hard",
          1000, "rlsac-lo", "uniform-lo", "tie"),
    Claim("Table 3 (a): the model without descriptors is above the full model in R (hard, 1k)", "README", "folds",
          "hard", 1000, "rlsac-nodesc", "rlsac", "better", ("R",)),
    Claim("Table 3 (b): max sampling in training loses in t (hard, 1k)", "README", "folds", "hard", 1000,
          "rlsac-trainmax", "rlsac", "worse", ("t",)),
    Claim("At small budgets RLSAC is above uniform sets in R (hard regime, 20 iterations)", "README, reports/folds.md",
          "folds", "hard", 20, "rlsac", "uniform", "better", ("R",)),
    Claim("Table 3 (c): with N = 300 correspondences RLSAC is above the full model (N = 150) in R (hard, 1k)",
          "README, reports/folds.md", "folds", "hard", 1000, "rlsac-n300", "rlsac", "better", ("R",)),
    Claim("Table 3 (c): with N = 300 the policy is below uniform sets on the same points in t (hard, 1k)",
          "README, reports/folds.md", "folds", "hard", 1000, "rlsac-n300", "uniform-n300", "worse", ("t",)),
    Claim("Table E: RLSAC is above the uniform control in R (essential matrix, 1k)", "README", "essential", "hard",
          1000, "rlsac", "uniform", "better", ("R",)),
    Claim("Table E: RLSAC is below OpenCV's PROSAC (essential matrix, 1k)", "README", "essential", "hard", 1000,
          "rlsac", "prosac", "worse"),
)


def verdict(kind: str, lo: float, hi: float) -> str:
    """One metric's verdict from the 95% interval [lo, hi] of model − control (see the module's docstring)."""
    if kind not in KINDS:
        raise ValueError(f"claim kind must be one of {KINDS}, got {kind!r}")
    if kind == "better":
        return "supported" if lo > 0 else "not supported" if hi < 0 else "inconclusive"
    if kind == "worse":
        return "supported" if hi < 0 else "not supported" if lo > 0 else "inconclusive"
    if lo > -TIE_MARGIN and hi < TIE_MARGIN:
        return "supported"
    return "not supported" if lo > 0 or hi < 0 else "inconclusive"


def combine(verdicts: list[str]) -> str:
    if verdicts and all(v == "supported" for v in verdicts):
        return "supported"
    return "not supported" if "not supported" in verdicts else "inconclusive"


def check(claim: Claim, res: dict[tuple[str, str, int], pd.DataFrame]) -> dict[str, Any] | None:
    """The claim against ``res`` (rlsac.reports.folds.collect of its benchmark) -> a row of claims.md, or None when
    its rows are missing."""
    from rlsac.metrics import seed_bootstrap_maa
    from rlsac.reports.folds import LIMIT, N_BOOT, _aligned, seed_runs

    runs = seed_runs(res, claim.regime).get(claim.model, [claim.model])
    frames = [res.get((claim.regime, m, claim.iterations)) for m in runs]
    control = res.get((claim.regime, claim.control, claim.iterations))
    if control is None or any(f is None for f in frames):
        return None
    row: dict[str, Any] = {"claim": claim.text, "where": claim.where, "kind": claim.kind,
                           "seeds": len(runs), "rows": f"{claim.model} − {claim.control}"}
    verdicts = []
    for name in claim.metrics:
        got = _aligned(frames + [control], f"err_{name}")
        if got is None:
            return None
        err, fold = got
        s = seed_bootstrap_maa(err[:-1], err[-1:], LIMIT, strata=fold, n_boot=N_BOOT, seed=0)
        v = verdict(claim.kind, s["lo"], s["hi"])
        verdicts.append(v)
        row[f"{name}: model − control [95%]"] = f"{s['diff']:+.3f} [{s['lo']:+.3f}, {s['hi']:+.3f}]"
        row[f"{name}: P(improve)"] = f"{s['p_improve']:.2f}"
        row[f"{name}: verdict"] = v
        row["pairs"] = err.shape[1]
    row["verdict"] = combine(verdicts)
    return row


def build(eval_root: str | Path = "reports/eval", out_dir: str | Path = "reports",
          claims: tuple[Claim, ...] = CLAIMS) -> dict[str, Any]:
    """Write <out_dir>/claims.{md,csv} from the fold results; -> {"files", "missing"} (claims whose rows are absent)."""
    from rlsac.reports.folds import N_BOOT, collect

    results = {sub: collect(eval_root, sub) for sub in sorted({c.sub for c in claims})}
    rows, missing = [], []
    for c in claims:
        row = check(c, results[c.sub])
        (rows.append(row) if row is not None else missing.append(c.text))
    if not any(results.values()):
        print(f"claims: no results under {eval_root}; nothing written")
        return {"files": [], "missing": missing}
    # results but no claim's rows (a profile with other budgets or rows, e.g. the quick one): the files say so
    df = pd.DataFrame(rows, columns=None if rows else ["claim", "where", "rows", "kind", "seeds", "pairs", "verdict"])
    cols = ["claim", "where", "rows", "kind", "seeds", "pairs"] + [
        c for name in ("R", "t") for c in (f"{name}: model − control [95%]", f"{name}: P(improve)",
                                           f"{name}: verdict") if c in df.columns] + ["verdict"]
    df = df[cols].fillna("–")  # a metric the claim does not speak of
    counts = df["verdict"].value_counts()
    one_seed = int((df["seeds"] == 1).sum())
    head = ("# Claims about RLSAC, each checked against the results (issue #27)\n\n"
            "Generated by `rlsac table --which claims` from reports/eval (no number here is typed by hand). Each claim "
            "sets one row against another on the same test pairs, mAA@10° of R and t, pooled over the folds. "
            "`seeds`: the model's training seeds taken (its rows <model>-s<seed>); the 95% interval resamples the "
            f"seeds, then the pairs within each test building ({N_BOOT} draws); with one seed it resamples pairs only "
            "and cannot speak for training noise. `P(improve)`: the probability that a random seed of the model beats "
            "the control on a random test building. Verdicts: *better* / *worse* are supported when the interval "
            f"excludes 0 on that side; *tie* is supported when the interval lies inside ±{TIE_MARGIN} mAA (and not "
            "supported when it excludes 0 and reaches beyond); a claim is *not supported* when an interval "
            "contradicts it, *inconclusive* otherwise.\n\n"
            f"{len(df)} claims: " + ", ".join(f"{counts.get(v, 0)} {v}" for v in ("supported", "inconclusive",
                                                                                    "not supported"))
            + f"; {one_seed} rest on one training seed.\n\n")
    body = df.to_markdown(index=False, disable_numparse=True) + "\n"
    if missing:
        body += "\nNot checked (their rows are not in reports/eval): " + "; ".join(missing) + ".\n"
    out_dir = Path(out_dir)
    write_text(out_dir / "claims.md", head + body)
    with atomic_path(out_dir / "claims.csv") as tmp:
        df.to_csv(tmp, index=False)
    return {"files": [str(out_dir / "claims.md"), str(out_dir / "claims.csv")], "missing": missing}

