"""Leave-one-building-out benchmark for the fundamental matrix (``rlsac folds``, params.yaml ``folds``).

The six Strecha scenes show four buildings. Fold ``b`` tests on every pair of building ``b`` and trains
on the other buildings, validating on a held-out ``val_fraction`` of their pairs (a stable hash of the
pair key), so every co-visible pair is a test pair exactly once and no test building is seen in
training. Each fold is prepared in every *regime* (``pool``: 0 = the N lowest-SNN matches, P > N = N
drawn from the P lowest-SNN ones, a tutorial-like inlier ratio) and evaluated with every method at every
budget (RLSAC models are trained once per fold, on the ``model_regime`` data, and evaluated in every regime),
including ``uniform`` (the RLSAC environment with uniform minimal sets: RLSAC - uniform is the
learned sampler alone) and each RLSAC model of ``models`` (train overrides over ``train.fundamental``).

Stages (one DVC stage per regime x fold, per model for training):
    data      data/folds/<regime>/<fold>/{train,val,test}.h5 (--points N: data/folds/<regime>-n<N>/<fold>, Table 3 c)
    train     checkpoints/folds/<regime>/<fold>/<model>.pt
    evaluate  reports/eval/folds/<regime>/<fold>/<method>/i<iterations>/{errors.csv,summary.json}
The data stage also writes reports/folds/data/<regime>/<fold>.json (pairs, dropped pairs and why, ground-truth
inlier-ratio distribution per split): the tables read that record, never data/ itself.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError
from rlsac.io import check_writable, write_json

STAGES = ("data", "train", "tune", "evaluate", "select")
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
    "iterations": [10, 100, 1000],
    "seed": 0,
    "model_regime": "hard",
    "lo_models": [],
    # our samplers with rlsac.lo (the same-LO arm): rows <method>, e.g. ransac-lo, in variant_regimes only
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
    # checkpoint selection measured (issue #27, item 3; rlsac.selection): these models (of seed_models: every training
    # seed) replayed, each validated actor tested at these budgets of the model regime; validation scores within
    # select_tie of the kept one's count as a tie
    "select_models": [],
    "select_iterations": [1000],
    "select_tie": 0.01,
}
OPTIONS: dict[str, Any] = {"stage": None, "regime": None, "fold": None, "model": None, "only": None, "points": None,
                           "task": "fundamental",
                           "params": "params.yaml",
                           "device": "auto", "threads": 1}


def protocol(params: dict[str, Any]) -> dict[str, Any]:
    """``DEFAULTS`` with each key replaced by params.yaml ``folds``'s, checked for consistency."""
    from rlsac.config import over_defaults, section

    p = _typed(over_defaults(params, "folds", DEFAULTS))
    if not p["test"] or not set(p["test"]) <= set(p["scenes"]) or len(p["scenes"]) < 2:
        raise RlsacError(f"folds.test {p['test']} must name buildings of folds.scenes {sorted(p['scenes'])} "
                         "(at least two buildings: one to test, one to train)")
    all_scenes = [s for b in p["scenes"] for s in scene_list(p["scenes"][b])]
    if len(all_scenes) != len(set(all_scenes)):
        raise RlsacError("folds.scenes: a scene belongs to two buildings")
    if set(p["regimes"]) != set(p["pool"]):
        raise RlsacError(f"folds.regimes {p['regimes']} and the keys of folds.pool {sorted(p['pool'])} differ")
    trained = trained_models(p)
    if set(trained) != set(p["train"]) or len(set(trained)) != len(trained):
        raise RlsacError(f"folds.models + folds.ablation_models {trained} and the keys of folds.train "
                         f"{sorted(p['train'])} differ")
    if not set(p["prob_models"]) <= set(trained):
        raise RlsacError(f"folds.prob_models {p['prob_models']} must be models of folds.models or ablation_models")
    if p["model_regime"] not in p["regimes"]:
        raise RlsacError(f"folds.model_regime {p['model_regime']!r} is not one of folds.regimes {p['regimes']}")
    if set(p["iterations"]) != set(p["regimes"]) or not all(p["iterations"].values()):
        raise RlsacError(f"folds.iterations must give budgets for every regime of {p['regimes']} (a list for all, or "
                         f"a mapping regime -> list), got {p['iterations']}")
    from rlsac.methods import METHODS

    bad = [m for m in p["methods"] if m not in METHODS or METHODS[m].checkpoint or m == "oracle"]
    if bad:
        raise RlsacError(f"folds.methods {bad}: not a baseline of `rlsac evaluate` (RLSAC models go in folds.models, "
                         "NG-RANSAC ones too: a folds.train recipe with method ngransac)")
    bad = [m for m in p["lo_methods"] if m not in METHODS or not METHODS[m].lo or METHODS[m].checkpoint]
    if bad:
        raise RlsacError(f"folds.lo_methods {bad}: not a -lo baseline of `rlsac evaluate` (rlsac-lo: folds.lo_models)")
    if not set(p["variant_regimes"]) <= set(p["regimes"]):
        raise RlsacError(f"folds.variant_regimes {p['variant_regimes']} must be regimes of {p['regimes']}")
    if not set(p["lo_models"]) <= set(p["models"]):
        raise RlsacError(f"folds.lo_models {p['lo_models']} must be models of folds.models {p['models']}")
    clash = sorted(m for m in set(p["models"]) & set(METHODS) if model_method(p, m) != m)
    if clash:
        raise RlsacError(f"folds.models {clash}: a model may not share a method's name (but its own method's)")
    if not set(p["fast"]) <= set(p["models"]):
        raise RlsacError(f"folds.fast {p['fast']} must be models of folds.models {p['models']} (rows <model>-fast)")
    # k sets per step and test-time sampling are the RLSAC environment's (rlsac.rollout); NG-RANSAC's sampler has none
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
    from rlsac.config import build, deep_update
    from rlsac.train import TrainConf

    base = {**section(params, "train", "fundamental"), "task": "fundamental"}
    for model, recipe in p["train"].items():  # each model's recipe a TrainConf, whichever stage reads the params
        conf = build(TrainConf, deep_update(base, recipe or {}), f"folds.train.{model}")
        if model in seeded and conf.seed in p["seeds"]:
            raise RlsacError(f"folds.seeds {p['seeds']} holds seed {conf.seed}, the seed of model {model!r} itself "
                             "(its recipe's train seed): list the other seeds")
    return p


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


