"""Two sources of variance the tables' intervals leave out (issue #47 item 7): params.yaml ``tuning_budget`` and the
re-selection of a row's settings on bootstrap resamples of its validation pairs.

(a) Every row of the tables is tuned at ``tuning.iterations`` (100) and tested at 1000 too; the CVPR 2020 tutorial
    tunes at the budget it tests at. ``iterations`` / ``regimes`` / ``methods``: the rows tuned again at that budget
    (``rlsac folds --stage tune --tune-iterations``, records under reports/tuning_at<budget>/) and tested at it
    (reports/eval/folds_at<budget>/).
(b) The intervals resample test pairs with each row's settings fixed; the settings were chosen on a few dozen
    validation pairs, which are a sample too. ``retune_*``: the rows whose choice is replayed on ``retune_draws``
    stratified resamples of the validation pairs with the tuning's own rule (rlsac.evaluation.tune.search), each
    re-selected setting tested on the fold's test pairs at ``retune_iterations`` (``rlsac folds --stage retune``,
    reports/retune/).

Pure functions only (no runner, no files): the runner rlsac.experiments.folds_retune and the report
rlsac.reports.tuning_budget share them.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from rlsac.errors import RlsacError

DEFAULTS: dict[str, Any] = {
    "iterations": 1000,
    "regimes": [],
    "methods": [],
    "retune_regime": "hard",
    "retune_methods": [],
    "retune_draws": 200,
    "retune_seed": 0,
    "retune_iterations": [1000],
    # a second regime's rows re-tuned the same way (their tables' choice, tested at ``retune_iterations``), so that
    # the claims made in that regime carry their selection term too (issue #62: "not measured" otherwise)
    "retune_also": {"regime": "easy", "methods": []},
    # learned rows (a checkpoint each, e.g. rlsac and its seed rows rlsac-s<k>) re-tuned at ``iterations`` in
    # ``learned_regimes``: their threshold alone, at the tables' pre-filter (their grid runs the network at every
    # point, ~0.3 s a pair at 1000 iterations; the pre-filter and the row's knobs stay the tables' choice)
    "learned": [],
    "learned_regimes": [],
}


def conf(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``tuning_budget`` over ``DEFAULTS``, typed, its rows and budgets those of params ``folds``;
    unknown keys are errors."""
    from rlsac.config import check_value, over_defaults
    from rlsac.layout.protocol import read

    c = over_defaults(params, "tuning_budget", DEFAULTS)
    p = read(params)
    c["iterations"] = check_value("tuning_budget.iterations", c["iterations"], int, "[1, inf)")
    c["retune_draws"] = check_value("tuning_budget.retune_draws", c["retune_draws"], int, "[1, 100000]")
    c["retune_seed"] = check_value("tuning_budget.retune_seed", c["retune_seed"], int, "[0, 4294967295]")
    c["retune_regime"] = check_value("tuning_budget.retune_regime", c["retune_regime"], str)
    for key in ("regimes", "methods", "retune_methods", "retune_iterations", "learned", "learned_regimes"):
        if not isinstance(c[key], list):
            raise RlsacError(f"tuning_budget.{key} must be a list, got {c[key]!r}")
        c[key] = [check_value(f"tuning_budget.{key}", v, int if key == "retune_iterations" else str)
                  for v in c[key]]
    for key in ("methods", "retune_methods"):  # rows of the tables with their own settings (no checkpoint to load)
        bad = sorted(set(c[key]) - set(p["methods"]))
        if bad:
            raise RlsacError(f"tuning_budget.{key} {bad}: not methods of folds.methods {p['methods']}")
    bad = sorted(set(c["learned"]) - set(p["models"]) - {f"{m}-s{k}" for m in p["seed_models"] for k in p["seeds"]})
    if bad:
        raise RlsacError(f"tuning_budget.learned {bad}: not models of folds.models or their seed rows")
    bad = sorted(set(c["regimes"] + c["learned_regimes"] + [c["retune_regime"]]) - set(p["regimes"]))
    if bad:
        raise RlsacError(f"tuning_budget regime(s) {bad}: not regimes of folds.regimes {p['regimes']}")
    for r in c["regimes"] + c["learned_regimes"]:  # tuned at the budget it is tested at: one of the regime's tables
        if c["iterations"] not in p["iterations"][r]:
            raise RlsacError(f"tuning_budget.iterations {c['iterations']}: not a test budget of regime {r!r} "
                             f"(folds.iterations {p['iterations'][r]})")
    also = c["retune_also"]
    if not isinstance(also, dict) or sorted(also) != ["methods", "regime"] or not isinstance(also["methods"], list):
        raise RlsacError(f"tuning_budget.retune_also must be {{regime: <a regime>, methods: [<rows>]}}, got {also!r}")
    also = {"regime": check_value("tuning_budget.retune_also.regime", also["regime"], str),
            "methods": [check_value("tuning_budget.retune_also.methods", v, str) for v in also["methods"]]}
    if also["methods"] and (also["regime"] not in p["regimes"] or also["regime"] == c["retune_regime"]):
        raise RlsacError(f"tuning_budget.retune_also.regime {also['regime']!r}: a regime of folds.regimes "
                         f"{p['regimes']} other than retune_regime {c['retune_regime']!r}")
    bad = sorted(set(also["methods"]) - set(p["methods"]))
    if bad:
        raise RlsacError(f"tuning_budget.retune_also.methods {bad}: not methods of folds.methods {p['methods']}")
    c["retune_also"] = also
    for regime in [c["retune_regime"]] + ([also["regime"]] if also["methods"] else []):
        bad = sorted(set(c["retune_iterations"]) - set(p["iterations"][regime]))
        if bad:
            raise RlsacError(f"tuning_budget.retune_iterations {bad}: not test budgets of regime "
                             f"{regime!r} (folds.iterations {p['iterations'][regime]})")
    return c


