"""The protocol's vocabulary: the fold benchmark's rows, names and result paths, and how results are compared, shared
by its runners (rlsac.experiments.folds, rlsac.experiments.selection, rlsac.experiments.scale) and the reports that read
their results.

params.yaml ``folds`` read and checked (``read``); its rows, models and training seeds and their names (<model>-s<seed>,
<row>-n<N>); where each stage writes (data, checkpoints, evaluations, tuning records); the mAA limits and bootstrap
draws of the reports.

Imports nothing above rlsac.config: a report reads the names here, never a runner.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any, Callable, Mapping

from rlsac.errors import RlsacError

# how the reports compare results: the mAA limits (Table 1's line angle; the fold benchmark's R and t, the tutorial's)
# and the bootstrap's draws (interval ends stable to ~0.001)
LINE_LIMIT_DEG = 0.5  # Table 1's mAA limit (thresholds 0.05..0.5 deg)
# the line claims' tie margin: ±0.01 mAA@0.5° (10 of the 1000 test instances per rate; our RANSAC-to-oracle gap is
# 0.001-0.09)
LINE_TIE_MARGIN = 0.01
LIMIT = 10.0  # mAA@10 deg (the tutorial's and Table 2's)
PAIRED_BOOT = 2000  # bootstrap resamples of the Table 1 paired comparison: interval ends stable to ~0.001
N_BOOT = 2000  # bootstrap resamples of the fold benchmark's intervals

DEFAULTS: dict[str, Any] = {
    "test": ["castle", "herzjesu", "fountain", "entry"],
    "scenes": {"castle": "castle-P19,castle-P30", "herzjesu": "Herz-Jesus-P8,Herz-Jesus-P25",
               "fountain": "fountain-P11", "entry": "entry-P10"},
    "val_fraction": 0.2,
    "regimes": ["easy", "hard"],
    "pool": {"easy": 0, "hard": 600},
    "methods": ["uniform", "ransac", "opencv_ransac", "usac", "usac_accurate", "magsac"],
    "models": ["rlsac"],
    "train": {"rlsac": {}},
    # models of folds.models whose episodes are redrawn from the fold's pool of matches (their recipe's episodes.pool
    # names data/folds/pool/{fold}.h5: ``pool_file``, filled per fold by ``train_options``), so their training depends
    # on that file too (dvc.yaml's fold_train_pool*); file_models / file_seed_models: the other models of folds.models
    # / seed_models (dvc.yaml's fold_train / fold_train_seed iterate them), None = derived; given, they must be that
    "pool_models": [],
    "file_models": None,
    "file_seed_models": None,
    "iterations": [10, 100, 1000],
    "seed": 0,
    "model_regime": "hard",
    "lo_models": [],
    # our samplers with rlsac.estimation.lo (the same-LO arm): rows <method>, e.g. ransac-lo, in variant_regimes only
    "lo_methods": [],
    # regimes of the variant rows (lo_methods, <model>-lo, <model>-fast, ablations); None = every regime
    "variant_regimes": None,
    # Table 3 on the folds (variant regimes only): models trained with the paper's ablations (folds.train recipes,
    # the full model's budget), and models also run with probabilistic test-time sampling (rows <model>-prob)
    "ablation_models": [],
    "prob_models": [],
    # Table 3 (c), the paper's N study (variant regimes only): the regime's data prepared again with N points per pair
    # (data/folds/<regime>-n<N>) and rows <row>-n<N> on it: models of folds.models trained on that data with their
    # own recipe, methods of folds.methods
    "points": [],
    "points_models": [],
    "points_methods": [],
    # training seeds (issue #27): each model of seed_models trained again with every seed of ``seeds`` (its recipe's
    # own seed is the model itself), tuned and evaluated like it in every regime: rows <model>-s<seed>
    "seeds": [],
    "seed_models": [],
    # Table 3's models (of ablation_models) trained with every seed too; with them, every variant row of a model trained
    # with other seeds (<model>-lo, -fast, -prob, the ablation models) is also a row per seed: <row>-s<seed>, in the
    # variant regimes (issue #27: the ablations and the same-LO and speed rows are claims about a learned model)
    "seed_ablation_models": [],
    # models also run with the speed levers of issue #17 (several sets per step, the confidence stop), k and the
    # confidence tuned on validation: rows <model>-fast (not in the paper; the plain rows are the paper's algorithm)
    "fast": [],
    # checkpoint selection measured (issue #27, item 3; rlsac.experiments.selection): these models (of seed_models:
    # every training seed) replayed, each validated actor tested at these budgets of the model regime; validation scores
    # within select_tie of the kept one's count as a tie
    "select_models": [],
    "select_iterations": [1000],
    "select_tie": 0.01,
}


def read(params: dict[str, Any], methods: Mapping[str, Any] | None = None,
         train_conf: Callable[[dict[str, Any], str], Any] | None = None) -> dict[str, Any]:
    """``DEFAULTS`` with each key replaced by params.yaml ``folds``'s, checked for consistency. ``methods`` (the
    evaluate methods' registry, rlsac.evaluation.methods.METHODS) and ``train_conf`` (a training recipe and its name ->
    its TrainConf, checked) add the checks of the rows' methods and recipes: rlsac.experiments.folds.protocol passes
    both."""
    from rlsac.config import over_defaults, section

    p = _typed(over_defaults(params, "folds", DEFAULTS))
    if not p["test"] or not set(p["test"]) <= set(p["scenes"]) or len(p["scenes"]) < 2:
        raise RlsacError(f"folds.test {p['test']} must name buildings of folds.scenes {sorted(p['scenes'])} "
                         "(at least two buildings: one to test, one to train)")
    all_scenes = [s for b in p["scenes"] for s in scene_list(p["scenes"][b])]
    if len(all_scenes) != len(set(all_scenes)):
        raise RlsacError("folds.scenes: a scene belongs to two buildings")
    if "pool" in p["regimes"]:  # data/folds/pool/ holds the folds' pools of matches (pool_file)
        raise RlsacError("folds.regimes: 'pool' names the folder of the folds' pools of matches (data/folds/pool)")
    if set(p["regimes"]) != set(p["pool"]):
        raise RlsacError(f"folds.regimes {p['regimes']} and the keys of folds.pool {sorted(p['pool'])} differ")
    trained = trained_models(p)
    staged = {m for m in set(p["train"]) - set(trained)  # a pool recipe waiting for its runs (_check_pool_models)
              if ((p["train"][m] or {}).get("episodes") or {}).get("pool") == POOL_TEMPLATE}
    if set(trained) != set(p["train"]) - staged or len(set(trained)) != len(trained):
        raise RlsacError(f"folds.models + folds.ablation_models {trained} and the keys of folds.train "
                         f"{sorted(p['train'])} differ")
    if not set(p["prob_models"]) <= set(trained):
        raise RlsacError(f"folds.prob_models {p['prob_models']} must be models of folds.models or ablation_models")
    if p["model_regime"] not in p["regimes"]:
        raise RlsacError(f"folds.model_regime {p['model_regime']!r} is not one of folds.regimes {p['regimes']}")
    if set(p["iterations"]) != set(p["regimes"]) or not all(p["iterations"].values()):
        raise RlsacError(f"folds.iterations must give budgets for every regime of {p['regimes']} (a list for all, or "
                         f"a mapping regime -> list), got {p['iterations']}")
    if methods is not None:
        bad = [m for m in p["methods"] if m not in methods or methods[m].checkpoint or m == "oracle"]
        if bad:
            raise RlsacError(f"folds.methods {bad}: not a baseline of `rlsac evaluate` (RLSAC models go in "
                             "folds.models, NG-RANSAC ones too: a folds.train recipe with method ngransac)")
        bad = [m for m in p["lo_methods"] if m not in methods or not methods[m].lo or methods[m].checkpoint]
        if bad:
            raise RlsacError(f"folds.lo_methods {bad}: not a -lo baseline of `rlsac evaluate` (rlsac-lo: "
                             "folds.lo_models)")
    if not set(p["variant_regimes"]) <= set(p["regimes"]):
        raise RlsacError(f"folds.variant_regimes {p['variant_regimes']} must be regimes of {p['regimes']}")
    if not set(p["lo_models"]) <= set(p["models"]):
        raise RlsacError(f"folds.lo_models {p['lo_models']} must be models of folds.models {p['models']}")
    clash = sorted(m for m in set(p["models"]) & set(methods or ()) if model_method(p, m) != m)
    if clash:
        raise RlsacError(f"folds.models {clash}: a model may not share a method's name (but its own method's)")
    if not set(p["fast"]) <= set(p["models"]):
        raise RlsacError(f"folds.fast {p['fast']} must be models of folds.models {p['models']} (rows <model>-fast)")
    # k sets per step and test-time sampling are the RLSAC environment's (rlsac.rl.rollout); NG-RANSAC's sampler has
    # none
    not_rl = sorted(m for m in p["fast"] + p["prob_models"] if model_method(p, m) != "rlsac")
    if not_rl:
        raise RlsacError(f"folds.fast / prob_models {not_rl}: only RLSAC models have the -fast and -prob rows")
    if not set(p["points_models"]) <= set(p["models"]) or not set(p["points_methods"]) <= set(p["methods"]):
        raise RlsacError(f"folds.points_models {p['points_models']} / points_methods {p['points_methods']} must be "
                         "models of folds.models / methods of folds.methods")
    if not set(p["seed_models"]) <= set(p["models"]):
        raise RlsacError(f"folds.seed_models {p['seed_models']} must be models of folds.models {p['models']}")
    if not set(p["seed_ablation_models"]) <= set(p["ablation_models"]):
        raise RlsacError(f"folds.seed_ablation_models {p['seed_ablation_models']} must be models of "
                         f"folds.ablation_models {p['ablation_models']}")
    seeded = set(p["seed_models"]) | set(p["seed_ablation_models"])
    if p["seeds"]:  # the variant rows per seed need their model per seed (dvc.yaml's *_seed stages)
        for key in ("lo_models", "fast", "prob_models"):
            if not set(p[key]) <= seeded:
                raise RlsacError(f"folds.{key} {p[key]}: with folds.seeds every one must be trained with the other "
                                 f"seeds too (in folds.seed_models or seed_ablation_models)")
    _check_pool_models(p)
    if not set(p["select_models"]) <= set(p["seed_models"]):
        raise RlsacError(f"folds.select_models {p['select_models']} must be models of folds.seed_models "
                         f"{p['seed_models']} (the study covers every training seed)")
    not_rl = sorted(m for m in p["select_models"] if model_method(p, m) != "rlsac")
    if not_rl:
        raise RlsacError(f"folds.select_models {not_rl}: the replay keeps RLSAC's validated actors only")
    if p["select_models"] and not set(p["select_iterations"]) <= set(p["iterations"][p["model_regime"]]):
        raise RlsacError(f"folds.select_iterations {p['select_iterations']} must be budgets of folds.iterations "
                         f"{p['iterations'][p['model_regime']]} (the kept actor's evaluation is read, not redone)")
    if p["points"] and p["model_regime"] not in p["variant_regimes"]:
        raise RlsacError(f"folds.points needs folds.model_regime {p['model_regime']!r} among folds.variant_regimes "
                         f"{p['variant_regimes']} (its models train on that regime's data with N points)")
    from rlsac.config import deep_update

    base = {**section(params, "train", "fundamental"), "task": "fundamental"}
    for model, recipe in p["train"].items() if train_conf is not None else ():
        # each model's recipe a TrainConf, whichever stage reads the params
        conf = train_conf(deep_update(base, recipe or {}), f"folds.train.{model}")
        if model in seeded and conf.seed in p["seeds"]:
            raise RlsacError(f"folds.seeds {p['seeds']} holds seed {conf.seed}, the seed of model {model!r} itself "
                             "(its recipe's train seed): list the other seeds")
    return p


PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
FOLD_PLACEHOLDER = "{fold}"  # the one placeholder a fold recipe may hold: the fold's name (``fill_fold``)


def _strings(value: Any, where: str):
    """Every string of a recipe (nested mappings and lists) with its dotted key."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _strings(v, f"{where}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _strings(v, f"{where}[{i}]")
    elif isinstance(value, str):
        yield where, value