def variants(out: dict[str, dict[str, Any]], p: dict[str, Any], fold: str, trained: str, task: str, run,
             ablation: list[str]) -> None:
    """Add to ``out`` the variant rows of one training run of each model (``run``: a model's or a row's name -> the
    name of that run's, e.g. <name>-s<seed>): <model>-lo, <model>-fast, the ablation models, <model>-prob."""
    out.update({run(f"{m}-lo"): {"method": f"{model_method(p, m)}-lo",
                                 "checkpoint": checkpoint(trained, fold, run(m), task)} for m in p["lo_models"]})
    out.update({run(f"{m}-fast"): {**out[run(m)], "fast": True} for m in p["fast"]})
    out.update({run(m): {"method": model_method(p, m), "checkpoint": checkpoint(trained, fold, run(m), task)}
                for m in ablation})
    out.update({run(f"{m}-prob"): {**out[run(m)], "sampling": "prob"} for m in p.get("prob_models", [])})


def rows(p: dict[str, Any], fold: str, regime: str | None = None) -> dict[str, dict[str, Any]]:
    """Every row of the fold benchmark in ``regime`` (None: any) -> {method (evaluate's), checkpoint (RLSAC rows),
    fast (the -fast variant), knobs (the settings tuned after threshold x pre-filter, rlsac.tune)}; the variant rows
    (lo_methods, <model>-lo, <model>-fast) only in ``variant_regimes``."""
    trained, task = p["model_regime"], p.get("task", "fundamental")  # every regime: the models of this one's data
    out = {m: {"method": m, "checkpoint": None} for m in p["methods"]}
    out.update({m: {"method": model_method(p, m), "checkpoint": checkpoint(trained, fold, m, task)}
                for m in p["models"]})
    out.update({seed_name(m, s): {"method": model_method(p, m), "checkpoint": checkpoint(
        trained, fold, seed_name(m, s), task)} for s in p.get("seeds", []) for m in p.get("seed_models", [])})
    if regime is None or regime in p.get("variant_regimes", p["regimes"]):
        out.update({m: {"method": m, "checkpoint": None} for m in p.get("lo_methods", [])})
        variants(out, p, fold, trained, task, lambda m: m, p.get("ablation_models", []))
        for n in p.get("points", []):  # Table 3 (c): each row on the data with N points, a model trained on it
            out.update({points_name(r, n): {**out[r], "points": int(n), "checkpoint": checkpoint(
                trained, fold, points_name(r, n), task) if out[r]["checkpoint"] else None}
                for r in p.get("points_methods", []) + p.get("points_models", [])})
        for s in p.get("seeds", []):  # issue #27: every variant row of a model (all seeded), per training seed
            variants(out, p, fold, trained, task, lambda m, s=s: seed_name(m, s), p.get("seed_ablation_models", []))
    for r in out.values():
        r.setdefault("fast", False)
        r.setdefault("points", None)
        r["knobs"] = (["guide_temperature"] if r["method"] in ("guided", "guided-lo") else []) + (
            ["lo_sigma_scale"] if r["method"].endswith("-lo") else []) + (
            ["sets_per_step", "confidence"] if r["fast"] else []) + (
            ["refit_output"] if task == "essential" and r["method"] in OUR_SAMPLERS else [])
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
    for key in ("test", "regimes", "methods", "models", "lo_models", "fast", "lo_methods", "variant_regimes",
                "ablation_models", "prob_models", "points_models", "points_methods", "seed_models", "select_models",
                "seed_ablation_models"):
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


