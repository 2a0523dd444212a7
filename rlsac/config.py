"""Typed configurations: every option has a default, a type and a range, and unknown keys are rejected.

Each section of params.yaml maps onto one dataclass; ``build(Cls, mapping)`` merges a mapping over the
defaults and is the one place where options are checked, for every command and every source (code,
params.yaml, ``--set``):

* unknown keys raise a one-line error naming the known ones;
* each value is coerced to its field's annotated type (``int``, ``float``, ``bool``, ``str``,
  ``list[int]``, ``dict``, a nested config dataclass, ``X | None``); strings such as "1e-4" (YAML 1.1
  reads them as strings) become floats, integral floats such as 1e4 become ints; a float must be finite;
* a class may declare ``ranges = {field: spec}`` (a plain class attribute, not a field): an interval
  "[lo, hi]" / "(lo, hi)" / "[lo, inf)" checked on the value (on each element of a list), or a tuple
  of allowed values;
* a class may define ``check()`` for rules across fields; ``build`` calls it last.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from rlsac.errors import RlsacError

T = TypeVar("T")
SEED_RANGE = "[0, 4294967295]"  # numpy's seeds are unsigned 32-bit integers

_INTERVAL = re.compile(r"^\s*([\[(])\s*([^,]+?)\s*,\s*([^,]+?)\s*([\])])\s*$")


def build(cls: type[T], overrides: dict[str, Any] | None = None, where: str = "") -> T:
    """Return ``cls`` with its defaults replaced by ``overrides``; nested dataclasses recurse.

    Every override is type-checked, coerced and range-checked (see the module docstring); any
    failure is an RlsacError naming the dotted key, e.g. ``train.sac.actor_lr must be > 0``.
    """
    where = where or cls.__name__
    if overrides is None:
        overrides = {}
    if not isinstance(overrides, dict):
        raise RlsacError(f"{where} must be a mapping of options, got {_show(overrides)}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - set(fields), key=str)
    if unknown:
        raise RlsacError(f"unknown config key(s) {unknown} in {where}; known: {sorted(fields)}")
    hints = _hints(cls)
    ranges = getattr(cls, "ranges", None) or {}
    kwargs = {}
    for name, value in overrides.items():
        f = fields[name]
        key = f"{where}.{name}"
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            if not isinstance(value, dict):
                raise RlsacError(f"{key} must be a mapping of {type(default).__name__} options, got {_show(value)}")
            kwargs[name] = build(type(default), value, key)
            continue
        value = coerce(key, value, hints.get(name, Any))
        if name in ranges:
            check_range(key, value, ranges[name])
        kwargs[name] = value
    conf = cls(**kwargs)
    check = getattr(conf, "check", None)
    if callable(check):
        check()
    return conf


def _hints(cls) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # an annotation that cannot be resolved is simply not type-checked
        return {}


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def coerce(key: str, value: Any, tp: Any) -> Any:
    """``value`` as type ``tp`` (see the module docstring) or a one-line RlsacError about ``key``."""
    origin = typing.get_origin(tp)
    if tp is Any or tp is object:
        return value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return coerce(key, value, a)
            except RlsacError as e:
                errors.append(str(e))
        raise RlsacError(errors[0] if len(errors) == 1 else f"{key}: {_show(value)} matches none of {tp}")
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise RlsacError(f"{key} must be true or false, got {_show(value)}")
    if tp is int:
        v = value
        if isinstance(v, str):
            v = _number(v)
        if isinstance(v, float) and math.isfinite(v) and v == int(v):
            v = int(v)
        if isinstance(v, int) and not isinstance(v, bool):
            return v
        raise RlsacError(f"{key} must be an integer, got {_show(value)}")
    if tp is float:
        v = _number(value) if isinstance(value, str) else value
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = float(v)
            if not math.isfinite(v):
                raise RlsacError(f"{key} must be a finite number, got {_show(value)}")
            return v
        raise RlsacError(f"{key} must be a number, got {_show(value)}")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)
        raise RlsacError(f"{key} must be a string, got {_show(value)}")
    if tp is list or origin is list:
        if not isinstance(value, (list, tuple)):
            raise RlsacError(f"{key} must be a list, got {_show(value)}")
        args = typing.get_args(tp)
        return [coerce(f"{key}[{i}]", v, args[0]) for i, v in enumerate(value)] if args else list(value)
    if tp is dict or origin is dict:
        if not isinstance(value, dict):
            raise RlsacError(f"{key} must be a mapping, got {_show(value)}")
        return dict(value)
    return value


def _number(text: str) -> Any:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def check_range(key: str, value: Any, spec: Any) -> None:
    """Check ``value`` (each element of a list) against an interval string or a tuple of choices."""
    if isinstance(value, list):
        for i, v in enumerate(value):
            check_range(f"{key}[{i}]", v, spec)
        return
    if value is None:
        return
    if isinstance(spec, (tuple, list, set, frozenset, dict)):  # a dict: a registry's names
        if value not in spec:
            raise RlsacError(f"{key} must be one of {', '.join(map(str, spec))}, got {_show(value)}")
        return
    m = _INTERVAL.match(str(spec))
    if not m:
        raise ValueError(f"bad range spec {spec!r} for {key}")
    lo_b, lo, hi, hi_b = m.groups()
    lo_v, hi_v = float(lo), float(hi)
    ok = (value >= lo_v if lo_b == "[" else value > lo_v) and (value <= hi_v if hi_b == "]" else value < hi_v)
    if not ok:
        raise RlsacError(f"{key} must be in {lo_b}{lo}, {hi}{hi_b}, got {_show(value)}")


def check_value(key: str, value: Any, tp: Any, spec: Any = None) -> Any:
    """Coerce and range-check one option outside a dataclass (e.g. evaluate's options dict)."""
    value = coerce(key, value, tp)
    if spec is not None:
        check_range(key, value, spec)
    return value


def check_mapping(options: dict[str, Any], defaults: dict[str, Any], where: str,
                  types: dict[str, Any] | None = None, ranges: dict[str, Any] | None = None) -> dict[str, Any]:
    """The same checks as ``build`` for an options dict with a dict of defaults (``rlsac ablate``,
    ``rlsac plot``): unknown keys, and each value not None coerced to ``types[key]`` (else the type of
    its default, when that is a bool, int, float or str) and checked against ``ranges[key]``."""
    types, ranges = types or {}, ranges or {}
    unknown = sorted(set(options) - set(defaults), key=str)
    if unknown:
        raise RlsacError(f"unknown {where} option(s) {unknown}; known: {sorted(defaults)}")
    out = dict(options)
    for key, value in options.items():
        if value is None:
            continue
        default = defaults[key]
        tp = types.get(key, type(default) if isinstance(default, (bool, int, float, str)) else Any)
        out[key] = coerce(f"{where}.{key}", value, tp)
        if key in ranges:
            check_range(f"{where}.{key}", out[key], ranges[key])
    return out


def to_dict(conf) -> dict[str, Any]:
    return dataclasses.asdict(conf)


def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{'a': {'b': 1}} -> {'a.b': 1}, the form MLflow params take."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def load_params(path: str | Path | None = "params.yaml", required: bool = False) -> dict[str, Any]:
    """params.yaml -> mapping. A missing file is {} unless ``required`` (a file the user named);
    a file that is not valid YAML, or whose top level is not a mapping, is an error."""
    if path is None or str(path) == "":
        return {}
    path = Path(path)
    if not path.is_file():
        if required or path.exists():
            raise RlsacError(f"{path}: no such params file" if not path.exists() else f"{path}: not a file")
        return {}
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise RlsacError(f"{path}: invalid YAML ({e.__class__.__name__})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise RlsacError(f"{path}: unreadable ({e.__class__.__name__})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise RlsacError(f"{path}: params file must be a mapping of sections, got {type(data).__name__}")
    return data


DEFAULT_PARAMS = "params.yaml"


def read_params(path: str | Path | None = DEFAULT_PARAMS) -> dict[str, Any]:
    """A command's ``--params`` file -> mapping, every section checked (``check_params``). The default
    ./params.yaml may be absent (code defaults apply); any other file named (``--params FILE``) must exist;
    "" or None = no params file."""
    if not path:
        return {}
    params = load_params(path, required=str(path) != DEFAULT_PARAMS)
    try:
        check_params(params)
    except RlsacError as e:  # the key alone does not say which file holds it (issue #64: --params FILE, a worktree's)
        raise RlsacError(f"{path}: {e}") from None
    return params


# params.yaml section -> "module:function(params)" that types and range-checks it, next to the code that reads it
# (imported when a params file is read, not when this module is)
PARAM_SECTIONS = {
    "lines_data": "rlsac.commands:check_lines_data",
    "lines": "rlsac.commands:check_lines",
    "calibration": "rlsac.commands:check_calibration",
    "train": "rlsac.learners.harness:check_params",
    "evaluate": "rlsac.evaluation.evaluate:check_params",
    "fundamental": "rlsac.experiments.folds:check_fundamental",
    "folds": "rlsac.experiments.folds:protocol",
    "essential": "rlsac.experiments.folds:check_essential",
    "ablation": "rlsac.experiments.ablate:protocol",
    "tuning": "rlsac.evaluation.tune:conf",
    "tuning_budget": "rlsac.evaluation.retune:conf",
    "scale": "rlsac.layout.scale_layout:protocol",
    "positive_control": "rlsac.experiments.positive_control:conf",
    "ladder": "rlsac.layout.ladder_layout:conf",
    "ladder_record": "rlsac.layout.ladder_layout:record",
}


def check_params(params: dict[str, Any]) -> None:
    """Every section of a params file typed and range-checked, whichever command and stage reads it (issue #28,
    item 3: a section was checked only by the stage that used it, and some keys by none): an unknown section is
    an error, each known one goes through its checker (``PARAM_SECTIONS``)."""
    import importlib

    unknown = sorted(set(params) - set(PARAM_SECTIONS), key=str)
    if unknown:
        raise RlsacError(f"unknown params section(s) {unknown}; known: {sorted(PARAM_SECTIONS)}")
    for name in params:
        module, func = PARAM_SECTIONS[name].split(":")
        getattr(importlib.import_module(module), func)(params)


def section(params: dict, *keys: str) -> dict[str, Any]:
    """params[k1][k2]... as a new dict ({} when absent); RlsacError when it is not a mapping."""
    d: Any = params
    for k in keys:
        d = (d or {}).get(k) if isinstance(d, dict) else None
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise RlsacError(f"params section {'.'.join(keys)} must be a mapping, got {type(d).__name__}")
    return dict(d)


def over_defaults(params: dict, name: str, defaults: dict[str, Any]) -> dict[str, Any]:
    """params.yaml section ``name`` over ``defaults`` (deep copies; each top-level key replaced); RlsacError for a key
    ``defaults`` does not have. The caller types and range-checks the values."""
    import copy

    given = section(params, name)
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise RlsacError(f"unknown params key(s) {name}.{unknown}; known: {sorted(defaults)}")
    return {**copy.deepcopy(defaults), **copy.deepcopy(given)}


def parse_sets(pairs: tuple[str, ...] | list[str]) -> dict[str, Any]:
    """("a.b=1", "c=[1, 2]") -> {"a": {"b": 1}, "c": [1, 2]}; values are parsed as YAML."""
    out: dict[str, Any] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        key = key.strip()
        if not sep or not key or any(not p for p in key.split(".")):
            raise RlsacError(f"--set expects key=value (dotted keys allowed), got {pair!r}")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError:
            raise RlsacError(f"--set {key}: value {raw!r} is not valid YAML") from None
        if isinstance(value, str):  # YAML 1.1 reads 1e-4 (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                pass
        d = out
        parts = key.split(".")
        for p in parts[:-1]:
            if not isinstance(d.get(p), dict):
                d[p] = {}
            d = d[p]
        d[parts[-1]] = value
    return out


def deep_update(base: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``new`` merged in, nested mappings merged key by key."""
    out = dict(base)
    for k, v in new.items():
        out[k] = deep_update(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
