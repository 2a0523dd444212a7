"""A few rows of the fold benchmark on one fold's test pairs, in minutes on one core, from the clone alone
(issue #63, items 4 and 6): ``rlsac ablate --what sampling``'s default and the README's first command.

The rows are the record's own: each RLSAC model is the committed checkpoint (checkpoints/folds/<regime>/<fold>/), each
row's threshold and pre-filter the committed tuning record (reports/tuning/fundamental/<regime>/<fold>/, chosen on the
fold's validation pairs), and the test pairs those of ``data/folds/<data regime>/<fold>/test.h5`` when the pipeline
made it, else prepared the same way into ``<out>/data`` from the committed matches (data/strecha, through
``rlsac import-scenes`` and ``prepare-cvpr2020``'s code). Every result goes under ``<out>`` (git-ignored scratch/):
nothing committed is written. The table: each row's pooled mAA@10° (R, t) and its paired difference to the reference
row over the same pairs, with a 95% percentile bootstrap interval (rlsac.maths.metrics.paired_bootstrap_maa).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError


def _fold_test(p: dict, params: dict, regime: str, fold: str, out: Path, track: bool) -> tuple[Path, str]:
    """The fold's test file and where it came from: the pipeline's, else one prepared under ``out``."""
    from rlsac.config import section
    from rlsac.layout.protocol import data_dir, split_scenes

    made = data_dir(regime, fold) / "test.h5"
    if made.is_file():
        return made, f"{made} (the pipeline's)"
    fundamental = section(params, "fundamental")
    raw = Path(fundamental.get("raw", "data/raw/strecha"))
    if not (raw / "all").is_dir():  # the import of the committed matches (seconds), into the scratch folder
        from rlsac.commands import import_scenes

        raw = out / "raw"
        if not (raw / "all" / "import_summary.json").is_file():
            import_scenes({"src": fundamental.get("src", "data/strecha"), "out": str(raw),
                           "scenes": fundamental.get("import_scenes", ""),
                           "max_features": int(fundamental.get("max_features", 8000)),
                           "min_matches": int(fundamental.get("min_matches", 100)),
                           "matches": fundamental.get("matches", "")}, track=track)
    from rlsac.data.tutorial import PrepareConf, prepare

    test = out / "data" / regime / fold / "test.h5"
    if not test.is_file():
        _, test_scenes = split_scenes(p, fold)
        prepare(PrepareConf(root=str(raw), split="all", n_points=int(fundamental.get("n_points", 150)),
                            max_pairs_per_scene=int(fundamental.get("max_pairs_per_scene", 0)),
                            pool=int(p["pool"][regime]), val_fraction=float(p["val_fraction"]),
                            scenes=test_scenes, holdout="all", out=str(test)), track=track, progress=False)
    return test, f"{test} (prepared as fold_data does, from {raw})"


def run_rows(names: list[str], fold: str, regime: str, iterations: int, out: str | Path, track: bool = True,
             params_path: str = "params.yaml", device: str = "cpu") -> dict[str, Any]:
    """Evaluate rows ``names`` of the fold benchmark on ``fold``'s test pairs at ``iterations`` into ``out``;
    -> {"rows": {name: summary}, "errors": {name: errors DataFrame}, "test": where the pairs came from}. Every
    row's checkpoint and tuning record is checked before anything is written."""
    from rlsac.config import read_params, section
    from rlsac.evaluation.evaluate import check_all, evaluate
    from rlsac.evaluation.results import read_errors
    from rlsac.evaluation.tune import tuned_settings
    from rlsac.experiments.folds import for_task, protocol
    from rlsac.layout.protocol import row_options, rows, scene_list, split_scenes

    params = read_params(params_path)
    p = for_task(protocol(params), params, "fundamental")
    if fold not in p["test"]:
        raise RlsacError(f"fold must be one of {', '.join(p['test'])}, got {fold!r}")
    if regime not in p["regimes"]:
        raise RlsacError(f"regime must be one of {', '.join(p['regimes'])}, got {regime!r}")
    known = rows(p, fold, regime)
    bad = [n for n in names if n not in known]
    if bad:
        raise RlsacError(f"row(s) {bad} not in the fold benchmark's {regime} regime")
    ev = section(params, "evaluate", "fundamental")
    train_scenes, test_scenes = (scene_list(s) for s in split_scenes(p, fold))
    settings = {n: tuned_settings(ev, regime, fold, n, train_scenes, test_scenes) for n in names}
    out = Path(out)
    test, source = _fold_test(p, params, regime, fold, out, track)
    jobs = {n: {**row_options(known[n], p, ev, {"device": device}), **settings[n], "data": str(test),
                "iterations": int(iterations), "out_dir": str(out / "eval" / n / f"i{int(iterations)}"),
                "tags": {"benchmark": "quick", "regime": regime, "fold": fold, "model": n}} for n in names}
    check_all(list(jobs.values()), track)
    summaries = {n: evaluate(o, track=track) for n, o in jobs.items()}
    errors = {n: read_errors(Path(o["out_dir"]) / "errors.csv").assign(fold=fold) for n, o in jobs.items()}
    return {"rows": summaries, "errors": errors, "test": source}


