"""Typed configuration: dataclasses built from mappings (TOML/YAML files, CLI) strictly.

The dataclass is the schema. :func:`from_mapping` checks every value against its field's
annotation (an integer, a finite number, a string, a boolean, a list, a table, a nested
config), then the dataclass's ``__post_init__`` checks ranges and caps (:func:`check_range`,
:class:`Cap`). A misspelt option fails too: unknown keys are an error. Every failure is one
:class:`ConfigError` line that names the field and the value.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import tomllib
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "EPISODES_CAP",
    "LATENCY_STEPS_CAP",
    "ROBOTS_CAP",
    "SEED_CAP",
    "STEPS_CAP",
    "TRAINING_STEPS_CAP",
    "WORKERS_CAP",
    "Cap",
    "ConfigError",
    "FloatOrInf",
    "as_matrix",
    "check_range",
    "check_writable",
    "coerce_value",
    "from_mapping",
    "load_config_file",
    "show",
    "to_mapping",
]

T = TypeVar("T")


class ConfigError(ValueError):
    """A config value the schema rejects; the message names the field and the value."""


@dataclasses.dataclass(frozen=True)
class Cap:
    """An upper bound on a size a user may ask for, named in the error that enforces it.

    Sizes are capped so that a typo (``1e9`` robots) fails at once with a message instead of
    running out of memory or for ever: ``"robots must be <= 256 (the cap on robots on one
    channel), got 1000000000"``.
    """

    value: int
    what: str


EPISODES_CAP = Cap(100_000, "episodes or seeds of one run")
LATENCY_STEPS_CAP = Cap(1_000, "latency: 40 s, longer than any episode")
ROBOTS_CAP = Cap(256, "robots on one channel")
STEPS_CAP = Cap(1_000_000, "steps of one episode or trace")
TRAINING_STEPS_CAP = Cap(100_000_000, "training steps")
WORKERS_CAP = Cap(256, "worker processes")
SEED_CAP = Cap(2**32 - 1, "seeds: 32 bits")

_INT64_MAX = 2**63 - 1

FloatOrInf = typing.Annotated[float, "infinity allowed"]
"""A float field for which infinity means something (e.g. a Rician factor: no fading);
NaN is still an error. Every other float field must be finite."""


def show(value: Any) -> str:
    """A value as an error message shows it: ``repr``, huge numbers in short form."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        number = float(value)
        if math.isfinite(number) and abs(number) >= 1e15:
            return f"{number:.3g}"
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def check_range(
    name: str,
    value: Any,
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    cap: Cap | None = None,
) -> None:
    """Raise :class:`ConfigError` unless ``value`` (or each item of a list) is in range.

    ``None`` passes (an optional field left unset). Bounds are inclusive except ``gt``;
    ``cap`` is an upper bound whose message says what it protects.

    Examples
    --------
    >>> check_range("trials", 0, ge=1)
    Traceback (most recent call last):
    ...
    codesign_mb.core.config.ConfigError: trials must be >= 1, got 0
    """
    if value is None:
        return
    items = value if isinstance(value, Iterable) and not isinstance(value, str) else (value,)
    for item in items:
        if isinstance(item, bool) or not isinstance(item, numbers.Real):
            raise ConfigError(f"{name} must be a finite number, got {show(item)}")
        v = int(item) if isinstance(item, numbers.Integral) else float(item)
        if not math.isfinite(v):
            raise ConfigError(f"{name} must be a finite number, got {show(item)}")
        if ge is not None and v < ge:
            raise ConfigError(f"{name} must be >= {ge}, got {show(v)}")
        if gt is not None and v <= gt:
            raise ConfigError(f"{name} must be > {gt}, got {show(v)}")
        if le is not None and v > le:
            raise ConfigError(f"{name} must be <= {le}, got {show(v)}")
        if cap is not None and v > cap.value:
            raise ConfigError(
                f"{name} must be <= {cap.value} (the cap on {cap.what}), got {show(v)}"
            )


