"""The learner's ladder's vocabulary (issue #61): its params (``ladder``), its rungs and their files, shared by its
runner (rlsac.experiments.ladder) and its report (rlsac.reports.ladder)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError

ROOT = Path("experiments/ladder")
CKPT_ROOT = Path("checkpoints/ladder")

@dataclass(frozen=True)
class Rung:
    """One environment of the ladder: where its pairs come from and what its learner optimises."""

    name: str
    data: str  # "synthetic" or "real"
    snn: str = "separable"  # synthetic: rlsac.data.synthetic_pairs SNN_MODES; real: "real" or "redrawn"
    ratios: str = "fixed"  # synthetic: "fixed" (inlier_ratio) or "fitted"
    positions: str = "uniform"  # synthetic: "uniform" or "fitted"
    inlier_ratio: float = 0.3
    learner: str = "sac"  # "sac", "supervised", or "scale" (the scale study's redraw actors, measured only)
    reward: str = "inlier_ratio"  # EnvConf.reward
    reward_threshold: str = "train"  # "train" (the task's, 2 px) or "eval" (the rung's evaluation threshold)
    prefilter: bool = False  # measured with the settings_from row's tuned SNN pre-filter (Table 2's environment)
    # SAC's per-point entropy target (x log N, SACConf.target_entropy_scale); None: the recipe's (0.5). The drift
    # after the control's peak follows a rising temperature: the arm "entropy" sets the target to 0 so that it can
    # only fall, and shows whether the drift is the entropy target's doing
    entropy_target: float | None = None
    # the rung whose controls (uniform, guided, oracle) are this rung's: the same test pairs, inputs and settings,
    # so they are measured once (the learner-only arms of rung 3)
    controls_from: str = ""

    @property
    def controls(self) -> str:
        return self.controls_from or self.name

    @property
    def why(self) -> str:
        return WHY[self.name.split("-")[0]]

WHY = {"control": "separable SNN at a fixed inlier ratio (the positive control)",
       "rung0": "separable SNN, the real pairs' inlier ratios",
       "rung1": "+ the real pairs' SNN overlap of inliers and outliers",
       "rung2": "+ the real outliers' image positions (the fitted generator)",
       "rung3a": "real pairs, SNN redrawn per label as in rung 2",
       "rung3": "real pairs as they are (the scale study's redraw arm)",
       "supervised": "rung 3's inputs, trained on ground-truth labels",
       "reward": "rung 3, reward threshold = the evaluation's",
       "improvement": "rung 3, improvement reward",
       "rung4": "rung 3's actors in Table 2's environment (+ the tuned SNN pre-filter)",
       "entropy": "control-0.45 with SAC's entropy target at 0 (the temperature can only fall)"}

def rungs(c: dict[str, Any]) -> dict[str, Rung]:
    """The ladder's rungs in order (``c``: params ladder)."""
    out = {f"control-{r}": Rung(f"control-{r}", "synthetic", inlier_ratio=float(r)) for r in c["control_ratios"]}
    out.update({
        "rung0": Rung("rung0", "synthetic", ratios="fitted"),
        "rung1": Rung("rung1", "synthetic", snn="fitted", ratios="fitted"),
        "rung2": Rung("rung2", "synthetic", snn="fitted", ratios="fitted", positions="fitted"),
        "rung3a": Rung("rung3a", "real", snn="redrawn"),
        "rung3": Rung("rung3", "real", snn="real", learner="scale"),
        "supervised": Rung("supervised", "real", snn="real", learner="supervised", controls_from="rung3"),
        "reward": Rung("reward", "real", snn="real", reward_threshold="eval", controls_from="rung3"),
        "improvement": Rung("improvement", "real", snn="real", reward="improvement", controls_from="rung3"),
        "rung4": Rung("rung4", "real", snn="real", learner="scale", prefilter=True),
    })
    if "control-0.45" in out:  # the drift's cause (issue #61 item 1), on the control where it is largest
        out["entropy"] = Rung("entropy", "synthetic", inlier_ratio=0.45, entropy_target=0.0,
                              controls_from="control-0.45")
    return out

KEYS = {"steps": int, "every": int, "seeds": list, "iterations": list, "curve_iterations": int, "train_pairs": int,
        "test_pairs": int, "control_ratios": list, "fold": str, "regime": str, "settings_from": str}

