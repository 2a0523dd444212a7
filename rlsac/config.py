"""Typed configurations: every option has a default, and unknown keys are rejected.

Each section of params.yaml maps onto one dataclass below; ``build(Cls, mapping)`` merges a
mapping over the defaults and raises a one-line error for a key the dataclass does not declare.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, TypeVar

import yaml

from rlsac.errors import RlsacError

T = TypeVar("T")


def build(cls: type[T], overrides: dict[str, Any] | None = None, where: str = "") -> T:
    """Return ``cls`` with its defaults replaced by ``overrides``; nested dataclasses recurse."""
    overrides = dict(overrides or {})
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - set(fields))
    if unknown:
        raise RlsacError(f"unknown config key(s) {unknown} in {where or cls.__name__}; known: {sorted(fields)}")
    kwargs = {}
    for name, value in overrides.items():
        f = fields[name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = build(type(default), value, f"{where}.{name}" if where else name)
        kwargs[name] = value
    return cls(**kwargs)


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


def load_params(path: str | Path = "params.yaml") -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        return {}
    try:
        return yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise RlsacError(f"{path}: invalid YAML ({e.__class__.__name__})") from None
