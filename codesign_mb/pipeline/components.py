"""Controllers, estimators and QoS policies by configuration: ``{kind, checkpoint, options}``.

Every stage and every table row names its pieces with a :class:`ComponentSpec`, so the same
stage-C trainer and the same table code run the learned stack (SAC + MLP), the model-based one
(MPC + predictor) or any mix, without a branch on a type. A spec becomes a picklable
:class:`~codesign_mb.evaluation.evaluate.Factory` (what :func:`evaluate` takes), and
:func:`build` calls it on a plant env.

Known kinds (add one by adding an entry to the tables below):

========== ================== ==========================================================
role       kind               what
========== ================== ==========================================================
controller ``sac``            ``control.sac.SacController`` from ``checkpoint``
controller ``mpc``            ``control.mpc.MpcController`` (``options``: its kwargs)
controller ``scripted``       ``control.scripted.ScriptedPickController``
controller ``toy_pick``       ``pipeline.toy.ToyPickController`` (toy plant only)
estimator  ``none``/``plain`` ``estimation.base.PassThroughEstimator``
estimator  ``mlp``/``lstm``   a learned estimator from ``checkpoint`` (``load_estimator``)
estimator  ``predictor``      ``estimation.predictor.DelayCompensatingPredictor``
qos        ``static``         ``adaptation.base.StaticQos`` (``options``)
qos        ``learned``        ``adaptation.learned.LearnedQosPolicy`` (``checkpoint``: folder)
========== ================== ==========================================================

Checkpoint paths are looked up relative to the working directory first, then to the
package's ``models`` folder (so ``checkpoints/stage_a/model.zip`` finds the shipped one).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "CONTROLLER_KINDS",
    "ESTIMATOR_KINDS",
    "QOS_KINDS",
    "ComponentSpec",
    "build",
    "factory",
    "models_dir",
    "resolve_checkpoint",
]

# kind -> (factory target, takes_env, needs_checkpoint, checkpoint keyword)
CONTROLLER_KINDS: dict[str, tuple[str, bool, bool, str]] = {
    "sac": ("codesign_mb.control.sac:SacController.load", False, True, "path"),
    "mpc": ("codesign_mb.control.mpc:MpcController.from_env", True, False, ""),
    "scripted": ("codesign_mb.pipeline.components:scripted_pick", True, False, ""),
    "toy_pick": ("codesign_mb.pipeline.toy:ToyPickController.from_env", True, False, ""),
}
ESTIMATOR_KINDS: dict[str, tuple[str, bool, bool, str]] = {
    "none": ("codesign_mb.estimation.base:PassThroughEstimator", False, False, ""),
    "plain": ("codesign_mb.estimation.base:PassThroughEstimator", False, False, ""),
    "mlp": ("codesign_mb.estimation.learned:load_estimator", False, True, "path"),
    "lstm": ("codesign_mb.estimation.learned:load_estimator", False, True, "path"),
    "predictor": (
        "codesign_mb.estimation.predictor:DelayCompensatingPredictor.from_env",
        True,
        False,
        "",
    ),
}
QOS_KINDS: dict[str, tuple[str, bool, bool, str]] = {
    "static": ("codesign_mb.adaptation.base:StaticQos", False, False, ""),
    "rule": ("codesign_mb.adaptation.rules:CovarianceTriggeredQos.from_env", True, False, ""),
    "age_rule": ("codesign_mb.adaptation.rules:AgeTriggeredQos", False, False, ""),
    "learned": (
        "codesign_mb.adaptation.learned:LearnedQosPolicy.from_env",
        True,
        True,
        "directory",
    ),
}
_ROLES = {"controller": CONTROLLER_KINDS, "estimator": ESTIMATOR_KINDS, "qos": QOS_KINDS}


@dataclass(frozen=True)
class ComponentSpec:
    """One controller, estimator or QoS policy, by kind.

    Parameters
    ----------
    kind:
        A key of the role's table (see the module docstring).
    checkpoint:
        File or folder of a learned component (required for ``sac``, ``mlp``, ``lstm``,
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


def scripted_pick(env: Any, **options: Any) -> Any:
    """The conveyor's :class:`~codesign_mb.control.scripted.ScriptedPickController` for ``env``."""
    from codesign_mb.control.scripted import ScriptedPickController

    return ScriptedPickController(env.unwrapped.config, **options)


def models_dir() -> Path:
    """The package's ``models`` folder (``models/`` of the source tree in an editable install)."""
    import codesign_mb.models

    return Path(codesign_mb.models.__file__).resolve().parent


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


def factory(role: str, spec: ComponentSpec) -> Any:
    """The picklable :class:`~codesign_mb.evaluation.evaluate.Factory` of ``spec``."""
    from codesign_mb.evaluation.evaluate import Factory

    table = _ROLES.get(role)
    if table is None:
        raise ValueError(f"role must be one of {', '.join(_ROLES)}, got {role!r}")
    if spec.kind not in table:
        raise ValueError(f"unknown {role} kind {spec.kind!r}; expected one of {', '.join(table)}")
    target, takes_env, needs_checkpoint, keyword = table[spec.kind]
    kwargs = dict(spec.options)
    if needs_checkpoint:
        if not spec.checkpoint:
            raise ValueError(f"{role} kind {spec.kind!r} needs a checkpoint")
        kwargs[keyword] = str(resolve_checkpoint(spec.checkpoint))
    elif spec.checkpoint:
        raise ValueError(f"{role} kind {spec.kind!r} takes no checkpoint, got {spec.checkpoint!r}")
    return Factory(target, kwargs, takes_env=takes_env)


def build(role: str, spec: ComponentSpec, env: Any) -> Any:
    """Build ``spec`` for the plant ``env`` (wrapped or not) in this process."""
    return factory(role, spec)(env.unwrapped if hasattr(env, "unwrapped") else env)
