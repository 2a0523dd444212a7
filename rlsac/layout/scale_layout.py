"""The training-scale study's vocabulary (issue #46): its parameters and where its files live. Read by the runner
(rlsac.experiments.scale) and the report (rlsac.reports.scale) alike; imports nothing above config.

params.yaml ``scale``: one fold of the benchmark; data arms (what an episode sees); training seeds; the steps at
which each run's actor is kept (one run per arm and seed gives the whole curve: with a constant learning rate, the
actor after k steps is the actor of a k-step run) and how far each arm goes (``arm_steps``: an arm not carried
forward stops earlier); the budget every kept actor is tested at (``iterations``) and the budget only the actors of
``final_steps`` are (``final_iterations``: Table 2's 1000, ten times the CPU time; 0 = none); the legs a run is
trained in (``legs``: each leg resumes the last one's saved state, so a longer study extends its runs instead of
re-running them; a resumed leg starts new episodes at its first step, which makes the legs part of the recipe); the
synthetic pairs drawn with the statistics fitted to the fold (``synthetic_pairs``, for the comparison); the pretrain
arm's synthetic phase (``pretrain``: its steps, before the real pairs' steps counted by ``steps``, and its pairs).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rlsac.config import SEED_RANGE, check_value, section
from rlsac.errors import RlsacError

# the record's episodes; a fresh draw of the pool per episode, images swapped at random; ``pretrain.steps`` steps on
# synthetic pairs drawn with the fold's fitted statistics (``pretrain.pairs`` of them), then redraw's episodes; redraw's
# episodes pre-filtered at a ratio drawn per episode from the tuning grid's (``tuning.prefilter``), as at test
ARMS = ("fixed", "redraw", "pretrain", "prefilter")


def protocol(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``scale``, every key typed and range-checked (issue #64: a string ``val_every`` or ``pool`` was a
    ValueError traceback in the stage that read it, a negative one refused under another name): exactly the keys
    of ``TYPES``; integers are not bools, seeds numpy seeds, sizes positive, ``val_every`` at most the largest step."""
    s = dict(section(params, "scale"))
    missing = [k for k in TYPES if k not in s]
    if missing or set(s) - set(TYPES):
        raise RlsacError(f"scale: needs exactly {', '.join(TYPES)} (missing {missing}, "
                         f"unknown {sorted(set(s) - set(TYPES), key=str)})")
    for key, (tp, spec) in TYPES.items():
        if tp is list and (not isinstance(s[key], list) or not s[key]):
            raise RlsacError(f"scale.{key} must be a non-empty list, got {s[key]!r}")
        if tp is not None:
            s[key] = check_value(f"scale.{key}", s[key], tp, spec)
    bad = [a for a in s["arms"] if a not in ARMS]
    if bad:
        raise RlsacError(f"scale.arms {bad}: each one of {', '.join(ARMS)}")
    s["seeds"] = [check_value(f"scale.seeds[{i}]", v, int, SEED_RANGE) for i, v in enumerate(s["seeds"])]
    s["steps"] = sorted({check_value(f"scale.steps[{i}]", v, int, "[1, inf)") for i, v in enumerate(s["steps"])})
    if s["val_every"] > s["steps"][-1]:
        raise RlsacError(f"scale.val_every {s['val_every']} is larger than the largest step {s['steps'][-1]}: no "
                         "validation would run")
    legs = s["legs"]
    if (not isinstance(legs, list) or not legs or not all(_int(v) and v > 0 for v in legs)
            or legs != sorted(set(legs)) or legs[-1] != s["steps"][-1]):
        raise RlsacError(f"scale.legs must be increasing positive integers ending at the largest step "
                         f"{s['steps'][-1]}, got {legs!r}")
    fin = s["final_steps"]
    if not isinstance(fin, list) or not all(_int(v) for v in fin) or not set(fin) <= set(s["steps"]):
        raise RlsacError(f"scale.final_steps must be a list of steps of scale.steps {s['steps']} (each arm's last step "
                         f"is tested at final_iterations too), got {fin!r}")
    s["final_steps"] = sorted(set(fin))
    last = s["arm_steps"]
    if (not isinstance(last, dict) or set(last) - set(s["arms"])
            or any(not _int(v) or v not in s["steps"] for v in last.values())):
        raise RlsacError(f"scale.arm_steps must map arms of scale.arms to a step of scale.steps {s['steps']} (how far "
                         f"that arm's runs go; an arm left out goes to the largest), got {last!r}")
    pre = s["pretrain"]
    if not isinstance(pre, dict) or set(pre) != {"steps", "pairs"} or not all(_int(v) and v > 0 for v in pre.values()):
        raise RlsacError(f"scale.pretrain must be {{steps: <int > 0>, pairs: <int > 0>}} (the pretrain arm's synthetic "
                         f"steps and pairs), got {pre!r}")
    return s


