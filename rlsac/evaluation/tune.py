"""Settings chosen per fold on that fold's validation pairs only (issue #26; ``rlsac folds --stage tune``).

The CVPR 2020 RANSAC tutorial, whose "recommended settings" the paper cites, tunes every method on validation
pairs: an inlier-threshold grid {0.1, 0.2, 0.25, 0.5, 0.75, 1.0} px and an SNN pre-filter {0.75, 0.8, 0.85} (matches
above it dropped before fitting), at confidence 0.999. Here every row of the fold benchmark (a method, an RLSAC
model, their -lo and -fast variants) is tuned on its fold's ``val.h5`` (pairs of the training buildings, never of
the test building), at ``tuning.iterations``, by coordinate search:

1. the ``threshold_px`` grid at pre-filter ``start_prefilter`` (0.8, Lowe's ratio), then the ``prefilter`` grid at
   the chosen threshold (1.0 = no pre-filter: not in the tutorial's grid, added because our matches are already
   filtered), alternating for at most ``rounds`` rounds until neither moves: 9-15 points where the full grid
   costs 24 (CPU time; the RLSAC rows run a network per point). A best threshold on an edge of the grid extends
   the grid outward (x1.5 above, /1.5 below), a best pre-filter on its strict edge extends it by ``prefilter_step``
   (1.0, no filter, is the other edge), each at most ``extend`` times in all, so the optimum is never an artefact
   of the grid;
2. then, at the chosen pair, the row's own knobs one grid at a time: ``guide_temperature`` (guided), ``lo_sigma_scale``
   (the -lo rows: MAGSAC++'s sigma_max as a multiple of the threshold), ``sets_per_step`` then ``confidence`` (the
   -fast rows; the paper rows keep one set per step and the whole budget), ``refit_output`` (our samplers on the
   essential matrix, Table E: the 8-point refit projected onto the essential manifold, or the best minimal model).

Criterion: validation mAA@10 deg of max(err_R, err_t), the tutorial's; a tie keeps the earlier grid point. The record
``reports/tuning/<task>/<regime>/<fold>/<row>.json`` holds the chosen settings, every grid point's validation mAA and
the validation scenes; the fold's evaluation reads it and refuses one whose scenes meet its test scenes
(``check_record``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError
from rlsac.layout.protocol import record_path  # noqa: F401  (where a row's record lies; also rlsac.evaluation.tune.record_path)

DEFAULTS: dict[str, Any] = {
    "iterations": 1000,
    # the tutorial's grid widened to 3 px: a validation curve need not be monotone, and the edge rule alone can stop
    # short of a learned sampler's training threshold (2 px)
    "threshold_px": [0.1, 0.2, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0],
    "prefilter": [0.75, 0.8, 0.85, 1.0],
    "extend": 3,
    "start_prefilter": 0.8,
    "prefilter_step": 0.05,
    "rounds": 2,
    "guide_temperature": [0.02, 0.05, 0.1, 0.2],
    "lo_sigma_scale": [0.25, 0.5, 1.0],
    "sets_per_step": [2, 4, 8, 12, 16],
    "confidence": [0.99, 0.999, 0.9999],
    "refit_output": [False, True],
}
CRITERION = "mAA"  # the task summary's mAA of max(err_R, err_t) at 10 deg
EXTEND_FACTOR = 1.5


def conf(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``tuning`` over ``DEFAULTS``, every key typed and range-checked; unknown keys are errors."""
    from rlsac.config import check_value, over_defaults

    c = over_defaults(params, "tuning", DEFAULTS)
    c["iterations"] = check_value("tuning.iterations", c["iterations"], int, "[1, inf)")
    c["extend"] = check_value("tuning.extend", c["extend"], int, "[0, 10]")
    c["rounds"] = check_value("tuning.rounds", c["rounds"], int, "[1, 10]")
    c["start_prefilter"] = check_value("tuning.start_prefilter", c["start_prefilter"], float, "(0, 1]")
    c["prefilter_step"] = check_value("tuning.prefilter_step", c["prefilter_step"], float, "(0, 1)")
    from rlsac.evaluation.evaluate import RANGES, TYPES

    # each grid's values are evaluate options (their types and ranges), but the LO sigma, an LOConf field
    ranges = {k: (TYPES[k], RANGES[k]) for k in ("threshold_px", "prefilter", "guide_temperature", "sets_per_step",
                                                 "confidence")}
    ranges["lo_sigma_scale"] = (float, "(0, inf)")
    if not isinstance(c["refit_output"], list) or not c["refit_output"]:
        raise RlsacError(f"tuning.refit_output must be a non-empty list, got {c['refit_output']!r}")
    c["refit_output"] = [check_value("tuning.refit_output", v, bool) for v in c["refit_output"]]
    for key, (tp, spec) in ranges.items():
        if not isinstance(c[key], list) or not c[key]:
            raise RlsacError(f"tuning.{key} must be a non-empty list, got {c[key]!r}")
        c[key] = [check_value(f"tuning.{key}", v, tp, spec) for v in c[key]]
    return c


