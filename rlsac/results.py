"""Readers of the result files the reports and checks read back: an evaluation's errors.csv and summary.json, a
tuning record, an iterations CSV. Each refuses a corrupt file (``RlsacError``: "<file>: <what>", exit 2) and returns
None for an absent one, so a table shows an absent cell as "–" but never a number made from text, NaN or a truncated
file (issue #49: coercing bad values to NaN printed a wrong "+0.701" at exit 0).

Low in the import graph on purpose (errors, pandas, json only): the runners (folds, selection, evaluate) and every
report module read through it, so there is one definition of a valid result file.
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
    several rows per instance (rlsac.selection's, one per step and budget), whose count is not checked."""
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
    if n is None:
        s = read_summary(path.parent / "summary.json", required=())
        n = None if s is None else s.get("n_instances", s.get("n"))
    if n is not None and len(frame) != n:
        raise _fail(path, f"{len(frame)} rows, not the {n} instances its summary counts (a truncated file?)")
    if "instance" in frame and frame["instance"].duplicated().any():
        raise _fail(path, f"instance {frame['instance'][frame['instance'].duplicated()].iloc[0]} appears twice")
    return frame


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
    """A tuning record (rlsac.tune) -> dict, None when absent. Refused: not a JSON mapping (``[]``, ``null``),
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