def placeholders(recipe: Any, where: str) -> set[str]:
    """The placeholders (``{name}``) of a recipe's strings; RlsacError for any but ``{fold}``."""
    found = set()
    for key, text in _strings(recipe, where):
        for name in PLACEHOLDER.findall(text):
            if "{" + name + "}" != FOLD_PLACEHOLDER:
                raise RlsacError(f"{key} = {text!r}: unknown placeholder {{{name}}} (a fold recipe may hold only "
                                 f"{FOLD_PLACEHOLDER}, the fold's name)")
            found.add(name)
    return found


def fill_fold(recipe: Any, fold: str, where: str = "recipe") -> Any:
    """``recipe`` with ``{fold}`` replaced by ``fold`` in every string (nested mappings and lists); RlsacError for any
    other placeholder."""
    placeholders(recipe, where)

    def fill(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: fill(x) for k, x in v.items()}
        if isinstance(v, list):
            return [fill(x) for x in v]
        return v.replace(FOLD_PLACEHOLDER, fold) if isinstance(v, str) else v

    return fill(recipe)


def pool_file(fold: str) -> Path:
    """The fold's pool of matches (``rlsac folds --stage pool``): its training pairs with the model regime's pool
    size as points per pair, what the pool models' episodes are redrawn from."""
    return Path("data") / "folds" / "pool" / f"{fold}.h5"


