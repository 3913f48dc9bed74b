"""The one component registry: controllers, estimators, QoS policies, plants and allocators by kind.

Every table row, stage, sweep and CLI command names its pieces by ``{kind, checkpoint,
options}`` (a :class:`ComponentSpec`), so the learned stack (SAC + MLP), the model-based one
(MPC + predictor) and any mix run through the same code, without a branch on a type. The
registry knows each kind by import path only (``"package.module:attribute"``): it imports
nothing of the layers above it, and a spec becomes a picklable :class:`Factory` that a worker
process calls on its own plant.

========== ================== ==========================================================
role       kind               what
========== ================== ==========================================================
controller ``sac``            ``control.sac.SacController``: a SAC-trained actor (``checkpoint``)
controller ``bc``             ``control.sac.SacController``: a behaviour-cloned actor (stage A's
                              ``bc.zip``, the clone SAC starts from)
controller ``mpc``            ``control.mpc.MpcController`` (``options``: its kwargs)
controller ``scripted``       ``control.scripted.ScriptedPickController``
controller ``toy_pick``       ``control.scripted.ToyPickController`` (toy plant only)
estimator  ``none``           ``estimation.base.PassThroughEstimator`` (stale observation)
estimator  ``mlp``/``lstm``   a learned estimator from ``checkpoint`` (``load_estimator``)
estimator  ``sequence``       the Gaussian sequence estimator (``estimation.sequence``), likewise
estimator  ``predictor``      ``estimation.predictor.DelayCompensatingPredictor``
estimator  ``belt_imm``       ``estimation.belt_imm.BeltImmPredictor`` (switching belt, carried)
qos        ``static``         ``adaptation.base.StaticQos`` (``options``)
qos        ``random``         ``adaptation.base.RandomQos``: ``q = 1`` w.p. ``probability``
qos        ``rule``           the covariance-triggered rule on a predictor replica
qos        ``planner``        ``adaptation.planner.QosPlanner`` on a belt-aware predictor replica
qos        ``age_rule``       ``adaptation.rules.AgeTriggeredQos``
qos        ``learned``        ``adaptation.learned.LearnedQosPolicy`` (``checkpoint``: folder)
qos_feat.  ``elapsed_time``   ``adaptation.learned.ElapsedTimeFeature`` (``t / T``)
qos_feat.  ``predictor_std``  ``adaptation.learned.PredictorStdFeature`` on a predictor replica
                              (hybrid: a model-based replica at the edge)
qos_feat.  ``held_history``   ``adaptation.model_free_features.HeldHistoryFeature`` (model-free:
                              ``t / T``, held-position differences, lift, from ``(y, zeta)``)
qos_feat.  ``belief``         ``adaptation.belief_features.BeliefFeature``: the robot's estimate
                              and its uncertainty (bound to the robot's estimator by the loop)
plant      ``conveyor``       ``plants.conveyor.ConveyorPickPlace`` (``ConveyorConfig`` options)
plant      ``toy``            ``plants.toy.ToyConveyor`` (``ToyConveyorConfig`` options)
allocator  ``greedy``         ``wifi.allocators.GreedyEdfAllocator`` (the paper's, sec. 5)
allocator  ``greedy-admit``   ``wifi.allocators.AdmissionGreedyAllocator`` (improved greedy)
allocator  ``convex``         ``wifi.convex.ConvexAllocator`` (OSQP hot path)
allocator  ``convex-cvxpy``   the same allocator solved through its cvxpy model
allocator  ``tick-optimal``   ``wifi.tick_optimal.TickOptimalAllocator`` (exact per tick)
========== ================== ==========================================================

Checkpoint paths are looked up relative to the working directory first, then to the
package's ``models`` folder (so ``checkpoints/stage_a/model.zip`` finds the shipped one).
"""

from __future__ import annotations

import importlib
import importlib.resources
import inspect
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from codesign_mb.core.config import ConfigError, coerce_value, from_mapping