# params.yaml ``fundamental``: the Strecha import and preparation settings (dvc.yaml's import and prepare stages,
# ``make_data``), and the retired 87-pair split's methods and budgets
FUNDAMENTAL = {"src": str, "raw": str, "import_scenes": str, "max_features": int, "min_matches": int, "matches": str,
               "scenes": dict,
               "n_points": int, "max_pairs_per_scene": int, "methods": list[str], "iterations": list[int]}
FUNDAMENTAL_RANGES = {"max_features": "[1, inf)", "min_matches": "[0, inf)", "n_points": "[8, inf)",
                      "max_pairs_per_scene": "[0, inf)", "iterations": "[1, inf)"}


def check_fundamental(params: dict[str, Any]) -> None:
    """params.yaml ``fundamental`` typed and ranged; its methods those of `rlsac evaluate`, its scenes strings."""
    from rlsac.config import check_mapping, check_range, check_value, section
    from rlsac.methods import METHODS

    given = check_mapping(section(params, "fundamental"), dict.fromkeys(FUNDAMENTAL), "fundamental", FUNDAMENTAL,
                          FUNDAMENTAL_RANGES)
    for split, scenes in (given.get("scenes") or {}).items():
        check_value(f"fundamental.scenes.{split}", scenes, str)
    if given.get("methods"):
        check_range("fundamental.methods", given["methods"], METHODS)


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


ESSENTIAL = {"regime": "hard", "methods": ["uniform", "ransac", "opencv_ransac", "usac", "magsac"],
             "iterations": [100, 1000], "seeds": []}  # seeds: RLSAC's other training seeds (rows rlsac-s<seed>)


