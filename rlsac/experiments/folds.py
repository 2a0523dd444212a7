"""The runner of the leave-one-building-out benchmark (``rlsac folds``, params.yaml ``folds``): its data, train, tune,
evaluate and select stages of one fold. Its vocabulary (rows, names, paths) is rlsac.layout.protocol's.

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
    pool      data/folds/pool/<fold>.h5: the fold's training pairs with the model regime's pool size as points per
              pair, what the models of folds.pool_models redraw their episodes from (rlsac.rl.episodes)
    train     checkpoints/folds/<regime>/<fold>/<model>.pt
    evaluate  reports/eval/folds/<regime>/<fold>/<method>/i<iterations>/{errors.csv,summary.json}
    retune    reports/retune/fundamental/<regime>/<fold>/<row>.json (issue #47 item 7 b, rlsac.experiments.folds_retune)
With --tune-iterations N, tune and evaluate tune at N and test at N alone (issue #47 item 7 a): records
reports/tuning_at<N>/, results reports/eval/folds_at<N>/, beside the tables' own.
The data stage also writes reports/folds/data/<regime>/<fold>.json (pairs, dropped pairs and why, ground-truth
inlier-ratio distribution per split): the tables read that record, never data/ itself.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError
from rlsac.evaluation.tune import tuned_settings  # noqa: F401
from rlsac.io import check_writable, write_json

# the benchmark's vocabulary (rlsac.layout.protocol), and the tuned settings' reader (rlsac.evaluation.tune); also
# re-exported for the callers of rlsac.experiments.folds (rlsac.experiments.scale, the tests)
from rlsac.layout.protocol import (  # noqa: F401
    DEFAULTS,
    FOLD_STAGES,
    OUR_SAMPLERS,
    SUB,
    at_suffix,
    budgets,
    checkpoint,
    checkpoint_model,
    data_dir,
    data_record,
    data_regime,
    derived_models,
    eval_dir,
    fill_fold,
    model_method,
    points_name,
    pool_file,
    read,
    row_options,
    rows,
    scene_list,
    seed_name,
    select_runs,
    split_points,
    split_scenes,
    split_seed,
    train_options,
    trained_models,
    variants,
)

STAGES = FOLD_STAGES
OPTIONS: dict[str, Any] = {"stage": None, "regime": None, "fold": None, "model": None, "only": None, "points": None,
                           "task": "fundamental", "tune_iterations": None,
                           "params": "params.yaml",
                           "device": "auto", "threads": 1}


def protocol(params: dict[str, Any]) -> dict[str, Any]:
    """``DEFAULTS`` with each key replaced by params.yaml ``folds``'s, checked for consistency
    (rlsac.layout.protocol.read),
    its rows' methods against `rlsac evaluate`'s and each model's recipe a TrainConf."""
    from rlsac.config import build
    from rlsac.evaluation.methods import METHODS
    from rlsac.learners.harness import TrainConf

    return read(params, METHODS, lambda recipe, where: build(TrainConf, recipe, where))


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
    from rlsac.evaluation.methods import METHODS

    given = check_mapping(section(params, "fundamental"), dict.fromkeys(FUNDAMENTAL), "fundamental", FUNDAMENTAL,
                          FUNDAMENTAL_RANGES)
    for split, scenes in (given.get("scenes") or {}).items():
        check_value(f"fundamental.scenes.{split}", scenes, str)
    if given.get("methods"):
        check_range("fundamental.methods", given["methods"], METHODS)


ESSENTIAL = {"regime": "hard", "methods": ["uniform", "ransac", "opencv_ransac", "usac", "magsac"],
             "iterations": [100, 1000], "seeds": []}  # seeds: RLSAC's other training seeds (rows rlsac-s<seed>)


