"""``rlsac folds --stage retune`` (issue #47 item 7 b): how much a row's test numbers move when its settings are
chosen on another sample of validation pairs.

Per row of ``--only`` (cheap rows of folds.methods: no checkpoint), on one fold: every grid point the tuning's rule
visits is evaluated on the fold's val.h5 at ``tuning.iterations`` (lazily: only points some draw's search asks for),
the rule is replayed on all validation pairs and on ``tuning_budget.retune_draws`` resamples of them stratified by
scene (rlsac.evaluation.retune.reselect), and every setting some draw chose is evaluated on test.h5 at each budget of
``tuning_budget.retune_iterations``. The record reports/retune/<task>/<regime>/<fold>/<row>.json keeps the per-pair
errors (6 significant digits, as errors.csv) of every visited point on validation and of every chosen one on test,
and each draw's choice: the report (rlsac.reports.tuning_budget) reads it, never this module.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from rlsac.errors import RlsacError


def _rounded(a) -> list[float]:
    return [float(f"{float(v):.6g}") for v in np.asarray(a, dtype=np.float64)]


def retune_fold(p: dict, params: dict, regime: str, fold: str, o: dict) -> list[dict[str, Any]]:
    """Re-tune every row of ``o["only"]`` on bootstrap resamples of the fold's validation pairs; -> one summary per
    row ({row, draws, distinct, file}). Every input is read and checked before the first record is written."""
    from rlsac.config import section
    from rlsac.evaluation import retune, tune
    from rlsac.evaluation.evaluate import check_options, resolve_device, score
    from rlsac.evaluation.results import read_record
    from rlsac.io import check_writable, write_text
    from rlsac.layout.protocol import LIMIT, data_dir, retune_path, row_options, rows, scene_list, split_scenes
    from rlsac.tasks import task_class

    if "retune" not in p.get("fold_stages", ["retune"]):
        raise RlsacError(f"folds --stage retune is not --task {p['task']}'s")
    c, b = tune.conf(params), retune.conf(params)
    table = rows(p, fold, regime)
    names = o.get("only") or []
    cheap = [n for n in names if table[n]["checkpoint"] is None and table[n]["points"] is None]
    if not names or cheap != names:
        raise RlsacError(f"folds --stage retune needs --only with rows of folds.methods (no checkpoint: every grid "
                         f"point runs on validation and test), got {names or 'none'}")
    bad = sorted(set(b["retune_iterations"]) - set(p["iterations"][regime]))
    if bad:  # a re-tuned choice is tested where the tables test it, nowhere else
        raise RlsacError(f"tuning_budget.retune_iterations {bad}: not test budgets of regime {regime!r} "
                         f"(folds.iterations {p['iterations'][regime]})")
    train_scenes, test_scenes = (scene_list(s) for s in split_scenes(p, fold))
    d = data_dir(regime, fold)
    files = {}
    for split in ("val", "test"):
        if not (d / f"{split}.h5").is_file():
            raise RlsacError(f"{d / f'{split}.h5'}: no such file (run `rlsac folds --stage data` first)")
        files[split], _ = task_class(p["task"]).read(d / f"{split}.h5")
    tune.check_scenes(tune.scenes_of(files["val"]), train_scenes, test_scenes, str(d / "val.h5"))
    records = {n: read_record(tune.record_path(regime, fold, n)) for n in names}  # the tables' choice, to compare
    for n in names:
        check_writable(retune_path(regime, fold, n))
    ev = section(params, "evaluate", p["task"])
    device = resolve_device(o["device"])
    out = []
    for name in names:
        base = row_options(table[name], p, ev, o)

        def run(settings: dict, split: str, iterations: int, base=base) -> dict[str, np.ndarray]:
            opts = {**base, **tune.as_options(settings, ev.get("lo")), "data": str(d / f"{split}.h5"),
                    "iterations": int(iterations)}
            return score(check_options(opts), files[split], device)[1]

        val: dict[tuple, dict[str, list[float]]] = {}  # every visited point's rounded validation errors

        def errors(settings: dict, run=run, val=val) -> tuple[np.ndarray, np.ndarray]:
            k = retune.key(settings)
            if k not in val:
                e = run(settings, "val", c["iterations"])
                val[k] = {"err_R": _rounded(e["err_R"]), "err_t": _rounded(e["err_t"])}
            return np.asarray(val[k]["err_R"]), np.asarray(val[k]["err_t"])

        strata = [str(s) for s in files["val"]["scene"]]
        full, chosen = retune.reselect(errors, strata, c, table[name]["knobs"], b["retune_draws"], b["retune_seed"],
                                       LIMIT)
        keys = list(val)
        distinct = list(dict.fromkeys(retune.key(s) for s in [full] + chosen))
        test = {str(it): {str(keys.index(k)): {col: _rounded(v) for col, v in run(dict(k), "test", it).items()
                                                if col in ("err_R", "err_t")} for k in distinct}
                for it in b["retune_iterations"]}
        rec = records[name]
        record = {"task": p["task"], "regime": regime, "fold": fold, "row": name, "method": table[name]["method"],
                  "tuning_iterations": c["iterations"], "seed": int(p["seed"]), "draws": b["retune_draws"],
                  "draw_seed": b["retune_seed"], "criterion": f"validation {tune.CRITERION}@10deg of max(err_R, err_t)",
                  "val_data": str(d / "val.h5"), "val_scenes": strata, "test_data": str(d / "test.h5"),
                  "test_scenes": [str(s) for s in files["test"]["scene"]],
                  "test_pairs": [str(s) for s in files["test"]["pair"]],
                  "settings": [dict(k) for k in keys], "val": [val[k] for k in keys],
                  "full": keys.index(retune.key(full)), "choices": [keys.index(retune.key(s)) for s in chosen],
                  "record_chosen": None if rec is None else rec["chosen"], "test": test}
        # compact JSON: a few hundred errors per grid point
        import json

        write_text(retune_path(regime, fold, name), json.dumps(record, sort_keys=True, separators=(",", ":")) + "\n")
        out.append({"row": name, "draws": len(chosen), "distinct": len(distinct),
                    "file": str(Path(retune_path(regime, fold, name)))})
    return out
