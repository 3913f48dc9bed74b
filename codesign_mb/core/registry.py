"""The one component registry: the mechanism (kind, spec, factory); the kinds live at the edges.

Every table row, stage, sweep and CLI command names its pieces by ``{kind, checkpoint,
options}`` (a :class:`ComponentSpec`), so the learned stack (SAC + MLP), the model-based one
(MPC + predictor) and any mix run through the same code, without a branch on a type.

Each package registers its own kinds in one module of its own (``control/kinds.py``,
``estimation/kinds.py``, ``adaptation/kinds.py``, ``rollout/kinds.py``, ``plants/kinds.py``,
``wifi/kinds.py``) with :func:`register`. That module is an entry point of the group
``codesign_mb.kinds`` (``pyproject.toml``), named by the role it serves, and is imported the
first time the role is asked for: this module names no module above it, another package adds
kinds of its own the same way (a plugin), and each kinds module imports its targets for type
checking, where import-linter sees them. A kind names its factory by import path
(``"package.module:attribute"``): nothing is imported before it is built, its signature is the
schema of its options, and a spec becomes a picklable :class:`Factory` that a worker process
calls on its own plant.

Roles: ``controller``, ``estimator``, ``qos``, ``qos_feature``, ``plant``, ``perception`` (the
conveyor's edge perception error models), ``linear_plant`` (the named plants of the linear
study) and ``allocator``; each kinds module lists its kinds and what they are.

Checkpoint paths are looked up relative to the working directory first, then to the
package's ``models`` folder (so ``checkpoints/stage_a/model.zip`` finds the shipped one).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.resources
import inspect
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from codesign_mb.core.config import ConfigError, coerce_value, from_mapping

__all__ = [
    "ENTRY_POINT_GROUP",
    "ComponentSpec",
    "Factory",
    "Kind",
    "PlantSpec",
    "build",
    "check_options",
    "create",
    "factory",
    "kind",
    "kinds",
    "make_plant",
    "models_dir",
    "plant_factory",
    "register",
    "resolve",
    "resolve_checkpoint",
    "roles",
]


def resolve(target: str) -> Any:
    """The object named ``"package.module:attribute"`` (dotted attributes allowed)."""
    module_name, _, attr = target.partition(":")
    if not module_name or not attr:
        raise ValueError(f"factory target must be 'module:attribute', got {target!r}")
    obj: Any = importlib.import_module(module_name)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@dataclass(frozen=True)
class Factory:
    """A picklable factory named by import path: ``target(env, **kwargs)`` or ``target(**kwargs)``.

    Parameters
    ----------
    target:
        ``"package.module:attribute"`` (dotted attributes allowed, e.g. a classmethod).
    kwargs:
        Keyword arguments of the call.
    takes_env:
        Whether ``target`` takes the plant env as its first argument.

    Examples
    --------
    >>> f = Factory("codesign_mb.adaptation.base:StaticQos", {"reliability": 0.5}, takes_env=False)
    >>> f()
    StaticQos(reliability=0.5, latency_steps=0)
    """

    target: str
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    takes_env: bool = True

    def __call__(self, env: Any = None) -> Any:
        fn = resolve(self.target)
        if self.takes_env:
            return fn(env, **dict(self.kwargs))
        return fn(**dict(self.kwargs))


@dataclass(frozen=True)
class Kind:
    """How one kind is built: its factory, whether it takes the plant, its checkpoint keyword."""

    target: str
    takes_env: bool = False
    checkpoint_keyword: str = ""  # non-empty: a checkpoint is required and passed by this name
    config: str = ""  # plants: the config dataclass ("module:Class") their options are


ENTRY_POINT_GROUP = "codesign_mb.kinds"
"""The entry-point group of the kinds modules: an entry point's name is its role (``qos``, or
``qos.rollout`` for a second module of the role), its value the module that registers them."""

_REGISTERED: dict[str, dict[str, Kind]] = {}
_LOADED: set[str] = set()


def register(role: str, table: Mapping[str, Kind]) -> None:
    """Register the kinds of ``table`` (name -> :class:`Kind`) in ``role``: called by the
    package that owns them, in its kinds module."""
    if not (isinstance(role, str) and role):
        raise ValueError(f"role must be a non-empty string, got {role!r}")
    registered = _REGISTERED.setdefault(role, {})
    for name, kind in table.items():
        if not (isinstance(name, str) and name):
            raise ValueError(f"a {role} kind name must be a non-empty string, got {name!r}")
        if not isinstance(kind, Kind):
            raise TypeError(f"{role} kind {name!r} must be a Kind, got {type(kind).__name__}")
        if registered.get(name, kind) != kind:
            raise ValueError(f"{role} kind {name!r} is registered twice with different factories")
        registered[name] = kind


def _entry_points() -> dict[str, list[str]]:
    """Role -> the kinds modules its entry points name."""
    modules: dict[str, list[str]] = {}
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        modules.setdefault(entry.name.partition(".")[0], []).append(entry.value)
    return modules


def roles() -> tuple[str, ...]:
    """Every role with kinds: those of the entry points, and any registered directly."""
    return tuple(dict.fromkeys([*_entry_points(), *_REGISTERED]))


def _table(role: str) -> dict[str, Kind]:
    """The kinds of ``role``; its kinds modules are imported the first time it is asked for."""
    if role not in _LOADED:
        for module in _entry_points().get(role, []):
            importlib.import_module(module)
        _LOADED.add(role)
    table = _REGISTERED.get(role, {})
    if not table:
        raise ValueError(f"role must be one of {', '.join(roles())}, got {role!r}")
    return table


def kinds(role: str) -> tuple[str, ...]:
    """The kind names of ``role`` (``ValueError`` naming the roles for an unknown one)."""
    return tuple(_table(role))


def kind(role: str, name: str) -> Kind:
    """The :class:`Kind` registered as ``name`` in ``role`` (``ValueError`` naming the kinds)."""
    table = _table(role)
    if name not in table:
        raise ValueError(f"unknown {role} kind {name!r}; expected one of {', '.join(table)}")
    return table[name]


@dataclass(frozen=True)
class ComponentSpec:
    """One controller, estimator, QoS policy, plant or allocator, by kind.

    Parameters
    ----------
    kind:
        A key of the role's table (see the module docstring).
    checkpoint:
        File or folder of a learned component (required for ``sac``, ``bc``, ``mlp``, ``lstm``,
        ``learned``).
    options:
        Keyword arguments of the component's factory (e.g. ``{"reliability": 1.0}`` for
        ``static``).
    """

    kind: str
    checkpoint: str | None = None
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or not self.kind:
            raise ValueError(f"component kind must be a non-empty string, got {self.kind!r}")
        if not isinstance(self.options, Mapping):
            raise ValueError(f"component options must be a table, got {self.options!r}")


def models_dir() -> Path:
    """The package's ``models`` folder (``models/`` of the source tree in an editable install)."""

    return Path(str(importlib.resources.files("codesign_mb.models"))).resolve()