def check_essential(params: dict[str, Any]) -> dict[str, Any]:
    """params.yaml ``essential`` (Table E): a regime of folds.regimes, methods of `rlsac evaluate`, budgets
    -> the section over ``ESSENTIAL``."""
    from rlsac.config import check_mapping, check_range, section
    from rlsac.evaluation.methods import METHODS

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
    from rlsac.tasks import TASKS

    benchmarked = [n for n, cls in TASKS.items() if cls.fold_rows]
    if task not in benchmarked:
        raise RlsacError(f"folds --task must be {' or '.join(benchmarked)}, got {task!r}")
    cls = TASKS[task]
    layout = {"task": task, "fold_stages": list(cls.fold_stages), "fold_checkpoint": cls.fold_checkpoint,
              "sampler_knobs": list(cls.sampler_knobs)}
    if cls.fold_rows == "folds":  # the protocol's own rows
        return {**p, **layout}
    e = check_essential(params)  # Table E's rows (params essential)
    return {**p, **layout, "methods": list(e["methods"]), "models": ["rlsac"], "lo_models": [], "fast": [],
            "lo_methods": [], "variant_regimes": [e["regime"]], "ablation_models": [], "prob_models": [],
            "points": [], "points_models": [], "points_methods": [], "seeds": list(e["seeds"]),
            "seed_models": ["rlsac"], "select_models": [], "pool_models": [], "file_models": ["rlsac"],
            "file_seed_models": ["rlsac"],
            "regimes": [e["regime"]], "model_regime": e["regime"], "iterations": {e["regime"]: list(e["iterations"])}}


def check_options(options: dict[str, Any], p: dict[str, Any] | None = None) -> dict[str, Any]:
    from rlsac.config import check_value

    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise RlsacError(f"unknown folds option(s) {unknown}; known: {sorted(OPTIONS)}")
    o = {**OPTIONS, **{k: v for k, v in options.items() if v is not None}}
    if o["stage"] not in STAGES:
        raise RlsacError(f"folds --stage must be one of {', '.join(STAGES)}, got {o['stage']!r}")
    if p is not None:
        if o["stage"] == "pool":  # one pool per fold: the model regime's pool size (its models train on that regime)
            if o["regime"] not in (None, p["model_regime"]):
                raise RlsacError(f"folds --stage pool prepares the pool of folds.model_regime {p['model_regime']!r} "
                                 f"(leave --regime out), got --regime {o['regime']!r}")
            o["regime"] = p["model_regime"]
        if o["regime"] is None:
            raise RlsacError(f"folds --stage {o['stage']} needs --regime (one of {', '.join(p['regimes'])})")
        if o["regime"] not in p["regimes"]:
            raise RlsacError(f"unknown regime {o['regime']!r} (known: {', '.join(p['regimes'])})")
        split_scenes(p, o["fold"] or "")
        has = p.get("fold_stages", STAGES)  # the task's (for_task); a protocol without it: every stage
        if o["stage"] not in has:
            raise RlsacError(f"folds --stage {o['stage']}: --task {o['task']} has {' and '.join(has)} only (it reads "
                             f"the fundamental folds' data, its models train with `rlsac train --task {o['task']}`)")
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
        if o["tune_iterations"] is not None:
            # issue #47 item 7 (a): tune at the budget the row is tested at (the tutorial's protocol), beside the
            # tables' rows tuned at tuning.iterations; a budget the regime is not tested at would test nothing
            o["tune_iterations"] = check_value("--tune-iterations", o["tune_iterations"], int, "[1, inf)")
            if o["stage"] not in ("tune", "evaluate"):
                raise RlsacError("folds --tune-iterations goes with --stage tune or evaluate")
            if o["tune_iterations"] not in p["iterations"][o["regime"]]:
                raise RlsacError(f"folds --tune-iterations {o['tune_iterations']}: not a test budget of regime "
                                 f"{o['regime']!r} (folds.iterations {p['iterations'][o['regime']]})")
        if o["only"] is not None:
            o["only"] = [s.strip() for s in str(o["only"]).split(",") if s.strip()]
            known = set(rows(p, o["fold"], o["regime"]))
            bad = sorted(set(o["only"]) - known)
            if bad or not o["only"]:
                raise RlsacError(f"--only {bad or o['only']}: not a row of regime {o['regime']!r} (folds.methods, "
                                 "models, lo_methods; variants only in folds.variant_regimes)")
    return o


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