POOL_TEMPLATE = str(pool_file(FOLD_PLACEHOLDER))  # data/folds/pool/{fold}.h5: a pool model's episodes.pool


def _check_pool_models(p: dict[str, Any]) -> None:
    """folds.pool_models: models of folds.models whose recipe redraws episodes from the fold's pool (episodes.pool
    with {fold}); file_models / file_seed_models: the other models of models / seed_models, none in both; a recipe
    with a placeholder belongs to a pool model (only their stages depend on the fold's pool)."""
    pool, models = p["pool_models"], p["models"]
    if len(set(pool)) != len(pool) or not set(pool) <= set(models):
        raise RlsacError(f"folds.pool_models {pool} must be distinct models of folds.models {models}")
    for key, of in (("file_models", "models"), ("file_seed_models", "seed_models")):
        want = [m for m in p[of] if m not in pool]
        if p[key] is None:
            p[key] = want
        both = sorted(set(p[key]) & set(pool))
        if both:
            raise RlsacError(f"folds.{key} and folds.pool_models both hold {both}: a model trains on the fold's files "
                             "or redraws episodes from its pool, not both")
        if p[key] != want:
            raise RlsacError(f"folds.{key} {p[key]} must be folds.{of} without folds.pool_models: {want}")
    if p["seeds"] and not set(pool) <= set(p["seed_models"]):
        raise RlsacError(f"folds.pool_models {pool} must be models of folds.seed_models {p['seed_models']} "
                         "(dvc.yaml's fold_train_pool_seed trains every pool model with every seed of folds.seeds)")
    for key in ("points_models", "select_models"):  # their stages re-train with the fold's files only
        if set(pool) & set(p[key]):
            raise RlsacError(f"folds.{key} {p[key]}: a pool model ({sorted(set(pool) & set(p[key]))}) has no "
                             "such stages (they train on the fold's files)")
    size = p["pool"].get(p["model_regime"], 0)
    for model, recipe in p["train"].items():
        where = f"folds.train.{model}"
        held = placeholders(recipe or {}, where)
        episodes = (recipe or {}).get("episodes") or {}
        if model in pool:
            src = episodes.get("pool") if isinstance(episodes, dict) else None
            if not isinstance(src, str) or FOLD_PLACEHOLDER not in src:
                raise RlsacError(f"{where}: a model of folds.pool_models redraws its episodes from the fold's pool: "
                                 f"episodes.pool must name it with {FOLD_PLACEHOLDER} ({POOL_TEMPLATE}), got {src!r}")
            if src != POOL_TEMPLATE:
                raise RlsacError(f"{where}.episodes.pool {src!r}: the fold's pool is {POOL_TEMPLATE} (what "
                                 "`rlsac folds --stage pool` writes and dvc.yaml's fold_train_pool* depend on)")
            points = episodes.get("points", 150)
            if size <= 0 or (isinstance(points, int) and points > size):
                raise RlsacError(f"{where}: episodes of {points} points need the pool of folds.model_regime "
                                 f"{p['model_regime']!r} to hold at least as many (folds.pool.{p['model_regime']} = "
                                 f"{size})")
        elif held:
            # a pool recipe not (yet) in the benchmark's lists: a model whose runs span sessions joins models,
            # seed_models and pool_models when they are recorded (until then it has no stage)
            rest = {**recipe, "episodes": {k: v for k, v in episodes.items() if k != "pool"}} \
                if isinstance(episodes, dict) else recipe
            staged = isinstance(episodes, dict) and episodes.get("pool") == POOL_TEMPLATE and not placeholders(rest,
                                                                                                          where)
            if not staged or model in p["models"] + p["seed_models"] + p["ablation_models"]:
                raise RlsacError(f"{where} holds {FOLD_PLACEHOLDER}: only a model of folds.pool_models {pool} may (its "
                                 "training stages are the ones that depend on the fold's pool)")


