"""Typed configuration: dataclasses built from mappings (TOML/YAML files, CLI) strictly.

A misspelt option must fail, not be ignored: unknown keys raise a ``ValueError`` naming them.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["as_matrix", "from_mapping", "load_config_file", "to_mapping"]

T = TypeVar("T")


def from_mapping(cls: type[T], data: Mapping[str, Any], *, where: str = "") -> T:
    """Build the dataclass ``cls`` from ``data``, recursing into nested dataclass fields.

    Unknown keys raise ``ValueError("unknown key 'x' in <where>; expected one of ...")``;
    validation is the dataclass's own ``__post_init__``.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    if not isinstance(data, Mapping):
        raise ValueError(f"{where or cls.__name__} must be a table, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ValueError(
            f"unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
            f"in {where or cls.__name__}; expected one of {', '.join(sorted(fields))}"
        )
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints.get(name), value, f"{where}.{name}" if where else name)
    return cls(**kwargs)


def _coerce(tp: Any, value: Any, where: str) -> Any:
    nested = _dataclass_in(tp)
    if nested is not None and isinstance(value, Mapping):
        return from_mapping(nested, value, where=where)
    origin = typing.get_origin(tp)
    if origin is tuple and isinstance(value, list):
        return tuple(value)
    return value


def _dataclass_in(tp: Any) -> type | None:
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            if isinstance(arg, type) and dataclasses.is_dataclass(arg):
                return arg
    return None


def to_mapping(config: Any) -> dict[str, Any]:
    """The plain-dict form of a config dataclass (for JSON results and config files)."""
    return dataclasses.asdict(config)


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a TOML (``.toml``) or YAML (``.yaml``/``.yml``) config file into a dict."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"config file {str(path)!r} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".toml":
        with path.open("rb") as fh:
            return tomllib.load(fh)
    if suffix in (".yaml", ".yml"):
        import yaml

        with path.open() as fh:
            data = yaml.safe_load(fh) or {}
        if not isinstance(data, dict):
            raise ValueError(f"config file {str(path)!r} must hold a mapping at the top level")
        return data
    raise ValueError(f"config file must be .toml, .yaml or .yml, got {str(path)!r}")


def as_matrix(
    name: str, value: ArrayLike, shape: tuple[int, int] | None = None
) -> NDArray[np.float64]:
    """``value`` as a finite 2-D float array (scalars become 1 x 1), its shape checked.

    Errors name the field: ``"W must have shape (2, 2), got (3, 3)"``.
    """
    try:
        out = np.array(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric matrix, got {value!r}") from exc
    if out.ndim == 0:
        out = out.reshape(1, 1)
    if out.ndim != 2:
        raise ValueError(f"{name} must be a 2-D matrix, got an array of shape {out.shape}")
    if shape is not None and out.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {out.shape}")
    if not np.isfinite(out).all():
        raise ValueError(f"{name} must be finite, got {out.tolist()}")
    return out
