"""The results as the reports read them: refusing readers of each result file (an evaluation's errors.csv and
summary.json, a tuning record, an iterations CSV) and the tidy tables made from reports/eval (Table 1's seed runs,
the fold benchmark's cells, data records and seed runs).

Each reader refuses a corrupt file (``RlsacError``: "<file>: <what>", exit 2) and returns None for an absent one, so a
table shows an absent cell as "–" but never a number made from text, NaN or a truncated file (issue #49: coercing bad
values to NaN printed a wrong "+0.701" at exit 0).

Below the runners and the reports (it imports the protocol's names, rlsac.layout.protocol, and the method registry to
check a cell's configuration): the runners (folds, selection, tune) and every report module read through it, so there is
one definition of a valid result file, and a report never needs a runner.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rlsac.errors import RlsacError

# summary.json fields that are numbers wherever they appear; the first of them every summary has
SUMMARY_REQUIRED = ("mAA",)
_COUNTS = ("n", "n_instances", "iterations")  # integers >= 0


def _fail(path: Path, what: str) -> RlsacError:
    return RlsacError(f"{path}: {what}; re-run the command that wrote it, or remove it")


def _finite_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _load_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text(), parse_constant=lambda c: float(c))
    except (OSError, ValueError) as e:  # UnicodeDecodeError is a ValueError
        raise _fail(path, f"not a valid {what} ({e.__class__.__name__})") from None


def read_mapping(path: str | Path, what: str) -> dict[str, Any] | None:
    """A JSON file that holds a mapping (a record a report reads) -> dict, None when absent; not JSON or not a
    mapping is an error naming the file."""
    path = Path(path)
    if not path.is_file():
        return None
    d = _load_json(path, what)
    if not isinstance(d, dict):
        raise _fail(path, f"not a valid {what} (holds a {type(d).__name__}, not a mapping)")
    where = _non_finite(d)
    if where is not None:  # issue #64: a NaN in the positive control's record was rendered as "nan" at exit 0
        raise _fail(path, f"{where} is not a finite number")
    return d


def _non_finite(obj: Any, where: str = "") -> str | None:
    """The key path of the first NaN or infinity anywhere in a JSON value (None when there is none): no record a
    report reads holds one on purpose, and a report would print it, or compute with it, as a number."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return where or "the value"
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    for k, v in items:
        found = _non_finite(v, f"{where}[{k!r}]" if isinstance(k, int) else f"{where}.{k}".lstrip("."))
        if found is not None:
            return found
    return None


def read_retune_record(path: str | Path) -> dict[str, Any] | None:
    """A re-tuning record (``rlsac folds --stage retune``) -> dict, None when absent. Refused, naming the file: not
    a JSON mapping, a NaN anywhere; ``choices`` / ``full`` not indices of ``settings``; a chosen setting without
    test errors at some budget, or errors that are not one angle per test pair, each a finite number of degrees in
    [0, 180] (issue #64: a string was a ValueError traceback, a NaN a report, and an error of -1 a perfect pair)."""
    path = Path(path)
    rec = read_mapping(path, "re-tuning record")
    if rec is None:
        return None
    try:
        n, k = len(rec["test_scenes"]), len(rec["settings"])
        chosen = {rec["full"], *rec["choices"]}
        test = rec["test"]
        ok = bool(rec["choices"]) and bool(test) and isinstance(test, dict) and all(
            isinstance(i, int) and not isinstance(i, bool) and 0 <= i < k for i in chosen)
    except (KeyError, TypeError):
        ok = False
    if not ok:
        raise _fail(path, "not a re-tuning record of `rlsac folds --stage retune` (choices, settings and test errors "
                          "of every chosen setting)")
    for it, per in test.items():
        for i in sorted(chosen):
            errs = per.get(str(i)) if isinstance(per, dict) else None
            for col in ("err_R", "err_t"):
                e = errs.get(col) if isinstance(errs, dict) else None
                if not isinstance(e, list) or len(e) != n:
                    raise _fail(path, f"test[{it!r}][{str(i)!r}].{col} is not {n} errors, one per test pair")
                j = next((j for j, v in enumerate(e) if not (_finite_number(v) and 0 <= v <= 180)), None)
                if j is not None:
                    raise _fail(path, f"test[{it!r}][{str(i)!r}].{col}[{j}] is {e[j]!r}, not an angle in [0, 180] "
                                      "degrees")
    return rec


