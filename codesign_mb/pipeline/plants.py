"""Which plant a pipeline stage trains on, by name: the conveyor robot or the kinematic toy.

A :class:`PlantSpec` is part of every stage config, so the same command trains on either env
(``plant.name = "toy"`` makes a stage run in seconds, which the tests use).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym

from codesign_mb.config import from_mapping

__all__ = ["PLANTS", "PlantSpec", "make_plant", "make_plant_from", "plant_factory"]


def _conveyor(options: Mapping[str, Any]) -> gym.Env:
    from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace

    return ConveyorPickPlace(config=from_mapping(ConveyorConfig, options, where="plant.options"))


def _toy(options: Mapping[str, Any]) -> gym.Env:
    from codesign_mb.pipeline.toy import ToyConveyor, ToyConveyorConfig

    return ToyConveyor(config=from_mapping(ToyConveyorConfig, options, where="plant.options"))


PLANTS: dict[str, Callable[[Mapping[str, Any]], gym.Env]] = {
    "conveyor": _conveyor,
    "toy": _toy,
}
"""Plant factories by name; each takes the ``options`` mapping of its config dataclass."""


@dataclass(frozen=True)
class PlantSpec:
    """A plant by name plus the fields of its config dataclass.

    Parameters
    ----------
    name:
        A key of :data:`PLANTS`: ``"conveyor"`` (:class:`ConveyorConfig` options) or ``"toy"``
        (:class:`~codesign_mb.pipeline.toy.ToyConveyorConfig` options).
    options:
        Fields of that config, e.g. ``{"belt_speed_mps": 0.2}``; unknown ones are an error.
    """

    name: str = "conveyor"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.name not in PLANTS:
            raise ValueError(f"plant.name must be one of {sorted(PLANTS)}, got {self.name!r}")
        if not isinstance(self.options, Mapping):
            raise ValueError(f"plant.options must be a table, got {self.options!r}")


def make_plant(spec: PlantSpec) -> gym.Env:
    """A fresh plant env (not wrapped) for ``spec``."""
    return PLANTS[spec.name](dict(spec.options))


def make_plant_from(name: str, options: Mapping[str, Any] | None = None) -> gym.Env:
    """:func:`make_plant` from plain arguments (a picklable factory target)."""
    return make_plant(PlantSpec(name, dict(options or {})))


def plant_factory(spec: PlantSpec) -> Any:
    """A picklable zero-argument factory of ``spec``'s env (what ``evaluate`` takes)."""
    from codesign_mb.evaluation.evaluate import Factory

    return Factory(
        "codesign_mb.pipeline.plants:make_plant_from",
        {"name": spec.name, "options": dict(spec.options)},
        takes_env=False,
    )
