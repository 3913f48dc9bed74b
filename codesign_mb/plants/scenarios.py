"""Named conveyor scenarios: presets of :class:`~codesign_mb.plants.conveyor_config.ConveyorConfig`.

A scenario is a set of config fields (the rest keep their defaults). :data:`SCENARIOS` is the
one source; ``configs/scenarios/<name>.toml`` holds the same options as files (written by
:func:`scenario_toml`, checked against :data:`SCENARIOS` by the tests). Commands take
``--scenario NAME``; the default is :data:`DEFAULT_SCENARIO` (``realistic``: a task a robot
without packets fails, so a co-design's success is not luck; ``paper`` stays for continuity
with the paper's Table I and for the shipped learned checkpoints, trained on it).

``paper``
    The paper's plant, exactly the config's defaults: a constant 0.2 m/s belt, the object
    spawned at a fixed point along the belt (random across it), perceived without error, the
    packet carrying its true velocity.
``constant-0.2``, ``constant-0.6``
    The constant belt at 0.2 (the same as ``paper``) or 0.6 m/s.
``variable``
    0.6 m/s nominal with seeded speed steps (+-30 %) and stops.
``realistic``
    What an edge camera over a real belt gives: the belt speed drawn per episode from
    0.1-0.6 m/s (the robot assumes the nominal 0.35 m/s) with seeded steps and stops; the
    object's start random along (+-5 cm) and across (+-8 cm) the belt and its spawn time
    random (0-10 steps); small slips and turns on the belt; and perception at the edge with
    errors: the packet carries the perceived position only (no velocity), with 3 mm noise, a
    2 mm per-episode bias and 5 % missed detections. Without packets the prior is wrong by
    the spread of speed, start and spawn time, which a grasp does not tolerate.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from codesign_mb.core.config import from_mapping

if TYPE_CHECKING:  # the names alone import no physics (the sweep and the CLI read them)
    from codesign_mb.plants.conveyor_config import ConveyorConfig

__all__ = [
    "DEFAULT_SCENARIO",
    "SCENARIOS",
    "Scenario",
    "get_scenario",
    "scenario_config",
    "scenario_help",
    "scenario_options",
    "scenario_toml",
]


@dataclass(frozen=True)
class Scenario:
    """A named preset: a one-line description and the :class:`ConveyorConfig` fields it sets."""

    name: str
    description: str
    options: Mapping[str, Any] = field(default_factory=dict)

    def config(self, **overrides: Any) -> ConveyorConfig:
        """The :class:`ConveyorConfig` of the preset with ``overrides`` on top (checked)."""
        from codesign_mb.plants.conveyor_config import ConveyorConfig

        return from_mapping(
            ConveyorConfig, {**self.options, **overrides}, where=f"scenario {self.name}"
        )


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario(
            "paper",
            "the paper's plant: constant 0.2 m/s belt, exact perception, true velocity sent",
            {"belt_speed_mps": 0.2, "belt_profile": "constant"},
        ),
        Scenario(
            "realistic",
            "belt 0.1-0.6 m/s per episode with steps and stops, random start and spawn time, "
            "slips, perceived position only (noise, bias, missed detections)",
            {
                "belt_speed_mps": 0.35,
                "belt_speed_range_mps": (0.1, 0.6),
                "belt_profile": "variable",
                "belt_change_steps": (10, 30),
                "belt_speed_jitter": 0.3,
                "belt_stop_probability": 0.2,
                "spawn_along_range_m": 0.05,
                "spawn_lateral_range_m": 0.08,
                "spawn_delay_steps": (0, 10),
                "disturbance_probability": 0.02,
                "disturbance_speed_std_mps": 0.05,
                "disturbance_spin_std_radps": 0.5,
                "perceive_velocity": False,
                "perception_noise_std_m": 0.003,
                "perception_bias_std_m": 0.002,
                "perception_miss_probability": 0.05,
            },
        ),
        Scenario(
            "variable",
            "0.6 m/s nominal with seeded speed steps (+-30 %) and stops",
            {"belt_speed_mps": 0.6, "belt_profile": "variable"},
        ),
        Scenario(
            "constant-0.2",
            "constant 0.2 m/s belt (the same plant as paper)",
            {"belt_speed_mps": 0.2, "belt_profile": "constant"},
        ),
        Scenario(
            "constant-0.6",
            "constant 0.6 m/s belt, otherwise the paper's plant",
            {"belt_speed_mps": 0.6, "belt_profile": "constant"},
        ),
    )
}
"""Scenario name -> :class:`Scenario` (the source of ``configs/scenarios/*.toml``)."""

DEFAULT_SCENARIO = "realistic"
"""The scenario ``evaluate``, ``table`` and ``sweep`` use when none is given."""


def get_scenario(name: str) -> Scenario:
    """The scenario called ``name``; an unknown name is a ``ValueError`` naming the choices."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(
            f"unknown scenario {name!r}; expected one of {', '.join(SCENARIOS)}"
        ) from None


def scenario_options(name: str) -> dict[str, Any]:
    """The :class:`ConveyorConfig` fields of scenario ``name`` (a fresh dict)."""
    return dict(get_scenario(name).options)


def scenario_config(name: str, **overrides: Any) -> ConveyorConfig:
    """The :class:`ConveyorConfig` of scenario ``name`` with ``overrides`` on top."""
    return get_scenario(name).config(**overrides)


def scenario_help() -> str:
    """One line for a ``--scenario`` option's help: the names and the default."""
    return (
        f"Conveyor scenario: {', '.join(SCENARIOS)} (configs/scenarios/NAME.toml). "
        f"[default: {DEFAULT_SCENARIO}]"
    )


def scenario_toml(name: str) -> str:
    """The text of ``configs/scenarios/<name>.toml``: the description and an ``[env]`` table."""
    scenario = get_scenario(name)
    lines = [
        f"# Conveyor scenario {name!r}: {scenario.description}.",
        "# Generated from codesign_mb.plants.scenarios.SCENARIOS (tests check they agree);",
        "# the [env] table holds ConveyorConfig fields, usable as [evaluate.env].",
        "",
        "[env]",
    ]
    lines += [f"{key} = {_toml_value(value)}" for key, value in scenario.options.items()]
    return "\n".join(lines) + "\n"


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)