def read_summary(path: str | Path, required: tuple[str, ...] = SUMMARY_REQUIRED) -> dict[str, Any] | None:
    """summary.json -> dict, None when absent. Refused: not JSON, not a mapping, a ``required`` field missing, a
    metric (mAA*, median*, the counts) that is not a finite number, a count that is not a whole number >= 0."""
    path = Path(path)
    if not path.is_file():
        return None
    s = _load_json(path, "summary.json")
    if not isinstance(s, dict):
        raise _fail(path, f"not a valid summary.json (holds a {type(s).__name__}, not a mapping)")
    for key in required:
        if key not in s:
            raise _fail(path, f"no '{key}' in the summary")
    for key, v in s.items():
        if key.startswith(("mAA", "median")) or key in _COUNTS:
            if not _finite_number(v):
                raise _fail(path, f"'{key}' is {v!r}, not a finite number")
            if key in _COUNTS and (v < 0 or v != int(v)):
                raise _fail(path, f"'{key}' is {v!r}, not a count")
            if key.startswith("mAA") and not 0 <= v <= 1:
                raise _fail(path, f"'{key}' is {v!r}, outside [0, 1]")
    if "n" in s and "n_instances" in s and s["n"] != s["n_instances"]:
        raise _fail(path, f"'n' ({s['n']}) is not 'n_instances' ({s['n_instances']})")
    return s