def scenes_of(data: dict) -> list[str]:
    return sorted({str(s) for s in data["scene"]})


def check_scenes(val_scenes: list[str], train_scenes: list[str], test_scenes: list[str], where: str) -> None:
    """Settings may come from pairs of the fold's training buildings only: refuse validation scenes that are
    test scenes of the fold (pooled validation sets hold other folds' test pairs, and this fold's)."""
    seen = sorted(set(val_scenes) & set(test_scenes))
    if seen:
        raise RlsacError(f"{where}: tuned on pairs of test scene(s) {seen}; settings must come from the fold's own "
                         "validation pairs")
    outside = sorted(set(val_scenes) - set(train_scenes))
    if outside:
        raise RlsacError(f"{where}: tuned on scene(s) {outside} outside the fold's training buildings {train_scenes}")


def check_record(rec: dict[str, Any], path: Path, regime: str, fold: str, row: str, train_scenes: list[str],
                 test_scenes: list[str]) -> dict[str, Any]:
    """A tuning record as the fold's evaluation needs it: this (regime, fold, row), validation scenes of the
    training buildings only -> its chosen settings. ``rec`` is what rlsac.evaluation.results.read_record accepted."""
    if not isinstance(rec, dict):
        raise RlsacError(f"{path}: not a tuning record (holds a {type(rec).__name__}, not a mapping)")
    for key, want in (("regime", regime), ("fold", fold), ("row", row)):
        if rec.get(key) != want:
            raise RlsacError(f"{path}: tuning record for {key} {rec.get(key)!r}, not {want!r}")
    if not isinstance(rec.get("chosen"), dict) or not isinstance(rec.get("val_scenes"), list):
        raise RlsacError(f"{path}: not a tuning record (no 'chosen' settings or 'val_scenes')")
    check_scenes(rec["val_scenes"], train_scenes, test_scenes, str(path))
    return rec["chosen"]


def _edges(grid: list[float], best: float, extend_left: int) -> list[float]:
    """Grid points to add when ``best`` sits on an edge of ``grid`` (none when it is inside or no extension is
    left): one step of ``EXTEND_FACTOR`` beyond that edge."""
    if extend_left <= 0 or len(grid) < 2:
        return []
    if best == max(grid):
        return [round(best * EXTEND_FACTOR, 6)]
    if best == min(grid):
        return [round(best / EXTEND_FACTOR, 6)]
    return []