def _int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


# key -> (type, range) checked by rlsac.config.check_value; None: a structure ``protocol`` checks itself. The pool is
# what redraw's episodes draw their points from: at least a minimal set (8 points, the fundamental matrix's)
TYPES: dict[str, tuple[Any, Any]] = {
    "fold": (str, None), "regime": (str, None), "pool": (int, "[8, inf)"), "arms": (list, None),
    "seeds": (list, None), "steps": (list, None), "iterations": (int, "[1, inf)"),
    "final_iterations": (int, "[0, inf)"),  # one budget each: one stage's output folder; 0 = none
    "settings_from": (str, None), "val_every": (int, "[1, inf)"), "legs": (None, None), "final_steps": (None, None),
    "synthetic_pairs": (int, "[1, inf)"), "arm_steps": (None, None), "pretrain": (None, None)}


def arm_steps(s: dict[str, Any], arm: str) -> list[int]:
    """The steps an arm's runs go to: scale.steps up to its scale.arm_steps (the largest where it has none)."""
    last = s["arm_steps"].get(arm, s["steps"][-1])
    return [k for k in s["steps"] if k <= last]


def arm_legs(s: dict[str, Any], arm: str) -> list[int]:
    """The legs of an arm's runs: scale.legs up to its last step, which ends the last leg."""
    last = arm_steps(s, arm)[-1]
    return [k for k in s["legs"] if k < last] + [last]


def arm_final_steps(s: dict[str, Any], arm: str) -> list[int]:
    """The steps of an arm tested at final_iterations: those of final_steps it reaches, and its last (its last leg's
    end), so every arm has one."""
    mine = arm_steps(s, arm)
    return sorted({k for k in s["final_steps"] if k in mine} | {mine[-1]})


def pool_file(fold: str) -> Path:
    return Path("data") / "scale" / fold / "pool.h5"


def val_dir(fold: str, iterations: int, arm: str, seed: int, step: int | None = None) -> Path:
    """A run's actors on the fold's validation pairs at the test's settings (what chooses the recipe)."""
    d = Path("reports") / "eval" / "scale" / fold / f"val-i{int(iterations)}" / run_name(arm, seed)
    return d if step is None else d / f"step{int(step)}"


def synthetic_file(fold: str) -> Path:
    """The pretrain arm's synthetic pairs (stage scale_synthetic)."""
    return Path("data") / "scale" / fold / "synthetic.h5"


def pretrained(fold: str, seed: int) -> Path:
    """A pretrain run's synthetic phase (its actor; the state beside it starts the real phase: train ``init``)."""
    return run_dir(fold, "pretrain", seed) / "synthetic.pt"


def run_name(arm: str, seed: int) -> str:
    return f"{arm}-s{int(seed)}"


def run_dir(fold: str, arm: str, seed: int) -> Path:
    """A run's checkpoints: final.pt (the actor its selection rule kept) and step<k>.pt snapshots."""
    return Path("checkpoints") / "scale" / fold / run_name(arm, seed)


def snapshot(fold: str, arm: str, seed: int, step: int) -> Path:
    return run_dir(fold, arm, seed) / f"final.step{int(step)}.pt"


def eval_dir(fold: str, iterations: int, arm: str, seed: int, step: int | None = None) -> Path:
    """Budget first (reports/eval/scale/<fold>/i<it>/<arm>-s<seed>/step<k>): each budget's evaluations are one
    stage's output, so a budget added later runs without touching the others."""
    d = Path("reports") / "eval" / "scale" / fold / f"i{int(iterations)}" / run_name(arm, seed)
    return d if step is None else d / f"step{int(step)}"