def prepare_pool(p: dict, params: dict, fold: str, n_points: int, out: str | Path, track: bool) -> dict[str, Any]:
    """The fold's training pairs (the train holdout of its training buildings) prepared again with ``n_points`` points
    per pair (the ``n_points`` lowest-SNN matches, descriptors included) into ``out``: the pool redrawn episodes draw
    from (rlsac.rl.episodes). The fold benchmark's pools (``make_pool``) and the scale study's
    (rlsac.experiments.scale) -> prepare's
    summary."""
    from rlsac.config import section
    from rlsac.data.tutorial import PrepareConf, prepare

    fundamental = section(params, "fundamental")
    train_scenes, _ = split_scenes(p, fold)
    conf = PrepareConf(root=fundamental.get("raw", "data/raw/strecha"), split="all", scenes=train_scenes,
                       n_points=int(n_points), pool=0, holdout="train", val_fraction=float(p["val_fraction"]),
                       max_pairs_per_scene=int(fundamental.get("max_pairs_per_scene", 0)), out=str(out))
    return prepare(conf, track=track, progress=False)


def make_pool(p: dict, params: dict, fold: str, track: bool) -> dict[str, Any]:
    """``rlsac folds --stage pool``: the fold's pool file (``pool_file``) with folds.pool of the model regime as points
    per pair (the matches its training file's points were drawn from) -> {pool, pairs, points}."""
    n = int(p["pool"][p["model_regime"]])
    if n <= 0:
        raise RlsacError(f"folds.pool.{p['model_regime']} = {n}: the model regime keeps no pool of matches to prepare "
                         "(folds --stage pool needs folds.model_regime's pool size > 0)")
    made = prepare_pool(p, params, fold, n, pool_file(fold), track)
    return {"pool": made["out"], "pairs": made["pairs"], "points": n}


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


def train_models(p: dict, params: dict, regime: str, fold: str, models: list[str], o: dict, track: bool) -> dict:
    """Train ``models`` of the fold one after the other; every model's configuration, outputs and the fold's two
    data files are checked before the first one starts (issue #28, item 2). -> {model: train summary}"""
    from rlsac.data.fundamental import read
    from rlsac.evaluation.train import train
    from rlsac.learners.harness import check, saved_step

    for model in models:
        d = data_dir(regime, fold, derived_models(p).get(model, {"points": None})["points"])
        for split in ("train", "val"):
            if not (d / f"{split}.h5").is_file():
                raise RlsacError(f"{d / f'{split}.h5'}: no such file (run `rlsac folds --stage data` first)")
            read(d / f"{split}.h5")
    options = {m: train_options(p, params, regime, fold, m, o) for m in models}
    for m, opts in options.items():
        pool = (opts.get("episodes") or {}).get("pool")
        if pool and not Path(pool).is_file():
            raise RlsacError(f"{pool}: no pool file for model {m} (run `rlsac folds --stage pool --fold {fold}` first)")
    confs = {m: check(opts, track) for m, opts in options.items()}  # every model checked before the first trains
    for m, opts in options.items():
        # a run of this very recipe stopped part-way (SIGTERM at a session's end saves its state): resume it, which
        # gives the uninterrupted run's bytes; a finished state or another recipe's trains from the start as before
        if 0 < saved_step(opts) < confs[m].sac.total_steps:
            opts["resume"] = True
    return {m: train(opts, track=track) for m, opts in options.items()}


def _selected(p: dict, fold: str, o: dict, split: str) -> dict[str, dict[str, Any]]:
    """The rows of ``--only`` (every row of the regime without it), their data file (``split``.h5 of their N) and
    checkpoints checked before any work."""
    from rlsac.rl.checkpoint import load_actor

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


def threshold_only(c: dict, record: dict) -> dict:
    """The tuning grid ``c`` with the pre-filter fixed at ``record``'s choice (a tables' tuning record): a learned row
    re-tuned at its test budget re-chooses its threshold alone (params tuning_budget.learned: its grid runs the
    network at every point); its knobs stay the record's too."""
    pre = record["chosen"].get("prefilter", 1.0)
    return {**c, "prefilter": [pre], "start_prefilter": pre, "extend_prefilter": False, "rounds": 1}


def tuned_record(regime: str, fold: str, row: str, task: str, train_scenes, test_scenes) -> dict:
    """The tables' tuning record of ``row`` (reports/tuning/...), read and checked as the evaluation reads it."""
    from rlsac.evaluation import tune
    from rlsac.evaluation.results import read_record

    path = tune.record_path(regime, fold, row, task)
    rec = read_record(path)
    if rec is None:
        raise RlsacError(f"{path}: no tuning record (a learned row re-tuned at the test budget keeps its pre-filter: "
                         "run `rlsac folds --stage tune` first)")
    return {**rec, "chosen": tune.check_record(rec, path, regime, fold, row, train_scenes, test_scenes)}