def trained_models(p: dict[str, Any]) -> list[str]:
    """The models trained per fold with a recipe of folds.train: Table 2's (folds.models), then Table 3's
    (folds.ablation_models); the N study's and the other training seeds' (``derived_models``) reuse a recipe."""
    return p["models"] + p["ablation_models"]


def model_method(p: dict[str, Any], model: str) -> str:
    """The evaluate method of fold model ``model`` (its recipe's ``method``: rlsac unless it says ngransac)."""
    recipe = (p.get("train") or {}).get(model) or {}
    return str(recipe.get("method", "rlsac"))


def points_name(row: str, points: int) -> str:
    """Table 3 (c)'s row of ``row`` on the data with ``points`` points per pair (``split_points`` reads it back)."""
    return f"{row}-n{int(points)}"


def seed_name(model: str, seed: int) -> str:
    """``model`` trained with training seed ``seed`` (``split_seed`` reads it back)."""
    return f"{model}-s{int(seed)}"


def split_seed(row: str) -> tuple[str, int | None]:
    """A row's name -> (the model, training seed) for <model>-s<seed>, (row, None) for any other row."""
    base, _, n = row.rpartition("-s")
    return (base, int(n)) if base and n.isdigit() else (row, None)


def select_runs(p: dict[str, Any]) -> list[str]:
    """The training runs of the checkpoint-selection study: each model of folds.select_models and its other seeds."""
    return [r for m in p.get("select_models", []) for r in [m] + [seed_name(m, s) for s in p.get("seeds", [])]]