def resolve_checkpoint(path: str | Path) -> Path:
    """An existing checkpoint path: as given, else under :func:`models_dir`.

    Raises ``ValueError`` naming both places when neither exists.
    """
    p = Path(path).expanduser()
    if p.exists():
        return p.resolve()
    if not p.is_absolute():
        q = models_dir() / p
        if q.exists():
            return q
        if p.parts and p.parts[0] == "models":
            q = models_dir() / Path(*p.parts[1:])
            if q.exists():
                return q
    raise ValueError(
        f"checkpoint {str(path)!r} not found (looked in the working directory and in "
        f"{models_dir()}); train it with `codesign train`"
    )


def factory(role: str, spec: ComponentSpec) -> Factory:
    """The picklable :class:`Factory` of ``spec`` in ``role``."""
    found = kind(role, spec.kind)
    kwargs = dict(spec.options)
    if found.checkpoint_keyword:
        if not spec.checkpoint:
            raise ValueError(f"{role} kind {spec.kind!r} needs a checkpoint")
        kwargs[found.checkpoint_keyword] = str(resolve_checkpoint(spec.checkpoint))
    elif spec.checkpoint:
        raise ValueError(f"{role} kind {spec.kind!r} takes no checkpoint, got {spec.checkpoint!r}")
    check_options(
        f"{role} kind {spec.kind!r}",
        found.target,
        spec.options,
        takes_env=found.takes_env,
        reserved=found.checkpoint_keyword,
    )
    return Factory(found.target, kwargs, takes_env=found.takes_env)


