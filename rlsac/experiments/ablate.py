"""``rlsac ablate``: the ablation studies of the paper (Sec. 5): Table 3 and Table 1's Ours-0.5.

Studies (``what``):

    descriptors     (a) no_descriptors vs full
    sampling        (b) train_max-test_max, train_max-test_prob, train_prob-test_prob vs full
    points          (c) n100, n200, n300 vs full
    all             (a) + (b) + (c): every Table 3 row
    generalisation  Ours-0.5 of Table 1: checkpoints/line_o0.5.pt on every outlier rate

Table 3 is built from two lists in params.yaml ``ablation`` (the code defaults below are the same):

* ``models``: checkpoints ``<ckpt_dir>/ablation/<name>.pt``, each trained with ``train.fundamental``
  <- ``ablation.train`` (the budget shared by every ablation model) <- the model's ``train`` overrides,
  on ``<data_dir>/{train,val}<suffix>.h5``;
* ``variants``: rows of the table, ``reports/eval/ablation/<name>/``: a model (``full`` =
  ``checkpoints/fundamental.pt``, the paper's model) evaluated at ``ablation.iterations`` on
  ``<data_dir>/test<suffix>.h5`` with test-time ``sampling`` max or prob.

For each selected variant, its model is trained unless the checkpoint exists (``force`` retrains),
then it is evaluated; every MLflow run is tagged ``{"ablation": what, "variant": name}`` so the UI can
put them side by side. Finally Table 3 is rebuilt when ``rlsac.reports.tables`` is available.

Options (all optional but ``what``):

    what        descriptors | sampling | points | all | generalisation
    stage       "all" (train missing models, evaluate, rebuild the table), "train", or "evaluate"
    variants    names (list or comma string) restricting the variants; default: the whole study
    models      names restricting the models trained in stage "train"; default: those of the variants
    force       retrain a model even if its checkpoint exists (False)
    train_steps override sac.total_steps of every model trained here
    threads     torch CPU threads for training and evaluation (0 = torch's default)
    device      auto | cpu | cuda
    params      params.yaml path ("params.yaml")
    data_dir, lines_dir, ckpt_dir, eval_dir   default data/fundamental, data/lines, checkpoints, reports/eval
    table       rebuild the table at the end of stage "all" (True)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError

STUDIES = ("descriptors", "sampling", "points")
WHATS = STUDIES + ("all", "generalisation")
STAGES = ("all", "train", "evaluate")
FULL = "full"  # the paper's model, checkpoints/fundamental.pt: the reference row of every study
# Table 3 on the leave-one-building-out folds (issue #26): each study's DVC stages, as fnmatch patterns of stage names
# (`rlsac pipeline` and `dvc repro --glob` take them), then `tables`. The 87-pair split this command trains and
# evaluates on is retired (issue #25): no stage makes its data any more, so without them ablate prints these
FOLD_STUDIES = {
    "descriptors": ("fold_*_ablation*@*-rlsac-nodesc*",),  # (a): rlsac-nodesc and its training seeds
    "sampling": ("fold_*_ablation*@*-rlsac-trainmax*", "fold_*_prob*@*"),  # (b): max in training; prob. at test
    "points": ("fold_*_points*@*",),  # (c): the data with N points, a model and the uniform control per N
}

# Same as params.yaml ``ablation`` (which overrides each top-level key as a whole).
DEFAULTS: dict[str, Any] = {
    "iterations": 1000,
    "seed": 0,
    "train": {},
    "n_points": [100, 200, 300],
    "generalisation": {"train_rate": 0.5},
    "models": {
        "no_descriptors": {"study": "descriptors", "suffix": "", "train": {"task_options": {"use_descriptors": False}}},
        "train_max": {"study": "sampling", "suffix": "", "train": {"sac": {"train_sampling": "max"}}},
        "n100": {"study": "points", "suffix": "_n100", "train": {}},
        "n200": {"study": "points", "suffix": "_n200", "train": {}},
        "n300": {"study": "points", "suffix": "_n300", "train": {}},
    },
    "variants": {
        "no_descriptors": {"study": "descriptors", "model": "no_descriptors", "sampling": "max", "suffix": ""},
        "full": {"study": "all", "model": FULL, "sampling": "max", "suffix": ""},
        "train_max-test_max": {"study": "sampling", "model": "train_max", "sampling": "max", "suffix": ""},
        "train_max-test_prob": {"study": "sampling", "model": "train_max", "sampling": "prob", "suffix": ""},
        "train_prob-test_prob": {"study": "sampling", "model": FULL, "sampling": "prob", "suffix": ""},
        "n100": {"study": "points", "model": "n100", "sampling": "max", "suffix": "_n100"},
        "n200": {"study": "points", "model": "n200", "sampling": "max", "suffix": "_n200"},
        "n300": {"study": "points", "model": "n300", "sampling": "max", "suffix": "_n300"},
    },
}

OPTIONS: dict[str, Any] = {
    "what": None, "stage": "all", "variants": None, "models": None, "force": False, "train_steps": None,
    "threads": 0, "device": "auto", "params": "params.yaml", "data_dir": "data/fundamental",
    "lines_dir": "data/lines", "ckpt_dir": "checkpoints", "eval_dir": "reports/eval", "table": True,
    "full": False, "fold": "fountain", "iterations": 1000, "out": "scratch/ablate", "workers": None,
}
# The quick study on the folds (issue #63 item 4): one fold's test pairs (fountain: the smallest, 42 pairs), the
# committed checkpoints and tuning records, Table 2's budget (1000 iterations); each study's rows against the full
# model (rlsac.experiments.quick). The points study needs its own data (N points per pair): --full only.
QUICK_ROWS = {"descriptors": ["rlsac-nodesc"], "sampling": ["rlsac-trainmax", "rlsac-trainmax-prob", "rlsac-prob"]}
QUICK_REFERENCE, QUICK_REGIME = "rlsac", "hard"  # Table 3's reference row and regime (reports/table3_folds.md)
RECORD = "reports/table3_folds.md"


def _names(v) -> list[str] | None:
    if v is None or v == "":
        return None
    if isinstance(v, str):
        return [s.strip() for s in v.split(",") if s.strip()]
    return [str(s) for s in v]


def check_options(options: dict[str, Any]) -> dict[str, Any]:
    from rlsac.config import check_mapping

    options = check_mapping(options, OPTIONS, "ablate",  # types and ranges, as rlsac.config.build does
                            types={"train_steps": int, "variants": str | list[str], "models": str | list[str],
                                   "iterations": int, "workers": int},
                            ranges={"threads": "[0, inf)", "device": ("auto", "cpu", "cuda"), "iterations": "[1, inf)",
                                    "workers": "[1, inf)"})
    o = {**OPTIONS, **{k: v for k, v in options.items() if v is not None}}
    if o["what"] not in WHATS:
        raise RlsacError(f"ablate --what must be one of {', '.join(WHATS)}, got {o['what']!r}")
    if o["stage"] not in STAGES:
        raise RlsacError(f"ablate stage must be one of {', '.join(STAGES)}, got {o['stage']!r}")
    if o["train_steps"] is not None and int(o["train_steps"]) <= 0:
        raise RlsacError(f"train_steps must be positive, got {o['train_steps']}")
    o["variants"], o["models"] = _names(o["variants"]), _names(o["models"])
    return o


MODEL_KEYS = {"study": str, "suffix": str, "train": dict}  # ablation.models.<name>
VARIANT_KEYS = {"study": str, "model": str, "sampling": str, "suffix": str, "checkpoint": str}  # .variants.<name>


def protocol(params: dict[str, Any]) -> dict[str, Any]:
    """``DEFAULTS`` with each top-level key replaced by params.yaml ``ablation``'s, every key typed and checked
    (issue #28, item 3), each model's training recipe a valid TrainConf."""
    from rlsac.config import SEED_RANGE, build, check_mapping, check_value, deep_update, over_defaults, section
    from rlsac.learners.harness import TrainConf

    p = over_defaults(params, "ablation", DEFAULTS)
    p["iterations"] = check_value("ablation.iterations", p["iterations"], int, "[1, inf)")
    p["seed"] = check_value("ablation.seed", p["seed"], int, SEED_RANGE)
    p["n_points"] = check_value("ablation.n_points", p["n_points"], list[int], "[8, inf)")
    p["generalisation"] = check_mapping(check_value("ablation.generalisation", p["generalisation"], dict),
                                        {"train_rate": 0.5}, "ablation.generalisation", ranges={"train_rate": "[0, 1)"})
    p["train"] = check_value("ablation.train", p["train"], dict)
    for key, keys in (("models", MODEL_KEYS), ("variants", VARIANT_KEYS)):
        p[key] = check_value(f"ablation.{key}", p[key], dict)
        for name, spec in p[key].items():
            check_mapping(check_value(f"ablation.{key}.{name}", spec, dict), dict.fromkeys(keys),
                          f"ablation.{key}.{name}", keys)
    base = {**section(params, "train", "fundamental"), "task": "fundamental"}
    for name, m in p["models"].items():
        if m.get("study") not in STUDIES:
            raise RlsacError(f"ablation.models.{name}.study must be one of {', '.join(STUDIES)}")
        build(TrainConf, deep_update(deep_update(base, p["train"]), m.get("train") or {}), f"ablation.models.{name}")
    for name, v in p["variants"].items():
        if v.get("study") not in STUDIES + ("all",):
            raise RlsacError(f"ablation.variants.{name}.study must be one of {', '.join(STUDIES)}, all")
        if v.get("model") != FULL and v.get("model") not in p["models"]:
            raise RlsacError(f"ablation.variants.{name}.model {v.get('model')!r} is not in ablation.models")
        if v.get("sampling", "max") not in ("max", "prob"):
            raise RlsacError(f"ablation.variants.{name}.sampling must be max or prob")
    return p


def model_checkpoint(model: str, ckpt_dir: str | Path = "checkpoints") -> Path:
    """full -> <ckpt_dir>/fundamental.pt (the paper's model), else <ckpt_dir>/ablation/<model>.pt."""
    return Path(ckpt_dir) / ("fundamental.pt" if model == FULL else f"ablation/{model}.pt")


def variant_checkpoint(v: dict[str, Any], ckpt_dir: str | Path = "checkpoints") -> Path:
    """The variant's ``checkpoint`` from params.yaml (relative to the default checkpoints/ folder, re-rooted
    under ``ckpt_dir``), else its model's."""
    given = v.get("checkpoint")
    if not given:
        return model_checkpoint(v["model"], ckpt_dir)
    path = Path(given)
    if not path.is_absolute() and path.parts[:1] == ("checkpoints",):
        path = Path(ckpt_dir, *path.parts[1:])
    return path


def _rate(r) -> str:
    return f"{float(r):g}"


# ------------------------------------------------------------------------------------------ the plan


def plan(o: dict[str, Any], params: dict[str, Any]) -> dict[str, Any]:
    """-> {"models": {name: train options or None (the reference)}, "variants": {name: evaluate options}}"""
    if o["what"] == "generalisation":
        return _plan_generalisation(o, params)
    from rlsac.config import deep_update, section

    p = protocol(params)
    data, ckpts, evals = Path(o["data_dir"]), Path(o["ckpt_dir"]), Path(o["eval_dir"]) / "ablation"
    chosen = {n: v for n, v in p["variants"].items() if o["what"] == "all" or v["study"] in (o["what"], "all")}
    if o["variants"]:
        missing = [n for n in o["variants"] if n not in chosen]
        if missing:
            raise RlsacError(f"variant(s) {missing} not in ablation '{o['what']}' (known: {', '.join(chosen)})")
        chosen = {n: chosen[n] for n in o["variants"]}
    wanted = o["models"] or sorted({v["model"] for v in chosen.values()})
    unknown = [m for m in wanted if m != FULL and m not in p["models"]]
    if unknown:
        raise RlsacError(f"model(s) {unknown} not in ablation.models (known: {', '.join(p['models'])})")

    def checkpoint(model: str) -> Path:
        return model_checkpoint(model, ckpts)

    base = {**section(params, "train", "fundamental"), "task": "fundamental"}
    models: dict[str, dict | None] = {}
    for m in wanted:
        if m == FULL:  # the paper's model is trained by `rlsac train` (dvc stage train_fundamental)
            models[m] = None
            continue
        spec = p["models"][m]
        t = deep_update(deep_update(base, p["train"]), spec.get("train") or {})
        suffix = spec.get("suffix", "")
        t.update(task="fundamental", data=str(data / f"train{suffix}.h5"), val_data=str(data / f"val{suffix}.h5"),
                 out=str(checkpoint(m)), run_name=f"train ablation {m}",
                 tags={**(t.get("tags") or {}), "ablation": spec["study"], "model": m})
        models[m] = t
    variants = {}
    for n, v in chosen.items():
        variants[n] = {"task": "fundamental", "method": "rlsac", "data": str(data / f"test{v.get('suffix', '')}.h5"),
                       "checkpoint": str(variant_checkpoint(v, o["ckpt_dir"])), "iterations": int(p["iterations"]),
                       "seed": int(p["seed"]), "sampling": v.get("sampling", "max"), "out_dir": str(evals / n),
                       "tags": {"ablation": o["what"] if v["study"] == "all" else v["study"], "variant": n,
                                "model": v["model"]}}
    return {"models": models, "variants": variants}


def _plan_generalisation(o: dict[str, Any], params: dict[str, Any]) -> dict[str, Any]:
    from rlsac.config import section
    from rlsac.evaluation.evaluate import sampler_options

    lines = section(params, "lines")
    p = protocol(params)
    rates = lines.get("rates") or [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]
    src = _rate(p["generalisation"].get("train_rate", 0.5))
    ldir, ckpt = Path(o["lines_dir"]), Path(o["ckpt_dir"]) / f"line_o{src}.pt"
    names = {f"o{_rate(r)}": _rate(r) for r in rates}
    if o["variants"]:
        missing = [n for n in o["variants"] if n not in names]
        if missing:
            raise RlsacError(f"variant(s) {missing} not in ablation 'generalisation' (known: {', '.join(names)})")
        names = {n: names[n] for n in o["variants"]}
    t = {**section(params, "train", "line"), "task": "line"}
    t.update(data=str(ldir / f"train_o{src}.h5"), val_data=str(ldir / f"val_o{src}.h5"), out=str(ckpt),
             run_name=f"train line o{src}", tags={**(t.get("tags") or {}), "ablation": "generalisation"})
    if o["models"] and o["models"] != [f"line_o{src}"]:
        raise RlsacError(f"the generalisation study has one model, line_o{src}")
    # Table 1's column beside Ours: the same environment settings (params.yaml evaluate.line)
    sampler = sampler_options(section(params, "evaluate", "line"))
    variants = {n: {"task": "line", "method": "rlsac", "data": str(ldir / f"test_o{r}.h5"), "checkpoint": str(ckpt),
                    "iterations": int(lines.get("iterations", 150)), "seed": 0, "sampling": "max", **sampler,
                    "out_dir": str(Path(o["eval_dir"]) / "lines" / f"ours-{src}" / f"o{r}"),
                    "tags": {"ablation": "generalisation", "variant": n, "model": f"line_o{src}"}}
                for n, r in names.items()}
    return {"models": {f"line_o{src}": t}, "variants": variants}


# ------------------------------------------------------------------------------------------ running


def ablate(options: dict[str, Any], track: bool = True) -> dict[str, Any]:
    """Run one ablation study (see the module docstring); -> {"what", "trained", "skipped", "variants", "table"}."""
    from rlsac.config import read_params

    o = check_options(options)
    params = read_params(o["params"])
    pl = plan(o, params)
    if o["what"] != "generalisation":
        files = [t[k] for t in pl["models"].values() if t for k in ("data", "val_data")] if o["stage"] != "evaluate" \
            else []
        files += [e["data"] for e in pl["variants"].values()] if o["stage"] != "train" else []
        missing = [f for f in files if not Path(f).is_file()]
        if missing:  # the retired split's data: the study lives in the fold stages
            if o["full"]:
                return fold_full(o, track)
            if o["what"] in QUICK_ROWS:
                return fold_quick(o, track)
            return {"what": o["what"], "stage": o["stage"], "fold_stages": fold_commands(o["what"]),
                    "missing": missing[0]}
    if int(o["threads"]) > 0:
        import torch

        torch.set_num_threads(int(o["threads"]))
    trained, skipped = [], []
    if o["stage"] in ("all", "train"):
        for name, t in pl["models"].items():
            to_train = t is not None and (o["force"] or not Path(t["out"]).is_file())
            (trained if to_train else skipped).append(name)
    # every model and every variant checked before the first one trains or evaluates (issue #28, item 2: a
    # missing data file of the second variant failed after the first had overwritten its committed results)
    models = {name: model_options(pl["models"][name], o) for name in trained}
    for t in models.values():
        check_model(t, track)
    variants = {}
    if o["stage"] in ("all", "evaluate"):
        from rlsac.evaluation.evaluate import check_all

        later = {str(t["out"]) for t in models.values()}
        for name, e in pl["variants"].items():
            if not Path(e["checkpoint"]).is_file() and str(e["checkpoint"]) not in later:
                hint = ("train it with `rlsac train --task fundamental` (dvc stage train_fundamental)"
                        if e["checkpoint"].endswith("fundamental.pt") else "run the study with stage all or train")
                raise RlsacError(f"{e['checkpoint']}: no checkpoint for variant {name}; {hint}")
            variants[name] = {**e, "device": o["device"]}
        check_all(list(variants.values()), track, built_later=later)
    if models:
        from rlsac.evaluation.train import train

        for t in models.values():
            train(t, track=track)
    results: dict[str, dict] = {}
    if variants:
        from rlsac.evaluation.evaluate import evaluate

        for name, e in variants.items():
            s = evaluate(e, track=track)
            results[name] = {k: s.get(k) for k in ("mAA", "mAA_R", "mAA_t", "median_R", "median_t", "median_deg",
                                                    "out_dir", "checkpoint") if k in s}
    table = None
    if o["stage"] == "all" and o["table"] and results and o["what"] != "generalisation":
        table = rebuild_table(track)
    return {"what": o["what"], "stage": o["stage"], "trained": trained, "skipped": skipped, "variants": results,
            "table": table}


def fold_quick(o: dict[str, Any], track: bool) -> dict[str, Any]:
    """The study's rows and the full model on one fold's test pairs (see QUICK_ROWS), its table printed and written
    to <out>/<what>/table.md; nothing committed is written."""
    from rlsac.experiments.quick import run_rows, table
    from rlsac.io import write_text

    out = Path(o["out"]) / o["what"]
    names = [QUICK_REFERENCE, *QUICK_ROWS[o["what"]]]
    device = "cpu" if o["device"] == "auto" else o["device"]
    r = run_rows(names, o["fold"], QUICK_REGIME, int(o["iterations"]), out, track, o["params"], device)
    errors = r["errors"]
    head = (f"Table 3 ({o['what']}), quick: fold {o['fold']} ({len(errors[QUICK_REFERENCE])} test pairs), "
            f"{QUICK_REGIME} regime, {o['iterations']} iterations, the committed checkpoints and tuning records; "
            f"`R/t − {QUICK_REFERENCE}`: paired difference to the full model with its 95% bootstrap interval. "
            f"The record (every fold, every budget, all training seeds): {RECORD}; "
            f"`rlsac ablate --what {o['what']} --full` re-runs it.")
    text = table(errors, QUICK_REFERENCE)
    path = write_text(out / "table.md", f"{head}\n\nTest pairs: {r['test']}\n\n{text}\n")
    return {"what": o["what"], "stage": "quick", "quick": {"head": head, "table": text, "file": str(path)}}


def fold_full(o: dict[str, Any], track: bool) -> dict[str, Any]:
    """The study at the record's size: exactly its fold stages (FOLD_STUDIES) through `rlsac pipeline`, then Table 3
    (folds) from reports/eval into <out>/<what>-full/ (the `tables` stage writes the committed one: it depends on
    every stage of the record)."""
    from rlsac.evaluation.results import collect, load_records
    from rlsac.reports.folds import table3
    from rlsac.runners.pipeline import pipeline

    pats = [p for study in (STUDIES if o["what"] == "all" else (o["what"],)) for p in FOLD_STUDIES[study]]
    ran = pipeline({"stages": ",".join(pats), "workers": o["workers"]}, track=track)
    failed = [a for a, r in ran["results"].items() if r["status"] in ("failed", "not run", "interrupted")]
    if failed:
        raise RlsacError(f"ablate --full: {len(failed)} stages did not finish ({failed[0]} first; "
                         "logs/pipeline/<stage>.log); the table was not rebuilt")
    out = Path(o["out"]) / f"{o['what']}-full"
    files = table3(collect("reports/eval"), out, load_records())
    if not files:
        raise RlsacError("ablate --full: reports/eval has no Table 3 row in the hard regime")
    return {"what": o["what"], "stage": "full", "full": {"counts": ran["counts"], "files": files,
                                                       "table": Path(files[0]).read_text()}}


def model_options(t: dict[str, Any], o: dict[str, Any]) -> dict[str, Any]:
    """A model's `rlsac train` options with the command's device, train_steps and threads."""
    from rlsac.config import deep_update

    extra: dict[str, Any] = {"device": o["device"]}
    if o["train_steps"] is not None:
        extra["sac"] = {"total_steps": int(o["train_steps"])}
    if int(o["threads"]) > 0:
        extra["threads"] = int(o["threads"])
    return deep_update(t, extra)


def check_model(t: dict[str, Any], track: bool) -> None:
    """A model's training data files (read and validated) and configuration, before any model trains."""
    from rlsac.learners.harness import check
    from rlsac.tasks import task_class

    for key in ("data", "val_data"):
        if t.get(key) and not Path(t[key]).is_file():
            raise RlsacError(f"{t[key]}: no such file (prepare it first, e.g. `dvc repro` or rlsac prepare-cvpr2020)")
        if t.get(key):
            task_class(t["task"]).read(t[key])
    check(t, track)


def rebuild_table(track: bool = True) -> str:
    """Table 3 (rlsac.reports.tables) -> the files written, comma-separated."""
    from rlsac.reports.tables import build

    return build({"which": "3"}, track=track)["files"]


def fold_commands(what: str) -> list[str]:
    """The commands that run a Table 3 study on the folds (``FOLD_STUDIES``) and rebuild its table."""
    import shlex

    pats = [p for study in (STUDIES if what == "all" else (what,)) for p in FOLD_STUDIES[study]]
    quoted = " ".join(shlex.quote(p) for p in pats)
    return [f"rlsac pipeline {quoted} --workers 2", f"dvc repro --glob {quoted}",
            "rlsac table --which folds   (every table of the record, reports/table3_folds.md among them)"]


def format_summary(s: dict[str, Any]) -> str:
    if "quick" in s:
        q = s["quick"]
        return f"{q['head']}\n\n{q['table']}\n\ntable: {q['file']}"
    if "full" in s:
        counts = ", ".join(f"{v} {k}" for k, v in s["full"]["counts"].items() if v)
        return f"{s['full']['table']}\npipeline: {counts}\ntable: {', '.join(s['full']['files'])}"
    if "fold_stages" in s:
        return "\n".join([
            f"ablation {s['what']}: Table 3 runs on the leave-one-building-out folds (reports/table3_folds.md); the "
            f"87-pair split this command used is retired ({s['missing']} is made by no stage). "
            f"`rlsac ablate --what {s['what']} --full` runs its fold stages and rebuilds its table; by hand:",
            *(f"  {c}" for c in s["fold_stages"])])
    lines = [f"ablation {s['what']} ({s['stage']}): trained {', '.join(s['trained']) or 'none'}; "
             f"kept existing {', '.join(s['skipped']) or 'none'}"]
    for name, r in s["variants"].items():
        metrics = ", ".join(f"{k}={v:.4g}" for k, v in r.items() if isinstance(v, float))
        lines.append(f"  {name}: {metrics} -> {r.get('out_dir')}")
    if s.get("table"):
        lines.append(f"table: {s['table']}")
    return "\n".join(lines)