def derived_models(p: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The models trained with another model's recipe: Table 3 (c)'s <model>-n<N> on the data with N points, and
    issue #27's <model>-s<seed> with another training seed -> {name: {recipe, points, seed}}."""
    out = {points_name(m, n): {"recipe": m, "points": int(n), "seed": None}
           for n in p.get("points", []) for m in p.get("points_models", [])}
    out.update({seed_name(m, s): {"recipe": m, "points": None, "seed": int(s)}
                for s in p.get("seeds", []) for m in p.get("seed_models", []) + p.get("seed_ablation_models", [])})
    return out


def split_points(row: str) -> tuple[str, int | None]:
    """A row's name -> (the row it varies, N) for the N study's <row>-n<N>, (row, None) for any other row."""
    base, _, n = row.rpartition("-n")
    return (base, int(n)) if base and n.isdigit() else (row, None)


def variants(out: dict[str, dict[str, Any]], p: dict[str, Any], fold: str, trained: str, layout: str, run,
             ablation: list[str]) -> None:
    """Add to ``out`` the variant rows of one training run of each model (``run``: a model's or a row's name -> the
    name of that run's, e.g. <name>-s<seed>): <model>-lo, <model>-fast, the ablation models, <model>-prob."""
    out.update({run(f"{m}-lo"): {"method": f"{model_method(p, m)}-lo",
                                 "checkpoint": checkpoint(trained, fold, run(m), layout)} for m in p["lo_models"]})
    out.update({run(f"{m}-fast"): {**out[run(m)], "fast": True} for m in p["fast"]})
    out.update({run(m): {"method": model_method(p, m), "checkpoint": checkpoint(trained, fold, run(m), layout)}
                for m in ablation})
    out.update({run(f"{m}-prob"): {**out[run(m)], "sampling": "prob"} for m in p.get("prob_models", [])})


def rows(p: dict[str, Any], fold: str, regime: str | None = None) -> dict[str, dict[str, Any]]:
    """Every row of the fold benchmark in ``regime`` (None: any) -> {method (evaluate's), checkpoint (RLSAC rows),
    fast (the -fast variant), knobs (the settings tuned after threshold x pre-filter, rlsac.evaluation.tune)}; the
    variant rows (lo_methods, <model>-lo, <model>-fast) only in ``variant_regimes``."""
    trained = p["model_regime"]  # every regime: the models of this one's data
    layout = p.get("fold_checkpoint", FOLD_CHECKPOINT)  # the task's (rlsac.experiments.folds.for_task)
    out = {m: {"method": m, "checkpoint": None} for m in p["methods"]}
    out.update({m: {"method": model_method(p, m), "checkpoint": checkpoint(trained, fold, m, layout)}
                for m in p["models"]})
    out.update({seed_name(m, s): {"method": model_method(p, m), "checkpoint": checkpoint(
        trained, fold, seed_name(m, s), layout)} for s in p.get("seeds", []) for m in p.get("seed_models", [])})
    if regime is None or regime in p.get("variant_regimes", p["regimes"]):
        out.update({m: {"method": m, "checkpoint": None} for m in p.get("lo_methods", [])})
        variants(out, p, fold, trained, layout, lambda m: m, p.get("ablation_models", []))
        for n in p.get("points", []):  # Table 3 (c): each row on the data with N points, a model trained on it
            out.update({points_name(r, n): {**out[r], "points": int(n), "checkpoint": checkpoint(
                trained, fold, points_name(r, n), layout) if out[r]["checkpoint"] else None}
                for r in p.get("points_methods", []) + p.get("points_models", [])})
        for s in p.get("seeds", []):  # issue #27: every variant row of a model (all seeded), per training seed
            variants(out, p, fold, trained, layout, lambda m, s=s: seed_name(m, s), p.get("seed_ablation_models", []))
    for r in out.values():
        r.setdefault("fast", False)
        r.setdefault("points", None)
        r["knobs"] = (["guide_temperature"] if r["method"] in ("guided", "guided-lo") else []) + (
            ["lo_sigma_scale"] if r["method"].endswith("-lo") else []) + (
            ["sets_per_step", "confidence"] if r["fast"] else []) + (
            list(p.get("sampler_knobs", ())) if r["method"] in OUR_SAMPLERS else [])
    return out


def row_options(row: dict[str, Any], p: dict[str, Any], ev: dict[str, Any], o: dict[str, Any]) -> dict[str, Any]:
    """The evaluate options of a row before tuning: the paper's one set per step and whole budget (the -fast rows
    tune both), evaluate.fundamental's LO conf and guided temperature as the starting point."""
    return {"task": p.get("task", "fundamental"), "method": row["method"], "sampling": row.get("sampling", "max"),
            "checkpoint": str(row["checkpoint"]) if row["checkpoint"] else None, "seed": int(p["seed"]),
            "device": o["device"], "lo": ev.get("lo"), "guide_temperature": ev.get("guide_temperature"),
            "sets_per_step": 1, "confidence": 0.0}


def _typed(p: dict[str, Any]) -> dict[str, Any]:
    """Every key of the folds section coerced to its type and range-checked (issue #28: `folds.pool.hard: "x"` or
    `folds.iterations: ["x"]` were tracebacks, some only in the stage that reads them); -> the section, typed."""
    from rlsac.config import SEED_RANGE, check_value

    if p["variant_regimes"] is None:
        p["variant_regimes"] = list(p["regimes"])
    for key in ("file_models", "file_seed_models"):  # None: derived from models / seed_models (_check_pool_models)
        if p[key] is not None and not isinstance(p[key], list):
            raise RlsacError(f"folds.{key} must be a list, got {p[key]!r}")
        if p[key] is not None:
            p[key] = [check_value(f"folds.{key}", v, str) for v in p[key]]
    for key in ("test", "regimes", "methods", "models", "lo_models", "fast", "lo_methods", "variant_regimes",
                "ablation_models", "prob_models", "points_models", "points_methods", "seed_models", "select_models",
                "seed_ablation_models", "pool_models"):
        if not isinstance(p[key], list):
            raise RlsacError(f"folds.{key} must be a list, got {p[key]!r}")
        p[key] = [check_value(f"folds.{key}", v, str) for v in p[key]]
    for key in ("scenes", "pool", "train"):
        if not isinstance(p[key], dict) or not all(isinstance(v, (dict if key == "train" else (str, int)))
                                                   for v in p[key].values()):
            raise RlsacError(f"folds.{key} must map names to {'recipes' if key == 'train' else 'values'}, "
                             f"got {p[key]!r}")
    p["scenes"] = {b: check_value(f"folds.scenes.{b}", v, str) for b, v in p["scenes"].items()}
    p["pool"] = {r: check_value(f"folds.pool.{r}", v, int, "[0, inf)") for r, v in p["pool"].items()}
    p["iterations"] = budgets(p["iterations"], p["regimes"], "folds.iterations")
    p["val_fraction"] = check_value("folds.val_fraction", p["val_fraction"], float, "(0, 1)")
    p["seed"] = check_value("folds.seed", p["seed"], int, SEED_RANGE)
    if not isinstance(p["points"], list):
        raise RlsacError(f"folds.points must be a list of point counts, got {p['points']!r}")
    p["points"] = [check_value("folds.points", v, int, "[8, inf)") for v in p["points"]]
    if not isinstance(p["seeds"], list) or len(set(map(str, p["seeds"]))) != len(p["seeds"]):
        raise RlsacError(f"folds.seeds must be a list of distinct training seeds, got {p['seeds']!r}")
    p["seeds"] = [check_value("folds.seeds", v, int, SEED_RANGE) for v in p["seeds"]]
    p["model_regime"] = check_value("folds.model_regime", p["model_regime"], str)
    if not isinstance(p["select_iterations"], list) or not p["select_iterations"]:
        raise RlsacError(f"folds.select_iterations must be a list of budgets, got {p['select_iterations']!r}")
    p["select_iterations"] = [check_value("folds.select_iterations", v, int, "[1, inf)")
                              for v in p["select_iterations"]]
    p["select_tie"] = check_value("folds.select_tie", p["select_tie"], float, "[0, 1]")
    return p


def budgets(given: Any, regimes: list[str], where: str) -> dict[str, list[int]]:
    """Budgets as a list (every regime) or a mapping regime -> list -> {regime: [int, ...]}, each checked."""
    from rlsac.config import check_value

    per = given if isinstance(given, dict) else dict.fromkeys(regimes, given)
    out = {}
    for r, its in per.items():
        if not isinstance(its, list):
            raise RlsacError(f"{where} must be a list of budgets (or regime -> list), got {given!r}")
        out[str(r)] = [check_value(where, v, int, "[1, inf)") for v in its]
    return out


def scene_list(scenes: str) -> list[str]:
    return [s.strip() for s in str(scenes).split(",") if s.strip()]


def split_scenes(p: dict[str, Any], fold: str) -> tuple[str, str]:
    """-> (training scenes, test scenes) of fold ``fold`` as comma-separated lists."""
    if fold not in p["test"]:
        raise RlsacError(f"unknown fold {fold!r} (known: {', '.join(p['test'])})")
    train = [s for b in p["scenes"] if b != fold for s in scene_list(p["scenes"][b])]
    return ",".join(train), ",".join(scene_list(p["scenes"][fold]))


def data_regime(regime: str, points: int | None = None) -> str:
    """The folder name of a regime's data: the regime's own, or <regime>-n<N> for the N study's."""
    return regime if points is None else f"{regime}-n{int(points)}"


def data_dir(regime: str, fold: str, points: int | None = None) -> Path:
    return Path("data") / "folds" / data_regime(regime, points) / fold


FOLD_CHECKPOINT = "checkpoints/folds/{regime}/{fold}/{model}.pt"  # the fundamental task's (its fold_checkpoint)
FOLD_STAGES = ("data", "pool", "train", "tune", "evaluate", "select", "retune")  # `rlsac folds --stage`: all of them


def checkpoint(regime: str, fold: str, model: str, layout: str = FOLD_CHECKPOINT) -> Path:
    """Where a fold's model lives: ``layout`` is the task's ``fold_checkpoint`` (a protocol's "fold_checkpoint")."""
    seed = split_seed(model)[1]
    return Path(layout.format(regime=regime, fold=fold, model=model, seed="" if seed is None else f"-s{seed}"))


def checkpoint_model(path: str | Path) -> str | None:
    """The fold model a ``checkpoint`` path belongs to (its inverse): ``<model>`` of checkpoints/folds/<regime>/<fold>/
    <model>.pt, ``rlsac`` / ``rlsac-s<seed>`` of Table E's checkpoints/essential/<regime>/<fold>[-s<seed>].pt; None
    for a path outside that layout (a checkpoint of one's own)."""
    path = Path(path)
    if len(path.parts) >= 4 and path.parts[-4:-2] == ("checkpoints", "essential"):
        seed = split_seed(path.stem)[1]
        return "rlsac" if seed is None else seed_name("rlsac", seed)
    if len(path.parts) >= 5 and path.parts[-5:-3] == ("checkpoints", "folds"):
        return path.stem
    return None


def eval_dir(regime: str, fold: str, method: str, iterations: int, task: str = "fundamental",
             tuned_at: int | None = None) -> Path:
    """Where a row's evaluation at ``iterations`` goes; ``tuned_at``: the row tuned at that budget instead of
    tuning.iterations (issue #47 item 7, <sub>_at<budget>: beside the tables' cells, never mixed with them)."""
    return Path("reports") / "eval" / (SUB[task] + at_suffix(tuned_at)) / regime / fold / method / f"i{int(iterations)}"


def at_suffix(tuned_at: int | None) -> str:
    """The folder suffix of rows tuned at budget ``tuned_at`` ("" for the tables' own tuning, tuning.iterations)."""
    return "" if tuned_at is None else f"_at{int(tuned_at)}"


SUB = {"fundamental": "folds", "essential": "essential"}
# our samplers, whose output is refit on its inliers unless the task says otherwise (OpenCV's rows have their own)
OUR_SAMPLERS = ("uniform", "guided", "ransac", "rlsac")  # reports/eval/<sub>/ of each task's fold benchmark


def data_record(regime: str, fold: str, points: int | None = None) -> Path:
    return Path("reports") / "folds" / "data" / data_regime(regime, points) / f"{fold}.json"


def train_options(p: dict, params: dict, regime: str, fold: str, model: str, o: dict) -> dict:
    """`rlsac train`'s options of fold model ``model``: train.fundamental <- folds.train.<model> <- the fold's files."""
    from rlsac.config import deep_update, section

    derived = derived_models(p).get(model, {"recipe": model, "points": None, "seed": None})
    d = data_dir(regime, fold, derived["points"])
    base = section(params, "train", "fundamental")
    # {fold} of a pool model's recipe (episodes.pool: data/folds/pool/{fold}.h5) is this fold's
    recipe = deep_update(base, fill_fold(copy.deepcopy(p["train"][derived["recipe"]] or {}), fold,
                                         f"folds.train.{derived['recipe']}"))
    if derived["seed"] is not None:
        recipe["seed"] = derived["seed"]
    return deep_update(recipe, {
        "task": "fundamental", "data": str(d / "train.h5"), "val_data": str(d / "val.h5"),
        "out": str(checkpoint(regime, fold, model)), "device": o["device"], "threads": int(o["threads"]),
        "run_name": f"train folds {regime} {fold} {model}",
        "tags": {"command": "folds", "benchmark": "folds", "regime": regime, "fold": fold, "model": model}})


def record_path(regime: str, fold: str, row: str, task: str = "fundamental", tuned_at: int | None = None) -> Path:
    """Where ``rlsac folds --stage tune`` keeps row ``row``'s tuning record (rlsac.evaluation.tune); ``tuned_at``: the
    record of
    ``--tune-iterations`` (reports/tuning_at<budget>/, not a dependency of the tables)."""
    return Path("reports") / f"tuning{at_suffix(tuned_at)}" / task / regime / fold / f"{row}.json"


def retune_path(regime: str, fold: str, row: str, task: str = "fundamental") -> Path:
    """Where ``rlsac folds --stage retune`` keeps row ``row``'s re-tuning record (issue #47 item 7 b)."""
    return Path("reports") / "retune" / task / regime / fold / f"{row}.json"