def check_options(
    what: str,
    target: str | Any,
    options: Mapping[str, Any],
    *,
    takes_env: bool = False,
    reserved: str = "",
) -> None:
    """Options checked against the signature of ``target`` (a callable or its import path):
    known names, and the types of those annotated as scalars.

    The signature is the options' schema: an unknown name or a value of the wrong type is a
    :class:`~codesign_mb.core.config.ConfigError` when the config is read, not a
    ``TypeError`` in a worker. ``reserved`` names a keyword the caller passes itself.
    """
    if not options:
        return
    fn = resolve(target) if isinstance(target, str) else target
    try:
        signature = inspect.signature(fn, eval_str=True)
    except NameError:  # an annotation imported for type checking only: names, no types
        signature = inspect.signature(fn)
    params = list(signature.parameters.values())[1 if takes_env else 0 :]
    owner = getattr(fn, "__self__", None)
    if any(p.kind is p.VAR_KEYWORD for p in params) and isinstance(owner, type):
        # A classmethod forwarding **overrides to its class: the constructor is the schema.
        init = inspect.signature(owner, eval_str=True).parameters.values()
        params = [p for p in params if p.kind is not p.VAR_KEYWORD] + list(init)
    if any(p.kind is p.VAR_KEYWORD for p in params):
        return
    named = {p.name: p for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    named.pop(reserved, None)
    unknown = sorted(str(k) for k in options if k not in named)
    if unknown:
        raise ConfigError(
            f"unknown option{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))} "
            f"of {what}; expected {'one of ' + ', '.join(sorted(named)) if named else 'none'}"
        )
    for name, value in options.items():
        annotation = named[name].annotation
        scalars = {int, float, bool, str, type(None)}
        arms = set(typing.get_args(annotation)) or {annotation}
        if arms <= scalars:  # float, int | None, ...: checked like a config field
            coerce_value(annotation, value, f"options.{name} of {what}")


def build(role: str, spec: ComponentSpec, env: Any) -> Any:
    """Build ``spec`` for the plant ``env`` (wrapped or not) in this process."""
    return factory(role, spec)(env.unwrapped if hasattr(env, "unwrapped") else env)


def create(role: str, name: str, *args: Any, **kwargs: Any) -> Any:
    """Call the factory of ``kind`` with positional arguments (plants, allocators)."""
    return resolve(kind(role, name).target)(*args, **kwargs)


@dataclass(frozen=True)
class PlantSpec:
    """A plant by kind plus the fields of its config dataclass.

    Parameters
    ----------
    name:
        A plant kind: ``"conveyor"`` (``ConveyorConfig`` options) or ``"toy"``
        (``ToyConveyorConfig`` options).
    options:
        Fields of that config, e.g. ``{"belt_speed_mps": 0.2}``; unknown ones are an error.
    """

    name: str = "conveyor"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.name not in kinds("plant"):
            raise ValueError(
                f"plant.name must be one of {sorted(kinds('plant'))}, got {self.name!r}"
            )
        if not isinstance(self.options, Mapping):
            raise ValueError(f"plant.options must be a table, got {self.options!r}")
        # The options are the plant config's fields: checked now, where they are read.
        from_mapping(resolve(kind("plant", self.name).config), self.options, where="plant.options")


def make_plant(spec: PlantSpec) -> Any:
    """A fresh plant env (not wrapped) for ``spec``."""
    return create("plant", spec.name, dict(spec.options))


def plant_factory(spec: PlantSpec) -> Factory:
    """A picklable zero-argument factory of ``spec``'s env (what ``evaluate`` takes)."""
    target = kind("plant", spec.name).target
    return Factory(target, {"options": dict(spec.options)}, takes_env=False)