def conf(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``ladder``, checked: every key, its type (a bool is not an int) and range."""
    from rlsac.config import section

    c = section(params, "ladder")
    unknown, missing = sorted(set(c) - set(KEYS)), sorted(set(KEYS) - set(c))
    if unknown or missing:
        raise RlsacError(f"params.yaml ladder: unknown keys {unknown}, missing keys {missing}")
    for k, t in KEYS.items():
        if not isinstance(c[k], t) or isinstance(c[k], bool):
            raise RlsacError(f"params.yaml ladder.{k}: a {t.__name__}, got {c[k]!r}")
    for k in ("steps", "every", "curve_iterations", "train_pairs", "test_pairs"):
        if c[k] < 1:
            raise RlsacError(f"params.yaml ladder.{k}: at least 1, got {c[k]}")
    if c["every"] > c["steps"]:
        raise RlsacError(f"params.yaml ladder.every ({c['every']}) is more than ladder.steps ({c['steps']})")
    for k, ok in (("seeds", lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2 ** 32),
                  ("iterations", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1),
                  ("control_ratios", lambda v: isinstance(v, float) and 0 < v <= 1)):
        if not c[k] or not all(ok(v) for v in c[k]):
            raise RlsacError(f"params.yaml ladder.{k}: a non-empty list of valid values, got {c[k]!r}")
    return c

def record(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``ladder_record`` (the runs recorded so far, one dvc.yaml stage each), checked against ``ladder``:
    ``synthetic`` / ``real``: {"<rung>-s<seed>": {"arm": rung, "seed": seed}} of that kind of rung;
    ``synthetic_controls`` / ``real_controls``: rungs of that kind that have controls of their own."""
    from rlsac.config import section

    r = section(params, "ladder_record")
    kinds = ("synthetic", "real", "synthetic_controls", "real_controls")
    if sorted(r) != sorted(kinds):
        raise RlsacError(f"params.yaml ladder_record: keys {list(kinds)}, got {sorted(r)}")
    all_rungs, seeds = rungs(conf(params)), conf(params)["seeds"]
    for kind in ("synthetic", "real"):
        runs = r[kind] or {}
        if not isinstance(runs, dict):
            raise RlsacError(f"params.yaml ladder_record.{kind}: a mapping of runs, got {runs!r}")
        for name, item in runs.items():
            ok = (isinstance(item, dict) and sorted(item) == ["arm", "seed"] and item["arm"] in all_rungs
                  and all_rungs[item["arm"]].data == kind and item["seed"] in seeds
                  and name == f"{item['arm']}-s{item['seed']}")
            if not ok:
                raise RlsacError(f"params.yaml ladder_record.{kind}.{name}: {{arm: <a {kind} rung>, seed: <one of "
                                 f"ladder.seeds>}} named <arm>-s<seed>, got {item!r}")
        arms = r[f"{kind}_controls"] or []
        bad = [a for a in arms if a not in all_rungs or all_rungs[a].data != kind or all_rungs[a].controls_from]
        if not isinstance(arms, list) or bad:
            raise RlsacError(f"params.yaml ladder_record.{kind}_controls: {kind} rungs with controls of their own, "
                             f"got {bad or arms!r}")
    return r

def run_file(rung: str, seed: int) -> Path:
    return ROOT / rung / f"s{seed}.json"

def controls_file(rung: str) -> Path:
    return ROOT / rung / "controls.json"

def actor_file(rung: str, seed: int) -> Path:
    return CKPT_ROOT / rung / f"s{seed}.pt"


@dataclass(frozen=True)
class LadderClaim:
    """A claim about the ladder, written down before its runs finished (issue #61, item 5): ``a`` minus ``b``
    (each a rung's sampler: "rlsac" is the rung's learned policy, seed-resampled) on the same test pairs at
    ``budget`` hypotheses, in ``metric`` ("R" / "t": mAA@10 deg; "pi": pi(inliers)); ``expect``: "better" (the
    interval above 0), "worse", or "tie" (the interval inside +-TIE_MARGIN)."""

    text: str
    a: tuple[str, str]
    b: tuple[str, str]
    metric: str
    budget: int
    expect: str


TIE_MARGIN = 0.02  # mAA and pi(inliers): the equivalence margin of the paper's report (issue #62)

# Written at commit time from one run (rung 3, seed 0, and its controls) while the other runs were training: rung 3
# without the pre-filter showed RLSAC at guided's level and far above uniform; the rest are the ladder's questions.
CLAIMS = (
    LadderClaim("On real pairs without the pre-filter (rung 3), RLSAC is above uniform sets", ("rung3", "rlsac"),
                ("rung3", "uniform"), "R", 100, "better"),
    LadderClaim("On real pairs without the pre-filter (rung 3), RLSAC ties guided sets", ("rung3", "rlsac"),
                ("rung3", "guided"), "R", 100, "tie"),
    LadderClaim("In Table 2's environment (rung 4: the tuned SNN pre-filter on), RLSAC ties uniform sets",
                ("rung4", "rlsac"), ("rung4", "uniform"), "R", 100, "tie"),
    LadderClaim("The pre-filter lifts uniform sets more than RLSAC's: uniform gains from it", ("rung4", "uniform"),
                ("rung3", "uniform"), "R", 100, "better"),
    LadderClaim("The oracle is more than the margin above guided on real pairs: room a sampler could fill",
                ("rung3", "oracle"), ("rung3", "guided"), "R", 100, "better"),
    LadderClaim("Trained on labels (the supervised ceiling), the same actor is above guided sets", ("supervised",
                "rlsac"), ("supervised", "guided"), "R", 100, "better"),
    LadderClaim("RLSAC puts less mass on the inliers than the supervised actor", ("rung3", "rlsac"),
                ("supervised", "rlsac"), "pi", 100, "worse"),
    LadderClaim("The reward at the evaluation's threshold changes nothing (reward vs rung 3)", ("reward", "rlsac"),
                ("rung3", "rlsac"), "R", 100, "tie"),
    LadderClaim("The improvement reward changes nothing (improvement vs rung 3)", ("improvement", "rlsac"),
                ("rung3", "rlsac"), "R", 100, "tie"),
    LadderClaim("With real geometry and rung 2's SNN information (rung 3a), RLSAC ties guided", ("rung3a", "rlsac"),
                ("rung3a", "guided"), "R", 100, "tie"),
    LadderClaim("On the fitted generator (rung 2), RLSAC ties guided", ("rung2", "rlsac"), ("rung2", "guided"), "R",
                100, "tie"),
    LadderClaim("The positive control at inlier ratio 0.3 reaches guided sets by 3000 steps", ("control-0.3", "rlsac"),
                ("control-0.3", "guided"), "R", 100, "tie"),
    # written when control-0.45's three seeds were in (peak pi 0.998-1.000, then a drift of -0.017 to -0.023 while
    # the temperature rose 0.013 -> 0.06-0.07) and before the entropy arm's runs: the drift is the entropy target's
    LadderClaim("With the entropy target at 0 the control does not drift: more mass on the inliers at 3000 steps",
                ("entropy", "rlsac"), ("control-0.45", "rlsac"), "pi", 100, "better"),
)