def read_errors(path: str | Path, columns: tuple[str, ...] | None = None, n: int | None = None,
                per_instance: bool = True) -> pd.DataFrame | None:
    """An evaluation's errors.csv -> its rows, None when absent. ``columns`` (default: every ``err_*`` column, at
    least one) must be numbers, finite and >= 0 (a failed estimate is written as 90 / 180 degrees, never NaN). The
    row count must be the instance count: ``n``, else the ``n_instances`` of the summary.json beside it (a
    truncated file silently dropped pairs before); instances are not repeated. ``per_instance=False``: a file of
    several rows per instance (rlsac.experiments.selection's, one per step and budget), whose count is not checked."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        frame = pd.read_csv(path, dtype={"pair": str, "scene": str})
    except (OSError, ValueError) as e:  # EmptyDataError, ParserError, UnicodeDecodeError are ValueErrors
        raise _fail(path, f"not a readable errors.csv ({e.__class__.__name__})") from None
    cols = tuple(columns) if columns else tuple(c for c in frame.columns if str(c).startswith("err_"))
    if not cols or any(c not in frame for c in cols):
        need = [c for c in cols if c not in frame] or ["err_*"]
        raise _fail(path, f"no '{need[0]}' column (columns: {', '.join(map(str, frame.columns))})")
    for c in cols:
        _check_numbers(path, frame, c, low=0.0)
    if not per_instance:
        return frame
    where = "its summary counts"
    if n is None:
        s = read_summary(path.parent / "summary.json", required=())
        n = None if s is None else s.get("n_instances", s.get("n"))
    if n is None:  # no summary (evaluate writes config.json before it): the count its configuration recorded
        n, where = _configured_instances(path.parent / "config.json"), "its config.json counts"
    if n is not None and len(frame) != n:
        raise _fail(path, f"{len(frame)} rows, not the {n} instances {where} (a truncated file?)")
    if "instance" in frame and frame["instance"].duplicated().any():
        raise _fail(path, f"instance {frame['instance'][frame['instance'].duplicated()].iloc[0]} appears twice")
    return frame


def _configured_instances(path: Path) -> int | None:
    """``n_instances`` of an evaluation's config.json (the data file's usable instances), None when the file or the
    key is absent (results written before evaluate kept its configuration). Issue #49: a truncated errors.csv
    without a summary beside it was pooled, its missing pairs silently dropped."""
    if not path.is_file():
        return None
    conf = _load_json(path, "config.json")
    if not isinstance(conf, dict):
        raise _fail(path, f"not a valid config.json (holds a {type(conf).__name__}, not a mapping)")
    n = conf.get("n_instances")
    if n is not None and (not _finite_number(n) or n < 0 or n != int(n)):
        raise _fail(path, f"'n_instances' is {n!r}, not a count")
    return None if n is None else int(n)


def read_errors_column(path: str | Path, column: str = "err_deg") -> np.ndarray | None:
    """Column ``column`` of errors.csv as floats (read_errors' checks), None when the file is absent."""
    frame = read_errors(path, (column,))
    return None if frame is None else frame[column].to_numpy(dtype=float)


def _check_numbers(path: Path, frame: pd.DataFrame, column: str, low: float | None = None) -> None:
    col = frame[column]
    if not pd.api.types.is_numeric_dtype(col) or pd.api.types.is_bool_dtype(col):
        bad = next((v for v in col if not _parses(v)), col.iloc[0] if len(col) else None)
        raise _fail(path, f"'{column}' holds {bad!r}, not a number")
    values = col.to_numpy(dtype=float)
    where = np.flatnonzero(~np.isfinite(values) | ((values < low) if low is not None else False))
    if where.size:
        raise _fail(path, f"'{column}' is {values[where[0]]:g} in row {int(where[0]) + 1}, not a finite number"
                    + (f" >= {low:g}" if low is not None else ""))


def _parses(v: Any) -> bool:
    try:
        return math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def read_table(path: str | Path, numeric: tuple[str, ...], what: str) -> pd.DataFrame | None:
    """A CSV the reports wrote (e.g. folds_iterations.csv) -> its rows, None when absent; the ``numeric`` columns
    must be there and finite (NaN made ``rlsac plot`` fail with a traceback)."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        frame = pd.read_csv(path)
    except (OSError, ValueError) as e:
        raise _fail(path, f"not a readable {what} ({e.__class__.__name__})") from None
    for c in numeric:
        if c not in frame:
            raise _fail(path, f"no '{c}' column (columns: {', '.join(map(str, frame.columns))})")
        _check_numbers(path, frame, c)
    return frame


def read_record(path: str | Path) -> dict[str, Any] | None:
    """A tuning record (rlsac.evaluation.tune) -> dict, None when absent. Refused: not a JSON mapping (``[]``,
    ``null``),
    ``chosen`` not a non-empty mapping of numbers / booleans (``{}`` evaluated the row untuned), ``val_scenes`` not a
    non-empty list of names, a validation mAA that is not a finite number in [0, 1]."""
    path = Path(path)
    if not path.is_file():
        return None
    rec = _load_json(path, "tuning record")
    if not isinstance(rec, dict):
        raise _fail(path, f"not a tuning record (holds a {type(rec).__name__}, not a mapping)")
    chosen, scenes = rec.get("chosen"), rec.get("val_scenes")
    if not isinstance(chosen, dict) or not chosen:
        raise _fail(path, f"not a tuning record ('chosen' is {chosen!r}, not the settings chosen)")
    bad = next((k for k, v in chosen.items() if not (isinstance(v, bool) or _finite_number(v))), None)
    if bad is not None:
        raise _fail(path, f"chosen setting '{bad}' is {chosen[bad]!r}, not a finite number")
    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, str) and s for s in scenes):
        raise _fail(path, f"not a tuning record ('val_scenes' is {scenes!r}, not the validation scenes)")
    val = rec.get("val", {})
    if not isinstance(val, dict) or any(not _finite_number(v) or not 0 <= v <= 1 for v in val.values()):
        raise _fail(path, f"'val' is {val!r}, not validation mAAs in [0, 1]")
    return rec


# ---------------------------------------------------------------------------------------------- Table 1's results
# reports/eval/lines/<row>/o<rate>/ of every training seed of a learned row, as an array of per-instance errors

# Table 1's learned rows that have training seeds (<row>-s<seed>)
LINE_SEED_MODELS = ("ours", "ours-0.5", "ngransac")


def line_seed_runs(root: Path) -> dict[str, list[str]]:
    """Table 1's models with results of other training seeds under ``root`` (<eval_root>/lines): {"ours": ["ours",
    "ours-s1", ...], "ours-0.5": [...]} (the row's own directory is its seed 0; seeds in numeric order)."""
    from rlsac.layout.protocol import seed_name, split_seed

    out: dict[str, list[str]] = {}
    for d in LINE_SEED_MODELS:
        seeds = sorted(s for base, s in (split_seed(p.name) for p in root.glob(f"{d}-s*") if p.is_dir())
                       if base == d and s is not None)
        if seeds:
            out[d] = [d] + [seed_name(d, k) for k in seeds]
    return out


def line_runs_at(root: Path, runs: list[str], rate: float) -> list[str]:
    """The runs of a model (``line_seed_runs``) with results at ``rate``: its other seeds train only at
    lines.seed_rates; [] when the model's own (first) run has none there."""
    have = [d for d in runs if (root / d / f"o{rate:g}" / "errors.csv").is_file()]
    return have if have and have[0] == runs[0] else []


def line_errors(root: Path, runs: list[str], rate: float):
    """(S, M) errors at ``rate`` of the ``runs`` that have results there (``line_runs_at``), None when there are none
    or they are not on one test set."""
    runs = line_runs_at(root, runs, rate)
    if not runs:
        return None
    errs = [read_errors_column(root / d / f"o{rate:g}" / "errors.csv") for d in runs]
    if len({e.size for e in errs}) != 1:
        return None
    return np.stack(errs)


# ------------------------------------------------------------------------------------- the fold benchmark's results
# reports/eval/<sub>/<regime>/<fold>/<row>/i<iterations>/ as one frame per (regime, row, budget), the data stage's
# records, and the rows of several training seeds aligned on their common pairs


def _errors(path: Path) -> pd.DataFrame | None:
    """A cell's per-pair errors (read_errors: a corrupt or truncated file is an error naming it), None if absent."""
    return read_errors(path / "errors.csv", ("err_R", "err_t"))


def collect(eval_root: str | Path = "reports/eval", sub: str = "folds") -> dict[tuple[str, str, int], pd.DataFrame]:
    """(regime, method, iterations) -> per-pair errors of every fold found under <eval_root>/<sub>, with a
    ``fold`` column."""
    root = Path(eval_root) / sub
    out: dict[tuple[str, str, int], list[pd.DataFrame]] = {}
    if not root.is_dir():
        return {}
    for regime in sorted(p.name for p in root.iterdir() if p.is_dir()):
        for fold_dir in sorted(p for p in (root / regime).iterdir() if p.is_dir()):
            for mdir in sorted(p for p in fold_dir.iterdir() if p.is_dir()):
                for idir in sorted(p for p in mdir.iterdir() if p.is_dir() and p.name.startswith("i")):
                    df = _errors(idir)
                    if df is None:
                        continue
                    _check_cell(idir, mdir.name, int(idir.name[1:]))
                    df = df.assign(fold=fold_dir.name)
                    out.setdefault((regime, mdir.name, int(idir.name[1:])), []).append(df)
    return {k: pd.concat(v, ignore_index=True) for k, v in out.items()}


def _check_cell(path: Path, name: str, iterations: int) -> None:
    """The cell's resolved configuration (config.json, written by evaluate) must be what its folder says:
    the budget, and the method (an RLSAC model: method rlsac / rlsac-lo with the checkpoint of that name)."""
    from rlsac.evaluation.methods import METHODS

    f = path / "config.json"
    if not f.is_file():  # results written before evaluate kept its configuration
        return
    try:
        conf = json.loads(f.read_text())
    except (OSError, ValueError):
        raise RlsacError(f"{f}: unreadable") from None
    from rlsac.layout.protocol import checkpoint_model, seed_name, split_points, split_seed

    base, points = split_points(name)  # Table 3 (c)'s <row>-n<N>: the row of that name on the data with N points
    if points is not None:
        if (conf.get("data_attrs") or {}).get("n_points") != points:
            raise RlsacError(f"{f}: holds a run on {conf.get('data')!r}, not on the data with {points} points its "
                             f"folder {name!r} names")
        spec = METHODS.get(conf.get("method"))
        name = name if spec is not None and spec.checkpoint else base  # a model's checkpoint is named <model>-n<N>
    method, path = conf.get("method"), conf.get("checkpoint") or ""
    model = checkpoint_model(path) if path else None
    ckpt = model or Path(path).stem
    spec = METHODS.get(method)
    prob = conf.get("sampling") == "prob"  # Table 3 (b)'s <model>-prob rows: probabilistic test-time sampling
    variants = ("-prob",) if prob else ("", "-lo", "-fast")
    names = tuple(f"{ckpt}{v}" for v in variants)
    base, seed = split_seed(ckpt)
    if seed is not None:  # issue #27: the variant rows of another training seed are <row>-s<seed>
        names += tuple(seed_name(f"{base}{v}", seed) for v in variants if v)
    if spec is not None and spec.checkpoint and model is not None:  # the pipeline's checkpoint names the row
        ok = name in names
    else:  # a checkpoint of one's own (any name) can only be told by its method
        ok = method == name or (spec is not None and spec.checkpoint and name in names)
    if conf.get("iterations") != iterations or not ok:
        raise RlsacError(f"{f}: holds method {method!r} ({ckpt or 'no checkpoint'}) at {conf.get('iterations')} "
                         f"iterations, not the {name!r} at {iterations} its folder names")


def check_distinct(res: dict[tuple[str, str, int], pd.DataFrame], sub: str = "folds") -> None:
    """Two rows whose per-pair errors are identical in every regime and budget are one method shown twice (OpenCV's
    findEssentialMat ignores USAC_ACCURATE's flag: its rows were USAC's): RlsacError, before anything is written."""
    methods = sorted({m for _, m, _ in res})
    for i, a in enumerate(methods):
        for b in methods[i + 1:]:
            cells = [(r, it) for r, m, it in res if m == a and (r, b, it) in res]
            if cells and all(res[(r, a, it)][["err_R", "err_t"]].equals(res[(r, b, it)][["err_R", "err_t"]])
                             for r, it in cells):
                raise RlsacError(f"reports/eval/{sub}: methods '{a}' and '{b}' give identical errors on every pair, "
                                 f"fold and budget: one method shown as two rows (drop one from params.yaml)")


def pair_key(df: pd.DataFrame) -> pd.Series:
    """Each row's pair as <fold>/<scene>/<pair> (the key two rows' errors are aligned by)."""
    return df["fold"].astype(str) + "/" + df.get("scene", pd.Series([""] * len(df))).astype(str) + "/" + \
        df.get("pair", df["instance"]).astype(str)


def load_records(records: str | Path = "reports/folds/data") -> dict[tuple[str, str], dict]:
    """The folds' data records (rlsac folds --stage data); a corrupt one is an error naming it (issue #49: it was
    skipped with a printed line, and its fold left out of the data table at exit 0)."""
    out = {}
    root = Path(records)
    for f in sorted(root.glob("*/*.json")) if root.is_dir() else []:
        try:
            rec = json.loads(f.read_text())
        except (OSError, ValueError) as e:
            raise RlsacError(f"{f}: not a readable data record ({e.__class__.__name__})") from None
        if not isinstance(rec, dict) or not isinstance(rec.get("splits"), dict):
            raise RlsacError(f"{f}: not a data record of rlsac folds --stage data (no 'splits' mapping)")
        out[(f.parent.name, f.stem)] = rec
    return out


def seed_runs(res: dict[tuple[str, str, int], pd.DataFrame], regime: str) -> dict[str, list[str]]:
    """Models with rows of other training seeds in ``regime`` -> [the model, <model>-s<seed>, ...] (seed order)."""
    from rlsac.layout.protocol import split_seed

    found: dict[str, list[tuple[int, str]]] = {}
    for r, m, _ in res:
        base, s = split_seed(m)
        if r == regime and s is not None and any(k[:2] == (regime, base) for k in res):
            found.setdefault(base, []).append((s, m))
    return {b: [b] + [m for _, m in sorted(set(v))] for b, v in sorted(found.items())}


def _aligned(frames: list[pd.DataFrame], col: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(S, M) errors of ``frames`` on the pairs all of them have, in one order, and each pair's fold (M,)."""
    keyed = [df.assign(k=pair_key(df)).set_index("k") for df in frames]
    common = keyed[0].index
    for df in keyed[1:]:
        common = common.intersection(df.index)
    if common.empty:
        return None
    return np.stack([df.loc[common, col].to_numpy(np.float64) for df in keyed]), keyed[0].loc[common, "fold"].to_numpy()


def seed_errors(res, seeded: dict[str, list[str]], regime: str, model: str, control: str, it: int, col: str,
                building: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The errors ``seed_comparison`` compares: (S_model, M) and (S_control, M) in column ``col`` on the pairs every
    run has, and each pair's test building (M,); None when a run or common pairs are missing."""
    runs, controls = seeded.get(model, [model]), seeded.get(control, [control])
    frames = [res.get((regime, m, it)) for m in runs + controls]
    got = None if any(f is None for f in frames) else _aligned(frames, col)
    if got is None:
        return None
    err, fold = got
    if building is not None:
        err, fold = err[:, fold == building], fold[fold == building]
        if not err.shape[1]:
            return None
    return err[:len(runs)], err[len(runs):], fold