def table(errors: dict, reference: str, labels: dict[str, str] | None = None, ahead: bool = False) -> str:
    """A markdown table: each row's pooled mAA@10° R and t and its paired difference to ``reference`` over the same
    pairs with its 95% interval: row − reference, or with ``ahead`` reference − row (how far the reference is
    ahead of each control)."""
    import pandas as pd

    from rlsac.layout.protocol import LIMIT
    from rlsac.maths.metrics import mAA
    from rlsac.reports.folds import _ci, _paired

    ref = errors[reference]
    out = []
    for name, df in errors.items():
        pair = (ref, df) if ahead else (df, ref)
        d = {c: (_paired(*pair, f"err_{c}") if name != reference else None) for c in ("R", "t")}
        head = (lambda c: f"{reference} − row, {c}") if ahead else (lambda c: f"{c} − {reference}")
        out.append({"row": name, **({"what": labels.get(name, "")} if labels else {}), "pairs": len(df),
                    "mAA_R": f"{mAA(df['err_R'], LIMIT):.3f}", "mAA_t": f"{mAA(df['err_t'], LIMIT):.3f}",
                    head("R"): _ci(d["R"]), head("t"): _ci(d["t"])})
    return pd.DataFrame(out).to_markdown(index=False, disable_numparse=True)


# `rlsac quick`: the README's first command (issue #63 item 6): the committed RLSAC model against its controls
CONTROLS = {"rlsac": "RLSAC, the committed model", "uniform": "uniform minimal sets in RLSAC's environment",
            "opencv_ransac": "OpenCV RANSAC", "magsac": "OpenCV MAGSAC++"}
OPTIONS: dict[str, Any] = {"fold": "fountain", "regime": "hard", "iterations": 1000, "out": "scratch/quick",
                           "params": "params.yaml"}  # on the CPU: the record's own bytes, as the record ran
RECORD = ("reports/table2_folds.md (every method, the four folds' 606 pairs, every budget, all training seeds) and "
          "reports/paper.md (the paper's claims against ours)")


def quick(options: dict[str, Any], track: bool = True) -> dict[str, Any]:
    """RLSAC against uniform sets, OpenCV's RANSAC and MAGSAC++ on one fold's test pairs (``CONTROLS``) -> {"head",
    "table", "file"}; the table also goes to <out>/table.md."""
    from rlsac.config import check_mapping
    from rlsac.io import write_text

    o = {**OPTIONS, **check_mapping({k: v for k, v in options.items() if v is not None}, OPTIONS, "quick",
                                    types={"iterations": int}, ranges={"iterations": "[1, inf)"})}
    r = run_rows(list(CONTROLS), o["fold"], o["regime"], int(o["iterations"]), o["out"], track, o["params"])
    n = len(r["errors"]["rlsac"])
    head = (f"RLSAC against its controls on fold {o['fold']} ({n} test pairs of a building no model saw in training), "
            f"{o['regime']} regime, {o['iterations']} iterations (Table 2's budget), each row with the settings tuned "
            f"on the fold's validation pairs; `rlsac − row`: RLSAC's lead in pooled mAA@10° with its paired 95% "
            f"bootstrap interval over the pairs (one pair moves an mAA by {1 / max(n, 1):.3f}). The record: {RECORD}.")
    text = table(r["errors"], "rlsac", CONTROLS, ahead=True)
    path = write_text(Path(o["out"]) / "table.md", f"{head}\n\nTest pairs: {r['test']}\n\n{text}\n")
    return {"head": head, "table": text, "file": str(path)}


def format_summary(s: dict[str, Any]) -> str:
    return f"{s['head']}\n\n{s['table']}\n\ntable: {s['file']}"