def check_essential(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``essential`` (Table E): a regime of folds.regimes, methods of `rlsac evaluate`, budgets
    -> the section over ``ESSENTIAL``."""
    from rlsac.config import check_mapping, check_range, section
    from rlsac.methods import METHODS

    given = check_mapping(section(params, "essential"), {"regime": "", "methods": [], "iterations": [], "seeds": []},
                          "essential", {"methods": list[str], "iterations": list[int], "seeds": list[int]},
                          {"iterations": "[1, inf)", "seeds": "[1, 4294967295]"})
    check_range("essential.methods", given.get("methods") or [], METHODS)
    if "regime" in given:
        check_range("essential.regime", given["regime"], tuple(protocol(params)["regimes"]))
    return {**ESSENTIAL, **given}


def for_task(p: dict[str, Any], params: dict[str, Any], task: str) -> dict[str, Any]:
    """The benchmark of ``task`` on the fold data: the fundamental matrix's rows are params ``folds``'s; the
    essential matrix's (Table E) params ``essential``'s methods and its RLSAC model per fold (``rlsac``, trained by
    the essential_train stage, and ``rlsac-s<seed>`` for each of ``essential.seeds``), in its one regime."""
    if task == "fundamental":
        return {**p, "task": task}
    if task != "essential":
        raise RlsacError(f"folds --task must be fundamental or essential, got {task!r}")
    e = check_essential(params)
    return {**p, "task": task, "methods": list(e["methods"]), "models": ["rlsac"], "lo_models": [], "fast": [],
            "lo_methods": [], "variant_regimes": [e["regime"]], "ablation_models": [], "prob_models": [],
            "points": [], "points_models": [], "points_methods": [], "seeds": list(e["seeds"]),
            "seed_models": ["rlsac"], "select_models": [],
            "regimes": [e["regime"]], "model_regime": e["regime"], "iterations": {e["regime"]: list(e["iterations"])}}


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


def checkpoint(regime: str, fold: str, model: str, task: str = "fundamental") -> Path:
    if task == "essential":  # one model per fold (essential_train), and one per other training seed
        seed = split_seed(model)[1]
        return Path("checkpoints") / "essential" / regime / (f"{fold}.pt" if seed is None else f"{fold}-s{seed}.pt")
    return Path("checkpoints") / "folds" / regime / fold / f"{model}.pt"


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


def eval_dir(regime: str, fold: str, method: str, iterations: int, task: str = "fundamental") -> Path:
    return Path("reports") / "eval" / SUB[task] / regime / fold / method / f"i{int(iterations)}"


SUB = {"fundamental": "folds", "essential": "essential"}
# our samplers, whose output is refit on its inliers unless the task says otherwise (OpenCV's rows have their own)
OUR_SAMPLERS = ("uniform", "guided", "ransac", "rlsac")  # reports/eval/<sub>/ of each task's fold benchmark


def check_options(options: dict[str, Any], p: dict[str, Any] | None = None) -> dict[str, Any]:
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise RlsacError(f"unknown folds option(s) {unknown}; known: {sorted(OPTIONS)}")
    o = {**OPTIONS, **{k: v for k, v in options.items() if v is not None}}
    if o["stage"] not in STAGES:
        raise RlsacError(f"folds --stage must be one of {', '.join(STAGES)}, got {o['stage']!r}")
    if p is not None:
        if o["regime"] not in p["regimes"]:
            raise RlsacError(f"unknown regime {o['regime']!r} (known: {', '.join(p['regimes'])})")
        split_scenes(p, o["fold"] or "")
        if o["stage"] in ("data", "train", "select") and o["task"] != "fundamental":
            raise RlsacError(f"folds --stage {o['stage']} is the fundamental benchmark's (--task essential has tune "
                             "and evaluate only: it reads the fundamental folds' data, its models train with `rlsac "
                             "train --task essential`)")
        if o["stage"] in ("train", "select") and o["regime"] != p["model_regime"]:
            raise RlsacError(f"models are trained on regime {p['model_regime']!r} only (folds.model_regime)")
        if o["stage"] == "select" and o["model"] not in select_runs(p):
            raise RlsacError(f"folds --stage select needs --model, one of {', '.join(select_runs(p)) or 'none'} "
                             "(folds.select_models and their training seeds)")
        models = trained_models(p) + list(derived_models(p))
        if o["stage"] == "train" and o["model"] is not None and o["model"] not in models:
            raise RlsacError(f"unknown model {o['model']!r} (known: {', '.join(models)})")
        if o["points"] is not None:
            if o["stage"] != "data":
                raise RlsacError("folds --points goes with --stage data (the N study's rows name their N: <row>-n<N>)")
            if int(o["points"]) not in p["points"] or o["regime"] not in p["variant_regimes"]:
                raise RlsacError(f"folds --points {o['points']} --regime {o['regime']}: the N study prepares N of "
                                 f"folds.points {p['points']} in folds.variant_regimes {p['variant_regimes']}")
        if o["only"] is not None:
            o["only"] = [s.strip() for s in str(o["only"]).split(",") if s.strip()]
            known = set(rows(p, o["fold"], o["regime"]))
            bad = sorted(set(o["only"]) - known)
            if bad or not o["only"]:
                raise RlsacError(f"--only {bad or o['only']}: not a row of regime {o['regime']!r} (folds.methods, "
                                 "models, lo_methods; variants only in folds.variant_regimes)")
    return o


def data_record(regime: str, fold: str, points: int | None = None) -> Path:
    return Path("reports") / "folds" / "data" / data_regime(regime, points) / f"{fold}.json"


def make_data(p: dict, fundamental: dict, regime: str, fold: str, track: bool,
              points: int | None = None) -> dict[str, Any]:
    """The fold's three files through ``rlsac prepare-cvpr2020`` (same descriptors, seeded selection); ``points``:
    N points per pair instead of fundamental.n_points (Table 3 c), from the same pool."""
    from rlsac.data.tutorial import PrepareConf, collect, prepare
    from rlsac.tracking import check_store

    train_scenes, test_scenes = split_scenes(p, fold)
    d = data_dir(regime, fold, points)
    common = {"root": fundamental.get("raw", "data/raw/strecha"), "split": "all",
              "n_points": int(points or fundamental.get("n_points", 150)),
              "max_pairs_per_scene": int(fundamental.get("max_pairs_per_scene", 0)),
              "pool": int(p["pool"][regime]), "val_fraction": float(p["val_fraction"])}
    confs = {split: PrepareConf(**common, scenes=scenes, holdout=holdout, out=str(d / f"{split}.h5"))
             for split, scenes, holdout in (("train", train_scenes, "train"), ("val", train_scenes, "val"),
                                            ("test", test_scenes, "all"))}
    # the three files' inputs read (a missing scene, a corrupt h5 file or image) and their outputs checked before
    # the first file is written (issue #28, item 2: train and val were written before a test scene was found missing)
    collected = {split: collect(conf, progress=False) for split, conf in confs.items()}
    imported = _import_record(common["root"])
    for path in [c.out for c in confs.values()] + [data_record(regime, fold, points)]:
        check_writable(path)
    check_store(track, "fundamental")
    out = {split: prepare(conf, track=track, progress=False, collected=collected[split])
           for split, conf in confs.items()}
    record = {"regime": regime, "fold": fold, "pool": int(p["pool"][regime]),
              # N only for a variant regime: the default's record stays byte for byte the committed one
              **({"n_points": common["n_points"]} if points else {}),
              "train_scenes": train_scenes,
              "test_scenes": test_scenes, "splits": {k: {key: v[key] for key in (
                  "out", "pairs", "pairs_per_scene", "skipped", "skip_reasons", "mean_gt_inlier_ratio_sampson_2px",
                  "gt_inlier_ratio_quantiles")} for k, v in out.items()},
              "import": imported}
    write_json(data_record(regime, fold, points), record)
    return out


def _import_record(root: str) -> dict[str, Any]:
    """What the import kept and dropped (its summary.json beside the layout), if present."""
    import json

    for path in (Path(root) / "import_summary.json", Path(root) / "all" / "import_summary.json"):
        if path.is_file():
            try:
                s = json.loads(path.read_text())
            except (ValueError, OSError) as e:
                raise RlsacError(f"{path}: not a readable import summary ({e.__class__.__name__})") from None
            if not isinstance(s, dict):
                raise RlsacError(f"{path}: not an import summary (holds a {type(s).__name__})")
            return {k: s[k] for k in ("pairs", "kept", "dropped", "drop_rule", "per_scene") if k in s}
    return {}


def train_options(p: dict, params: dict, regime: str, fold: str, model: str, o: dict) -> dict:
    """`rlsac train`'s options of fold model ``model``: train.fundamental <- folds.train.<model> <- the fold's files."""
    from rlsac.config import deep_update, section

    derived = derived_models(p).get(model, {"recipe": model, "points": None, "seed": None})
    d = data_dir(regime, fold, derived["points"])
    base = section(params, "train", "fundamental")
    recipe = deep_update(base, copy.deepcopy(p["train"][derived["recipe"]] or {}))
    if derived["seed"] is not None:
        recipe["seed"] = derived["seed"]
    return deep_update(recipe, {
        "task": "fundamental", "data": str(d / "train.h5"), "val_data": str(d / "val.h5"),
        "out": str(checkpoint(regime, fold, model)), "device": o["device"], "threads": int(o["threads"]),
        "run_name": f"train folds {regime} {fold} {model}",
        "tags": {"command": "folds", "benchmark": "folds", "regime": regime, "fold": fold, "model": model}})


def train_models(p: dict, params: dict, regime: str, fold: str, models: list[str], o: dict, track: bool) -> dict:
    """Train ``models`` of the fold one after the other; every model's configuration, outputs and the fold's two
    data files are checked before the first one starts (issue #28, item 2). -> {model: train summary}"""
    from rlsac.data.fundamental import read
    from rlsac.train import check, train

    for model in models:
        d = data_dir(regime, fold, derived_models(p).get(model, {"points": None})["points"])
        for split in ("train", "val"):
            if not (d / f"{split}.h5").is_file():
                raise RlsacError(f"{d / f'{split}.h5'}: no such file (run `rlsac folds --stage data` first)")
            read(d / f"{split}.h5")
    options = {m: train_options(p, params, regime, fold, m, o) for m in models}
    for opts in options.values():
        check(opts, track)
    return {m: train(opts, track=track) for m, opts in options.items()}


def _selected(p: dict, fold: str, o: dict, split: str) -> dict[str, dict[str, Any]]:
    """The rows of ``--only`` (every row of the regime without it), their data file (``split``.h5 of their N) and
    checkpoints checked before any work."""
    from rlsac.checkpoint import load_actor

    table = rows(p, fold, o["regime"])
    only = o.get("only") or list(table)
    chosen = {r: table[r] for r in table if r in only}
    for r in chosen.values():
        path = data_dir(o["regime"], fold, r["points"]) / f"{split}.h5"
        if not path.is_file():
            raise RlsacError(f"{path}: no such file (run `rlsac folds --stage data` first)")
    for r in chosen.values():
        if r["checkpoint"] is not None:
            if not Path(r["checkpoint"]).is_file():
                raise RlsacError(f"no checkpoint {r['checkpoint']} (run `rlsac folds --stage train` first)")
            # a file that is not a checkpoint of the row's sampler, or one with non-finite weights, fails here, before
            # the first row's record is written (issue #49: --only a,b rewrote a's record, then failed on b's)
            load_actor(r["checkpoint"], "cpu", kind="ngransac" if r["method"].startswith("ngransac") else "rlsac")
    return chosen


def tune_fold(p: dict, params: dict, regime: str, fold: str, o: dict, track: bool) -> list[dict]:
    """Tune every selected row on the fold's val.h5 (rlsac.tune) -> what was chosen; writes the records."""
    from rlsac import tune
    from rlsac.config import section
    from rlsac.evaluate import check_options, resolve_device, score
    from rlsac.io import write_json
    from rlsac.tasks import task_class
    from rlsac.tracking import start_run

    c = tune.conf(params)
    chosen_rows = _selected(p, fold, o, "val")
    task = p["task"]
    train_scenes, test_scenes = (scene_list(s) for s in split_scenes(p, fold))
    files = {}  # every row's validation file (the N study's rows: their N's) read and checked before any tuning
    for row in chosen_rows.values():
        val = data_dir(regime, fold, row["points"]) / "val.h5"
        if val not in files:
            data, _ = task_class(task).read(val)
            tune.check_scenes(tune.scenes_of(data), train_scenes, test_scenes, str(val))
            files[val] = data
    ev = section(params, "evaluate", task)
    device = resolve_device(o["device"])
    out = []
    for name, row in chosen_rows.items():
        val = data_dir(regime, fold, row["points"]) / "val.h5"
        data, val_scenes = files[val], tune.scenes_of(files[val])
        base = {**row_options(row, p, ev, o), "data": str(val), "iterations": c["iterations"]}

        def run(options, data=data):
            return score(check_options(options), data, device)[0]

        tags = {"benchmark": SUB[task], "regime": regime, "fold": fold, "row": name}
        with start_run(task_class(task).experiment, f"tune {SUB[task]} {regime} {fold} {name}",
                       params={**base, "grid": c},
                       tags=tags, enabled=track) as mlrun:
            best, points = tune.search(run, base, c, row["knobs"])
            top = next(pt for pt in points if pt["settings"] == best)
            record = {"task": task, "regime": regime, "fold": fold, "row": name, "method": row["method"],
                      "checkpoint": base["checkpoint"], "data": str(val), "val_scenes": val_scenes,
                      "val_pairs": int(len(data["pair"])), "iterations": c["iterations"], "seed": int(p["seed"]),
                      "criterion": f"validation {tune.CRITERION}@10deg of max(err_R, err_t)", "chosen": best,
                      "val": {k: top[k] for k in ("mAA", "mAA_R", "mAA_t")}, "grid": points}
            write_json(tune.record_path(regime, fold, name, task), record)
            mlrun.metrics({f"val_{k}": v for k, v in record["val"].items()})
            mlrun.params({f"chosen.{k}": v for k, v in best.items()})
        out.append({"row": name, "chosen": best, **record["val"]})
    return out


def tuned_settings(ev: dict, regime: str, fold: str, name: str, train_scenes: list[str], test_scenes: list[str],
                   task: str = "fundamental") -> dict[str, Any]:
    """Row ``name``'s settings from its tuning record (chosen on the fold's validation pairs only, checked against
    the test scenes) as evaluate options."""
    from rlsac import tune
    from rlsac.results import read_record

    path = tune.record_path(regime, fold, name, task)
    rec = read_record(path)  # `[]`, `null`, `chosen: {}`, `val_scenes: []` are refused by name (issue #49)
    if rec is None:
        raise RlsacError(f"{path}: no tuning record (run `rlsac folds --stage tune` first)")
    return tune.as_options(tune.check_record(rec, path, regime, fold, name, train_scenes, test_scenes), ev.get("lo"))


def evaluate_fold(p: dict, params: dict, regime: str, fold: str, o: dict, track: bool) -> list[dict]:
    """Every selected row at every budget on the fold's test file, with the settings of its tuning record
    (rlsac.tune: chosen on the fold's validation pairs only, checked against the test scenes here)."""
    from rlsac.config import section
    from rlsac.evaluate import check_all, evaluate

    chosen_rows = _selected(p, fold, o, "test")
    train_scenes, test_scenes = (scene_list(s) for s in split_scenes(p, fold))
    task = p["task"]
    ev = section(params, "evaluate", task)
    # every record read and checked before the first evaluation
    settings = {name: tuned_settings(ev, regime, fold, name, train_scenes, test_scenes, task) for name in chosen_rows}
    jobs = []
    for name, row in chosen_rows.items():
        for it in p["iterations"][regime]:
            tags = {"benchmark": SUB[task], "regime": regime, "fold": fold, "model": name}
            test = data_dir(regime, fold, row["points"]) / "test.h5"
            jobs.append((name, int(it), {**row_options(row, p, ev, o), **settings[name], "data": str(test),
                                         "iterations": int(it), "out_dir": str(eval_dir(regime, fold, name, it, task)),
                                         "tags": tags}))
    # every evaluation checked (its checkpoint loaded, the test file read) before the first one writes anything
    check_all([opts for _, _, opts in jobs], track)
    out = []
    for name, it, opts in jobs:
        s = evaluate(opts, track=track)
        out.append({"method": name, "iterations": it, "mAA_R": s["mAA_R"], "mAA_t": s["mAA_t"],
                    "seconds": round(s["seconds"], 1)})
    return out


def folds(options: dict[str, Any], track: bool = True) -> dict[str, Any]:
    """Run one stage of one (regime, fold); -> a summary of what was written where."""
    from rlsac.config import read_params, section

    o = check_options(options)
    params = read_params(o["params"])
    p = for_task(protocol(params), params, o["task"])
    o = check_options(options, p)
    if int(o["threads"]) > 0:
        import torch

        torch.set_num_threads(int(o["threads"]))
    t0 = time.time()
    regime, fold = o["regime"], o["fold"]
    result: dict[str, Any] = {"stage": o["stage"], "task": o["task"], "regime": regime, "fold": fold}
    if o["stage"] == "data":
        made = make_data(p, section(params, "fundamental"), regime, fold, track, o["points"])
        result["files"] = {k: {"out": v["out"], "pairs": v["pairs"], "skipped": v["skip_reasons"],
                               "mean_gt_inlier_ratio": v["mean_gt_inlier_ratio_sampson_2px"]}
                           for k, v in made.items()}
    elif o["stage"] == "train":
        models = [o["model"]] if o["model"] else trained_models(p) + list(derived_models(p))
        result["models"] = train_models(p, params, regime, fold, models, o, track)
    elif o["stage"] == "tune":
        result["tuned"] = tune_fold(p, params, regime, fold, o, track)
    elif o["stage"] == "select":
        from rlsac.selection import select_fold

        result["selection"] = select_fold(p, params, regime, fold, o["model"], o, track)
    else:
        result["evaluations"] = evaluate_fold(p, params, regime, fold, o, track)
    result["seconds"] = round(time.time() - t0, 1)
    return result


def format_summary(s: dict[str, Any]) -> str:
    from rlsac import tune

    head = f"folds {s['stage']} {s['regime']}/{s['fold']} ({s['seconds']} s): "
    if s["stage"] == "data":
        return head + "; ".join(f"{k} {v['pairs']} pairs, inlier ratio {v['mean_gt_inlier_ratio']:.2f} -> {v['out']}"
                                for k, v in s["files"].items())
    if s["stage"] == "train":
        return head + "; ".join(f"{m} -> {v['checkpoint']} (best {v['selection']} {v['best_score']:.3f} at step "
                                f"{v['best_step']})" for m, v in s["models"].items())
    if s["stage"] == "tune":
        return head + "; ".join(f"{t['row']}: {t['chosen']} (val mAA {t['mAA']:.3f})" for t in s["tuned"]) + (
            f" -> {tune.record_path(s['regime'], s['fold'], '-', s['task']).parent}")
    if s["stage"] == "select":
        sel = s["selection"]
        return head + f"{sel['model']}: kept step {sel['kept_step']} of {sel['steps']}; " + "; ".join(
            f"step {st} " + ", ".join(f"@{it} R {m['mAA_R']:.3f} t {m['mAA_t']:.3f}" for it, m in per.items())
            for st, per in sel["test"].items()) + f" -> {', '.join(sel['files'])}"
    return head + "; ".join(f"{e['method']}@{e['iterations']} R {e['mAA_R']:.3f} t {e['mAA_t']:.3f}"
                            for e in s["evaluations"]) + (
        f" -> {eval_dir(s['regime'], s['fold'], '-', 1, s['task']).parent.parent}")