__all__ = [
    "KINDS",
    "ComponentSpec",
    "Factory",
    "Kind",
    "PlantSpec",
    "build",
    "check_options",
    "create",
    "factory",
    "kinds",
    "make_plant",
    "models_dir",
    "plant_factory",
    "resolve",
    "resolve_checkpoint",
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


KINDS: dict[str, dict[str, Kind]] = {
    "controller": {
        "sac": Kind("codesign_mb.control.sac:SacController.load", checkpoint_keyword="path"),
        "bc": Kind("codesign_mb.control.sac:SacController.load", checkpoint_keyword="path"),
        "mpc": Kind("codesign_mb.control.mpc:MpcController.from_env", takes_env=True),
        "scripted": Kind(
            "codesign_mb.control.scripted:ScriptedPickController.from_env", takes_env=True
        ),
        "toy_pick": Kind("codesign_mb.control.scripted:ToyPickController.from_env", takes_env=True),
    },
    "estimator": {
        "none": Kind("codesign_mb.estimation.base:PassThroughEstimator.from_env", takes_env=True),
        "mlp": Kind("codesign_mb.estimation.learned:load_estimator", checkpoint_keyword="path"),
        "lstm": Kind("codesign_mb.estimation.learned:load_estimator", checkpoint_keyword="path"),
        "sequence": Kind(
            "codesign_mb.estimation.learned:load_estimator", checkpoint_keyword="path"
        ),
        "predictor": Kind(
            "codesign_mb.estimation.predictor:DelayCompensatingPredictor.from_env", takes_env=True
        ),
        "belt_imm": Kind(
            "codesign_mb.estimation.belt_imm:BeltImmPredictor.from_env", takes_env=True
        ),
    },
    "qos": {
        "static": Kind("codesign_mb.adaptation.base:StaticQos"),
        "random": Kind("codesign_mb.adaptation.base:RandomQos"),
        "rule": Kind("codesign_mb.rollout.compose:covariance_rule", takes_env=True),
        "planner": Kind("codesign_mb.rollout.compose:qos_planner", takes_env=True),
        "age_rule": Kind("codesign_mb.adaptation.rules:AgeTriggeredQos"),
        "learned": Kind(
            "codesign_mb.adaptation.learned:LearnedQosPolicy.from_env",
            takes_env=True,
            checkpoint_keyword="directory",
        ),
    },
    "qos_feature": {
        "elapsed_time": Kind("codesign_mb.adaptation.learned:ElapsedTimeFeature.from_env"),
        "held_history": Kind(
            "codesign_mb.adaptation.model_free_features:HeldHistoryFeature.from_env"
        ),
        "predictor_std": Kind("codesign_mb.rollout.compose:predictor_std_feature"),
        "belief": Kind("codesign_mb.adaptation.belief_features:BeliefFeature.from_env"),
    },
    "plant": {
        "conveyor": Kind(
            "codesign_mb.plants.conveyor:ConveyorPickPlace.from_options",
            config="codesign_mb.plants.conveyor_config:ConveyorConfig",
        ),
        "toy": Kind(
            "codesign_mb.plants.toy:ToyConveyor.from_options",
            config="codesign_mb.plants.toy:ToyConveyorConfig",
        ),
    },
    "allocator": {
        "greedy": Kind("codesign_mb.wifi.config:greedy_allocator"),
        "convex": Kind("codesign_mb.wifi.config:convex_allocator"),
        "convex-cvxpy": Kind("codesign_mb.wifi.config:convex_cvxpy_allocator"),
        "greedy-admit": Kind("codesign_mb.wifi.allocators:admission_greedy_allocator"),
        "tick-optimal": Kind("codesign_mb.wifi.tick_optimal:tick_optimal_allocator"),
    },
}
"""role -> kind -> :class:`Kind`. Add a component by adding a row."""


def kinds(role: str) -> tuple[str, ...]:
    """The kind names of ``role`` (``ValueError`` naming the roles for an unknown one)."""
    if role not in KINDS:
        raise ValueError(f"role must be one of {', '.join(KINDS)}, got {role!r}")
    return tuple(KINDS[role])


def _kind(role: str, kind: str) -> Kind:
    table = KINDS.get(role, {})
    if not table:
        kinds(role)  # raises, naming the roles
    if kind not in table:
        raise ValueError(f"unknown {role} kind {kind!r}; expected one of {', '.join(table)}")
    return table[kind]


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
    kind = _kind(role, spec.kind)
    kwargs = dict(spec.options)
    if kind.checkpoint_keyword:
        if not spec.checkpoint:
            raise ValueError(f"{role} kind {spec.kind!r} needs a checkpoint")
        kwargs[kind.checkpoint_keyword] = str(resolve_checkpoint(spec.checkpoint))
    elif spec.checkpoint:
        raise ValueError(f"{role} kind {spec.kind!r} takes no checkpoint, got {spec.checkpoint!r}")
    check_options(
        f"{role} kind {spec.kind!r}",
        kind.target,
        spec.options,
        takes_env=kind.takes_env,
        reserved=kind.checkpoint_keyword,
    )
    return Factory(kind.target, kwargs, takes_env=kind.takes_env)


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


def create(role: str, kind: str, *args: Any, **kwargs: Any) -> Any:
    """Call the factory of ``kind`` with positional arguments (plants, allocators)."""
    return resolve(_kind(role, kind).target)(*args, **kwargs)


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
        if self.name not in KINDS["plant"]:
            raise ValueError(
                f"plant.name must be one of {sorted(KINDS['plant'])}, got {self.name!r}"
            )
        if not isinstance(self.options, Mapping):
            raise ValueError(f"plant.options must be a table, got {self.options!r}")
        # The options are the plant config's fields: checked now, where they are read.
        from_mapping(resolve(KINDS["plant"][self.name].config), self.options, where="plant.options")


def make_plant(spec: PlantSpec) -> Any:
    """A fresh plant env (not wrapped) for ``spec``."""
    return create("plant", spec.name, dict(spec.options))


def plant_factory(spec: PlantSpec) -> Factory:
    """A picklable zero-argument factory of ``spec``'s env (what ``evaluate`` takes)."""
    return Factory(
        KINDS["plant"][spec.name].target, {"options": dict(spec.options)}, takes_env=False
    )