def search(run, base: dict[str, Any], c: dict[str, Any], knobs: list[str],
           on_settings: bool = False) -> tuple[dict[str, Any], list[dict]]:
    """Coordinate search of ``base`` options on the validation pairs.

    run(options) -> summary dict with ``CRITERION``; ``knobs``: the row's own settings after the threshold x
    pre-filter grid (keys of ``c``). -> (chosen settings, every grid point as {settings, mAA, mAA_R, mAA_t}).
    ``on_settings``: run gets the grid point's settings themselves (rlsac.evaluation.retune replays the rule on stored
    errors, keyed by settings). The rule is this function's alone: the re-tuning study re-selects with it, never a
    copy."""
    points: list[dict] = []
    cache: dict[tuple, dict] = {}

    def score(settings: dict[str, Any]) -> float:
        key = tuple(sorted(settings.items()))
        if key not in cache:
            s = run(dict(settings) if on_settings else {**base, **_as_options(settings, base)})
            cache[key] = {"settings": dict(settings), **{k: s[k] for k in ("mAA", "mAA_R", "mAA_t")}}
            points.append(cache[key])
        return cache[key][CRITERION]

    thresholds, filters = list(c["threshold_px"]), list(c["prefilter"])
    start = c["start_prefilter"] if c["start_prefilter"] in filters else filters[0]
    best: dict[str, Any] = {"threshold_px": thresholds[0], "prefilter": start}
    extend_left = c["extend"]
    filter_left = c["extend"] if c.get("extend_prefilter", True) else 0  # off: the pre-filter grid is fixed
    for _ in range(c["rounds"]):  # alternate: the threshold grid (extended at an edge), then the pre-filter grid
        before = dict(best)
        while True:
            grid = [{**best, "threshold_px": t} for t in thresholds]
            best = max(grid, key=lambda s: (score(s), -grid.index(s)))
            more = _edges(thresholds, best["threshold_px"], extend_left)
            if not more:
                break
            extend_left -= 1
            thresholds = sorted(thresholds + more)
        while True:
            grid = [{**best, "prefilter": f} for f in filters]
            best = max(grid, key=lambda s: (score(s), -grid.index(s)))
            lower = round(best["prefilter"] - c["prefilter_step"], 6)
            if best["prefilter"] != min(filters) or filter_left <= 0 or lower <= 0:
                break
            filter_left -= 1  # the strictest filter won: try a stricter one (the grid's edge is not an optimum)
            filters = sorted(filters + [lower])
        if best == before:
            break
    for knob in knobs:
        grid = [{**best, knob: v} for v in c[knob]]
        best = max(grid, key=lambda s: (score(s), -grid.index(s)))
    return best, points


def _as_options(settings: dict[str, Any], base: dict[str, Any]) -> dict[str, Any]:
    """Tuned settings -> evaluate options (pre-filter 1.0 = none; the LO sigma goes into the lo conf)."""
    o = {k: v for k, v in settings.items() if k != "lo_sigma_scale"}
    if o.get("prefilter") == 1.0:
        o["prefilter"] = None
    if "lo_sigma_scale" in settings:
        o["lo"] = {**(base.get("lo") or {}), "sigma_scale": settings["lo_sigma_scale"]}
    return o


def as_options(chosen: dict[str, Any], lo: dict[str, Any] | None) -> dict[str, Any]:
    """A record's chosen settings -> the evaluate options of the row (``lo``: the row's base LO conf)."""
    return _as_options(chosen, {"lo": lo})


def record_options(path: str | Path, task: str, method: str, checkpoint: str | None,
                   lo: dict[str, Any] | None, data: str | Path | None = None, params: dict[str, Any] | None = None,
                   iterations: int | None = None) -> dict[str, Any]:
    """``rlsac evaluate --tuning FILE``: a tuning record's chosen settings as evaluate options (``as_options``), so a
    cell of Table 2 / Table E can be reproduced by hand. The record must be one of this task and method (its
    ``method`` field: a -fast row's is ``rlsac``) and, for a learned row, of this checkpoint: settings tuned for
    another row or model would be silently wrong. Given the ``data`` it would evaluate, the record is checked against
    it too (``check_record_data``: its budget, regime, fold and scenes)."""
    from rlsac.evaluation.results import read_record

    path = Path(path)
    # the fold stages' reader: `chosen: {}` or `val_scenes: []` evaluated the cell untuned at exit 0 (issue #49)
    try:
        rec = read_record(path)
    except RlsacError as e:
        raise RlsacError(f"--tuning {e}") from None
    if rec is None:
        raise RlsacError(f"--tuning {path}: no such file (records: reports/tuning/<task>/<regime>/<fold>/<row>.json)")
    if "method" not in rec:
        raise RlsacError(f"--tuning {path}: not a tuning record (no 'method')")
    if rec.get("task") != task or rec["method"] != method:
        raise RlsacError(f"--tuning {path}: a record of task {rec.get('task')!r}, method {rec['method']!r}, not "
                         f"task {task!r}, method {method!r}")
    want = rec.get("checkpoint")
    if want and (not checkpoint or Path(checkpoint).resolve() != Path(want).resolve()):
        raise RlsacError(f"--tuning {path}: tuned for checkpoint {want}, not {checkpoint or 'none'} (--checkpoint)")
    from rlsac.config import check_value
    from rlsac.evaluation.evaluate import RANGES, TYPES

    for key in sorted(set(rec["chosen"]) & {"threshold_px", "prefilter"}):  # the task's ranges, naming the record
        check_value(f"--tuning {path}: chosen {key}", rec["chosen"][key], TYPES[key], RANGES[key])
    if data is not None:
        check_record_data(rec, path, task, data, params or {}, iterations)
    return as_options(rec["chosen"], lo)