def scores(err_R: np.ndarray, err_t: np.ndarray, limit: float) -> dict[str, float]:
    """The tuning's criterion and its parts on some pairs: mAA of max(err_R, err_t), of err_R and of err_t."""
    from rlsac.maths.metrics import mAA

    return {"mAA": mAA(np.maximum(err_R, err_t), limit), "mAA_R": mAA(err_R, limit), "mAA_t": mAA(err_t, limit)}


def draws(strata, n: int, seed: int) -> np.ndarray:
    """(n, M) indices of ``n`` bootstrap resamples of M pairs, each stratum (scene) resampled within itself (its size
    kept), as the tables resample test pairs (rlsac.maths.metrics)."""
    from rlsac.maths.metrics import stratified_draws

    strata = np.asarray(strata)
    if strata.ndim != 1 or not strata.size:
        raise RlsacError(f"re-tuning needs one stratum per validation pair, got shape {strata.shape}")
    return stratified_draws(np.random.default_rng(seed), strata, n)


def reselect(errors: Callable[[dict[str, Any]], tuple[np.ndarray, np.ndarray]], strata, c: dict[str, Any],
             knobs: list[str], n: int, seed: int, limit: float) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The tuning's rule (rlsac.evaluation.tune.search with grid ``c``, params ``tuning``) run on all validation pairs,
    then on each of ``n`` stratified resamples of them (``draws``).

    errors(settings) -> (err_R, err_t) on every validation pair, in the order of ``strata`` (the caller caches: the
    rule visits a point once per draw). -> (the choice on all pairs, the choice of each draw)."""
    from rlsac.evaluation.tune import search

    def on(rows):
        def run(settings: dict[str, Any]) -> dict[str, float]:
            R, t = errors(settings)
            return scores(np.asarray(R)[rows], np.asarray(t)[rows], limit)
        return run

    full, _ = search(on(slice(None)), {}, c, knobs, on_settings=True)
    return full, [search(on(idx), {}, c, knobs, on_settings=True)[0] for idx in draws(strata, n, seed)]


def key(settings: dict[str, Any]) -> tuple:
    """A setting as a hashable key (the order of its knobs does not matter)."""
    return tuple(sorted(settings.items()))