def check_writable(name: str, path: str | Path) -> None:
    """Raise :class:`ConfigError` unless a file can be written at ``path``.

    The nearest existing folder on the way (the parent, or the first ancestor a writer would
    create the missing folders under) must take a new file: a temporary one is created there
    and removed, which catches what permission bits do not (``/proc``, a read-only mount).
    """
    import tempfile

    target = Path(path)
    if target.is_dir():
        raise ConfigError(f"{name} must be a file, got the folder {str(target)!r}")
    folder = target.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        if not folder.is_dir():
            raise OSError(f"{str(folder)!r} is not a folder")
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".codesign-check-"):
            pass
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise ConfigError(f"{name}: cannot write {str(target)!r} ({reason})") from None


def from_mapping(cls: type[T], data: Mapping[str, Any], *, where: str = "") -> T:
    """Build the dataclass ``cls`` from ``data``, each value checked against its annotation.

    Nested dataclass fields are built recursively; lists become tuples; an integer is
    accepted for a float and an integral float (``1e5``) for an integer. Unknown or missing
    keys, a wrong type, NaN or infinity, and whatever ``cls.__post_init__`` rejects
    (``ValueError`` or ``TypeError``) raise :class:`ConfigError` naming the field (dotted
    from ``where``) and the value.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where or cls.__name__} must be a table, got {show(data)}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(str(k) for k in data if k not in fields)
    if unknown:
        raise ConfigError(
            f"unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}"
            f"{f' in {where}' if where else ''}; expected one of {', '.join(sorted(fields))}"
        )
    missing = [
        name
        for name, f in fields.items()
        if name not in data
        and f.default is dataclasses.MISSING
        and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise ConfigError(f"missing key {missing[0]!r}{f' in {where}' if where else ''}")
    hints = typing.get_type_hints(cls, include_extras=True)
    kwargs = {
        name: coerce_value(hints.get(name, Any), value, f"{where}.{name}" if where else name)
        for name, value in data.items()
    }
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as exc:
        message = str(exc)
        first, parent, leaf = message.split(" ", 1)[0], *where.rpartition(".")[::2]
        if first.startswith(f"{leaf}.") and where:  # "sac.gamma ..." of qos.sac: qos.sac.gamma
            message = f"{parent}.{message}" if parent else message
        elif where:  # "horizon must be ..." of the table env -> "env.horizon must be ..."
            message = f"{where}{'.' if first in fields else ': '}{message}"
        raise ConfigError(message) from exc


def coerce_value(tp: Any, value: Any, name: str) -> Any:
    """``value`` checked against the annotation ``tp`` (and normalised); else ConfigError."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any or isinstance(tp, TypeVar):
        return value
    if tp == FloatOrInf:
        if isinstance(value, numbers.Real) and math.isinf(value):
            return float(value)
        return _number(value, name)
    if origin is typing.Annotated:
        return coerce_value(args[0], value, name)
    if origin in (typing.Union, types.UnionType):
        return _coerce_union(args, value, name)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return value if isinstance(value, tp) else from_mapping(tp, value, where=name)
    if tp is bool:
        if isinstance(value, bool | np.bool_):
            return bool(value)
        raise ConfigError(f"{name} must be true or false, got {show(value)}")
    if tp is int:
        return _integer(value, name)
    if tp is float:
        return _number(value, name)
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{name} must be a string, got {show(value)}")
    if origin is tuple or tp is tuple or origin is list:
        return _sequence(tp, value, name)
    if origin in (dict, Mapping) or tp in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{name} must be a table, got {show(value)}")
        item = args[1] if len(args) == 2 else Any
        return {str(k): coerce_value(item, v, f"{name}.{k}") for k, v in value.items()}
    if origin is typing.Literal:
        if value in args:
            return value
        raise ConfigError(f"{name} must be one of {', '.join(map(repr, args))}, got {show(value)}")
    if tp is Path and isinstance(value, str):
        return Path(value)
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ConfigError(f"{name} must be a {tp.__name__}, got {show(value)}")
    return value