def check_record_data(rec: dict[str, Any], path: Path, task: str, data: str | Path, params: dict[str, Any],
                      iterations: int | None) -> None:
    """A fold's tuning record against the evaluation it would set (issue #64: castle's record was evaluated on
    entry's pairs at exit 0): its budget that of the tables' tuning (params tuning.iterations) or the command's;
    a data file under data/folds/<regime>/<fold>/ the record's regime and fold; no pair of a scene the record was
    tuned on, and, for a fold params.yaml names, no pair outside that fold's test building."""
    from rlsac.layout.protocol import read as fold_protocol
    from rlsac.layout.protocol import scene_list
    from rlsac.tasks import task_class

    budgets = {conf(params)["iterations"], *([int(iterations)] if iterations is not None else [])}
    if rec.get("iterations") is not None and rec["iterations"] not in budgets:
        raise RlsacError(f"--tuning {path}: tuned at {rec['iterations']!r} iterations, neither the tables' tuning "
                         f"budget nor --iterations ({', '.join(map(str, sorted(budgets)))})")
    parts = Path(data).parts
    if len(parts) >= 5 and parts[-5:-3] == ("data", "folds") and "fold" in rec:
        if (parts[-3], parts[-2]) != (rec.get("regime"), rec["fold"]):
            raise RlsacError(f"--tuning {path}: a record of regime {rec.get('regime')!r}, fold {rec['fold']!r}; "
                             f"{data} is regime {parts[-3]!r}, fold {parts[-2]!r}")
    arrays, _ = task_class(task).read(data)
    if "scene" not in arrays:
        return
    scenes = scenes_of(arrays)
    leaked = sorted(set(scenes) & set(rec["val_scenes"]))
    if leaked:
        raise RlsacError(f"--tuning {path}: tuned on pairs of scene(s) {leaked}, which {data} holds: its settings "
                         "were chosen on the pairs being evaluated")
    p = fold_protocol(params)
    if rec.get("fold") in p["scenes"]:
        outside = sorted(set(scenes) - set(scene_list(p["scenes"][rec["fold"]])))
        if outside:
            raise RlsacError(f"--tuning {path}: a record of fold {rec['fold']!r}; {data} holds pairs of scene(s) "
                             f"{outside} outside that fold's test building")


def tuned_settings(ev: dict, regime: str, fold: str, name: str, train_scenes: list[str], test_scenes: list[str],
                   task: str = "fundamental", tuned_at: int | None = None) -> dict[str, Any]:
    """Row ``name``'s settings from its tuning record (chosen on the fold's validation pairs only, checked against
    the test scenes) as evaluate options; ``tuned_at``: the record tuned at that budget (``--tune-iterations``)."""
    from rlsac.evaluation.results import read_record

    path = record_path(regime, fold, name, task, tuned_at)
    rec = read_record(path)  # `[]`, `null`, `chosen: {}`, `val_scenes: []` are refused by name (issue #49)
    if rec is None:
        flag = "" if tuned_at is None else f" --tune-iterations {tuned_at}"
        raise RlsacError(f"{path}: no tuning record (run `rlsac folds --stage tune{flag}` first)")
    if tuned_at is not None and rec.get("iterations") != tuned_at:  # a record of another budget moved here by hand
        raise RlsacError(f"{path}: tuned at {rec.get('iterations')!r} iterations, not {tuned_at}")
    return as_options(check_record(rec, path, regime, fold, name, train_scenes, test_scenes), ev.get("lo"))