def tune_fold(p: dict, params: dict, regime: str, fold: str, o: dict, track: bool) -> list[dict]:
    """Tune every selected row on the fold's val.h5 (rlsac.evaluation.tune) -> what was chosen; writes the records."""
    from rlsac.config import section
    from rlsac.evaluation import tune
    from rlsac.evaluation.evaluate import check_options, make_estimator, resolve_device, score
    from rlsac.io import write_json
    from rlsac.tasks import task_class
    from rlsac.tracking import start_run

    c = tune.conf(params)
    at = o.get("tune_iterations")  # None: the tables' budget, tuning.iterations
    c["iterations"] = c["iterations"] if at is None else at
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
    bases = {name: {**row_options(row, p, ev, o), "data": str(data_dir(regime, fold, row["points"]) / "val.h5"),
                    "iterations": c["iterations"]} for name, row in chosen_rows.items()}
    if at is not None:  # a learned row re-tuned at the test budget re-chooses its threshold alone (threshold_only)
        bad = [n for n, r in chosen_rows.items() if r["checkpoint"] is not None and r["knobs"]]
        if bad:
            raise RlsacError(f"folds --tune-iterations: learned rows with knobs of their own ({', '.join(bad)}) would "
                             "need them fixed at the tables' choice too; re-tune them at tuning.iterations")
    for base in bases.values():  # every row's sampler built before the first record is written: a checkpoint whose
        make_estimator(check_options(base), device)  # 'kind' does not match its weights failed in its row (#49)
    out = []
    for name, row in chosen_rows.items():
        val = data_dir(regime, fold, row["points"]) / "val.h5"
        data, val_scenes = files[val], tune.scenes_of(files[val])
        base = bases[name]

        def run(options, data=data):
            return score(check_options(options), data, device)[0]

        grid, knobs = c, row["knobs"]
        if at is not None and row["checkpoint"] is not None:  # a learned row at the test budget: its threshold alone
            grid = threshold_only(c, tuned_record(regime, fold, name, task, train_scenes, test_scenes))

        tags = {"benchmark": SUB[task], "regime": regime, "fold": fold, "row": name}
        with start_run(task_class(task).experiment, f"tune {SUB[task]}{at_suffix(at)} {regime} {fold} {name}",
                       params={**base, "grid": c},
                       tags=tags, enabled=track) as mlrun:
            best, points = tune.search(run, base, grid, knobs)
            top = next(pt for pt in points if pt["settings"] == best)
            record = {"task": task, "regime": regime, "fold": fold, "row": name, "method": row["method"],
                      "checkpoint": base["checkpoint"], "data": str(val), "val_scenes": val_scenes,
                      "val_pairs": int(len(data["pair"])), "iterations": grid["iterations"], "seed": int(p["seed"]),
                      "criterion": f"validation {tune.CRITERION}@10deg of max(err_R, err_t)", "chosen": best,
                      "val": {k: top[k] for k in ("mAA", "mAA_R", "mAA_t")}, "grid": points}
            write_json(tune.record_path(regime, fold, name, task, at), record)
            mlrun.metrics({f"val_{k}": v for k, v in record["val"].items()})
            mlrun.params({f"chosen.{k}": v for k, v in best.items()})
        out.append({"row": name, "chosen": best, **record["val"]})
    return out