def _coerce_union(args: tuple[Any, ...], value: Any, name: str) -> Any:
    if value is None and type(None) in args:
        return None
    arms = [a for a in args if a is not type(None)]
    if isinstance(value, Mapping):  # a table is meant for the config arm: its own errors
        nested = [a for a in arms if isinstance(a, type) and dataclasses.is_dataclass(a)]
        arms = nested or arms
    if len(arms) == 1:
        return coerce_value(arms[0], value, name)
    for arm in arms:
        try:
            return coerce_value(arm, value, name)
        except ConfigError:
            continue
    kinds = " or ".join(dict.fromkeys(_describe(a) for a in arms))
    raise ConfigError(f"{name} must be {kinds}, got {show(value)}")


def _describe(tp: Any) -> str:
    """What a value of the annotation ``tp`` is, in a user's words ("an integer")."""
    origin = typing.get_origin(tp) or tp
    words = {int: "an integer", float: "a number", str: "a string", bool: "true or false"}
    if origin in words:
        return words[origin]
    if origin in (tuple, list):
        return "a list"
    if origin in (dict, Mapping) or dataclasses.is_dataclass(origin):
        return "a table"
    return getattr(tp, "__name__", str(tp))


def _integer(value: Any, name: str) -> int:
    if isinstance(value, numbers.Integral) and not isinstance(value, bool | np.bool_):
        out = int(value)
    elif isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_):
        number = float(value)
        if not (math.isfinite(number) and number.is_integer()):
            raise ConfigError(f"{name} must be an integer, got {show(value)}")
        out = int(number)
    else:
        raise ConfigError(f"{name} must be an integer, got {show(value)}")
    if abs(out) > _INT64_MAX:
        raise ConfigError(f"{name} must be an integer below 2**63, got {show(value)}")
    return out


def _number(value: Any, name: str) -> float:
    if isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_):
        try:
            out = float(value)
        except OverflowError:
            out = math.inf
        if math.isfinite(out):
            return out
        raise ConfigError(f"{name} must be a finite number, got {show(value)}")
    raise ConfigError(f"{name} must be a number, got {show(value)}")


def _sequence(tp: Any, value: Any, name: str) -> Any:
    if isinstance(value, str | bytes) or not isinstance(value, list | tuple):
        raise ConfigError(f"{name} must be a list, got {show(value)}")
    args = typing.get_args(tp)
    if typing.get_origin(tp) is list:
        items = [args[0] if args else Any] * len(value)
    elif len(args) == 2 and args[1] is Ellipsis:
        items = [args[0]] * len(value)
    elif args:
        if len(value) != len(args):
            raise ConfigError(f"{name} must hold {len(args)} values, got {show(value)}")
        items = list(args)
    else:
        items = [Any] * len(value)
    out = [
        coerce_value(t, v, f"{name}[{i}]")
        for i, (t, v) in enumerate(zip(items, value, strict=True))
    ]
    return out if typing.get_origin(tp) is list else tuple(out)


def to_mapping(config: Any) -> dict[str, Any]:
    """The plain-dict form of a config dataclass (for JSON results and config files)."""
    return dataclasses.asdict(config)


def load_config_file(path: str | Path) -> dict[str, Any]:
    """Read a TOML (``.toml``) or YAML (``.yaml``/``.yml``) config file into a dict.

    A syntax error is a ``ValueError`` naming the file and the line.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"config file {str(path)!r} does not exist")
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".yaml", ".yml"):
        raise ValueError(f"config file must be .toml, .yaml or .yml, got {str(path)!r}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"config file {str(path)!r} is not UTF-8 text ({exc.reason})") from None
    if suffix == ".toml":
        try:
            return tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            end = f"at the end, line {text.count(chr(10)) + 1}"
            message = str(exc).replace("at end of document", end)
            raise ValueError(f"config file {str(path)!r} is not valid TOML: {message}") from None
    import yaml

    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(
            f"config file {str(path)!r} is not valid YAML: {_yaml_error(exc)}"
        ) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"config file {str(path)!r} must hold a mapping at the top level")
    return data


def _yaml_error(exc: Exception) -> str:
    """A PyYAML error in one line: the problem and where (line and column, 1-based)."""
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    if mark is None:
        return " ".join(str(problem).split())
    return f"{' '.join(str(problem).split())} (at line {mark.line + 1}, column {mark.column + 1})"


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