def evaluate_fold(p: dict, params: dict, regime: str, fold: str, o: dict, track: bool) -> list[dict]:
    """Every selected row at every budget on the fold's test file, with the settings of its tuning record
    (rlsac.evaluation.tune: chosen on the fold's validation pairs only, checked against the test scenes here)."""
    from rlsac.config import section
    from rlsac.evaluation.evaluate import check_all, evaluate

    chosen_rows = _selected(p, fold, o, "test")
    train_scenes, test_scenes = (scene_list(s) for s in split_scenes(p, fold))
    task = p["task"]
    ev = section(params, "evaluate", task)
    at = o.get("tune_iterations")  # rows tuned at this budget are tested at it alone (their own folder)
    # every record read and checked before the first evaluation
    settings = {name: tuned_settings(ev, regime, fold, name, train_scenes, test_scenes, task, at)
                for name in chosen_rows}
    jobs = []
    for name, row in chosen_rows.items():
        for it in p["iterations"][regime] if at is None else [at]:
            tags = {"benchmark": SUB[task] + at_suffix(at), "regime": regime, "fold": fold, "model": name}
            test = data_dir(regime, fold, row["points"]) / "test.h5"
            jobs.append((name, int(it), {**row_options(row, p, ev, o), **settings[name], "data": str(test),
                                         "iterations": int(it),
                                         "out_dir": str(eval_dir(regime, fold, name, it, task, at)),
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
    result: dict[str, Any] = {"stage": o["stage"], "task": o["task"], "regime": regime, "fold": fold,
                              "tuned_at": o["tune_iterations"]}
    if o["stage"] == "data":
        made = make_data(p, section(params, "fundamental"), regime, fold, track, o["points"])
        result["files"] = {k: {"out": v["out"], "pairs": v["pairs"], "skipped": v["skip_reasons"],
                               "mean_gt_inlier_ratio": v["mean_gt_inlier_ratio_sampson_2px"]}
                           for k, v in made.items()}
    elif o["stage"] == "pool":
        result["pool"] = make_pool(p, params, fold, track)
    elif o["stage"] == "train":
        models = [o["model"]] if o["model"] else trained_models(p) + list(derived_models(p))
        result["models"] = train_models(p, params, regime, fold, models, o, track)
    elif o["stage"] == "tune":
        result["tuned"] = tune_fold(p, params, regime, fold, o, track)
    elif o["stage"] == "select":
        from rlsac.experiments.selection import select_fold

        result["selection"] = select_fold(p, params, regime, fold, o["model"], o, track)
    elif o["stage"] == "retune":
        from rlsac.experiments.folds_retune import retune_fold

        result["retuned"] = retune_fold(p, params, regime, fold, o)
    else:
        result["evaluations"] = evaluate_fold(p, params, regime, fold, o, track)
    result["seconds"] = round(time.time() - t0, 1)
    return result


def _kept(train: dict[str, Any]) -> str:
    """Which actor a training kept: the last one (selection: last, no score to report), or the best by its rule."""
    if train["selection"] == "last":
        return f"the last actor, step {train['steps']}"
    return f"best {train['selection']} {train['best_score']:.3f} at step {train['best_step']}"


def format_summary(s: dict[str, Any]) -> str:
    from rlsac.evaluation import tune

    head = f"folds {s['stage']} {s['regime']}/{s['fold']} ({s['seconds']} s): "
    if s["stage"] == "data":
        return head + "; ".join(f"{k} {v['pairs']} pairs, inlier ratio {v['mean_gt_inlier_ratio']:.2f} -> {v['out']}"
                                for k, v in s["files"].items())
    if s["stage"] == "pool":
        return head + f"{s['pool']['pairs']} training pairs, {s['pool']['points']} points each -> {s['pool']['pool']}"
    if s["stage"] == "train":
        return head + "; ".join(f"{m} -> {v['checkpoint']} ({_kept(v)})" for m, v in s["models"].items())
    if s["stage"] == "tune":
        return head + "; ".join(f"{t['row']}: {t['chosen']} (val mAA {t['mAA']:.3f})" for t in s["tuned"]) + (
            f" -> {tune.record_path(s['regime'], s['fold'], '-', s['task'], s.get('tuned_at')).parent}")
    if s["stage"] == "retune":
        return head + "; ".join(f"{r['row']}: {r['distinct']} setting(s) chosen in {r['draws']} draws" for r in
                                s["retuned"]) + f" -> {', '.join(r['file'] for r in s['retuned'])}"
    if s["stage"] == "select":
        sel = s["selection"]
        return head + f"{sel['model']}: kept step {sel['kept_step']} of {sel['steps']}; " + "; ".join(
            f"step {st} " + ", ".join(f"@{it} R {m['mAA_R']:.3f} t {m['mAA_t']:.3f}" for it, m in per.items())
            for st, per in sel["test"].items()) + f" -> {', '.join(sel['files'])}"
    return head + "; ".join(f"{e['method']}@{e['iterations']} R {e['mAA_R']:.3f} t {e['mAA_t']:.3f}"
                            for e in s["evaluations"]) + (
        f" -> {eval_dir(s['regime'], s['fold'], '-', 1, s['task'], s.get('tuned_at')).parent.parent}")
