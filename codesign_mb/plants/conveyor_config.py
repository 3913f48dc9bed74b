"""The conveyor env's configuration (:class:`ConveyorConfig`) and its observation layout.

Kept apart from the env (:mod:`codesign_mb.plants.conveyor`) so that the description (a frozen,
validated spec) lives apart from the state. Every option beyond the paper's plant (a belt
speed drawn from a range, the object's random start and spawn time, disturbances, perception
errors at the edge) is off by default: the defaults are the paper's plant, and the named
scenarios of :mod:`codesign_mb.plants.scenarios` switch them on.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from codesign_mb.core.config import STEPS_CAP, Cap, check_range
from codesign_mb.core.registry import kinds
from codesign_mb.robot.scene import BELT_HALF_WIDTH, OBJECTS

__all__ = ["BELT_PROFILES", "ConveyorConfig", "observation_layout"]

BELT_PROFILES = ("constant", "variable")


SUBSTEPS_CAP = Cap(10_000, "physics steps per control step")
PIXELS_CAP = Cap(8_192, "pixels of a rendered frame's side")


@dataclass(frozen=True)
class ConveyorConfig:
    """Configuration of :class:`~codesign_mb.plants.conveyor.ConveyorPickPlace` (validated).

    Parameters
    ----------
    belt_speed_mps:
        Nominal belt speed (m/s, >= 0); the paper uses 0.2 and 0.6.
    belt_profile:
        ``"constant"``, or ``"variable"``: every ``belt_change_steps`` (a seeded random
        interval) the speed jumps to ``belt_speed_mps * U(1 - belt_speed_jitter,
        1 + belt_speed_jitter)``, or to 0 (a stop) with probability ``belt_stop_probability``.
    belt_change_steps:
        Range ``(min, max)`` of the interval between speed changes (control steps).
    belt_speed_jitter:
        Relative amplitude of the speed changes (in [0, 1)).
    belt_speed_range_mps:
        Empty (the default): the episode's speed is ``belt_speed_mps``. ``(low, high)``: it is
        drawn per episode from ``U(low, high)`` (the speed changes of the variable profile are
        then relative to it and clipped into the range); ``belt_speed_mps`` stays the nominal
        speed, what the robot assumes (:mod:`codesign_mb.plants.belt_profiles`).
    belt_stop_probability:
        Probability that a change is a stop.
    object:
        The object to pick: a key of :data:`codesign_mb.robot.scene.OBJECTS`.
    horizon:
        Episode length ``T`` (control steps); truncation after ``horizon`` steps.
    n_substeps, timestep_s:
        Physics / inner-control substeps per control step and their length (s); the control
        period is their product (20 x 2 ms = 40 ms).
    max_gripper_speed_mps:
        TCP speed for an action of norm 1 per axis (m/s); must exceed the belt speed.
    spawn_y_m:
        Where the object is put on the belt, along it (m; upstream is negative y).
    spawn_lateral_range_m:
        Half-width of the uniform lateral (x) spawn interval around the belt centre (m).
    spawn_along_range_m:
        Half-width of the uniform interval of the start along the belt around ``spawn_y_m``.
    spawn_delay_steps:
        Range ``(min, max)`` of the step at which the object appears on the belt (seeded,
        uniform); before it, the object is off the scene and nothing is perceived.
    disturbance_probability:
        Probability per control step that the object, resting on the belt, slips or turns:
        its velocity gets a kick of ``N(0, disturbance_speed_std_mps^2)`` along x and y and
        ``N(0, disturbance_spin_std_radps^2)`` about z (:mod:`codesign_mb.plants.object_events`).
    disturbance_speed_std_mps, disturbance_spin_std_radps:
        Sizes of those kicks.
    perception_noise_std_m, velocity_noise_std_mps:
        Standard deviations of the Gaussian noise on the perceived position and velocity.
    perception_bias_m, perception_bias_std_m:
        Perceived position bias (m): the fixed ``perception_bias_m`` plus, per episode,
        ``N(0, perception_bias_std_m^2)`` per axis (a calibration error of the edge camera).
    perception_miss_probability:
        Probability per step of a missed detection: the edge has no fresh measurement and
        sends nothing (:mod:`codesign_mb.plants.perception`).
    perception_model:
        The edge's perception error model, a ``perception`` kind (:mod:`codesign_mb.plants.kinds`;
        ``"gaussian"``: the noise, bias and miss rate above).
    perceive_velocity:
        Whether the perceived object state includes its velocity.
    lift_height_m, success_distance_m, success_hold_steps:
        The success test (see the module docstring).
    terminate_on_success:
        End the episode (``terminated=True``) at success instead of running to the horizon.
    grasp_force_n, finger_speed_mps:
        Gripper force per finger (N) and finger speed (m/s).
    osc_model_period:
        Substeps between refreshes of the operational-space inertia matrices.
    render_width, render_height, render_camera:
        Frame size and camera of ``render()``.
    """

    belt_speed_mps: float = 0.2
    belt_profile: str = "constant"
    belt_change_steps: tuple[int, int] = (10, 30)
    belt_speed_jitter: float = 0.3
    belt_stop_probability: float = 0.2
    belt_speed_range_mps: tuple[float, ...] = ()
    object: str = "cube"
    horizon: int = 100
    n_substeps: int = 20
    timestep_s: float = 0.002
    max_gripper_speed_mps: float = 1.0
    spawn_y_m: float = -0.45
    spawn_lateral_range_m: float = 0.08
    spawn_along_range_m: float = 0.0
    spawn_delay_steps: tuple[int, int] = (0, 0)
    disturbance_probability: float = 0.0
    disturbance_speed_std_mps: float = 0.0
    disturbance_spin_std_radps: float = 0.0
    perception_noise_std_m: float = 0.0
    velocity_noise_std_mps: float = 0.0
    perception_bias_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    perception_bias_std_m: float = 0.0
    perception_miss_probability: float = 0.0
    perception_model: str = "gaussian"
    perceive_velocity: bool = True
    lift_height_m: float = 0.05
    success_distance_m: float = 0.03
    success_hold_steps: int = 3
    terminate_on_success: bool = False
    grasp_force_n: float = 20.0
    finger_speed_mps: float = 0.1
    osc_model_period: int = 10
    render_width: int = 480
    render_height: int = 360
    render_camera: str = "overview"

    def __post_init__(self) -> None:
        def number(name: str, *, low: float | None = None, strict: bool = False) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r}")
            if low is not None and (value <= low if strict else value < low):
                raise ValueError(f"{name} must be {'>' if strict else '>='} {low}, got {value!r}")

        def integer(name: str, low: int) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"{name} must be an integer, got {value!r}")
            if value < low:
                raise ValueError(f"{name} must be >= {low}, got {value!r}")

        number("belt_speed_mps", low=0.0)
        if self.belt_profile not in BELT_PROFILES:
            raise ValueError(
                f"belt_profile must be one of {', '.join(BELT_PROFILES)}, got {self.belt_profile!r}"
            )
        lo_hi = tuple(self.belt_change_steps)
        if (
            len(lo_hi) != 2
            or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in lo_hi)
            or not 1 <= lo_hi[0] <= lo_hi[1]
        ):
            raise ValueError(
                "belt_change_steps must be two integers 1 <= min <= max, "
                f"got {self.belt_change_steps!r}"
            )
        object.__setattr__(self, "belt_change_steps", (int(lo_hi[0]), int(lo_hi[1])))
        number("belt_speed_jitter", low=0.0)
        if self.belt_speed_jitter >= 1.0:
            raise ValueError(f"belt_speed_jitter must be < 1, got {self.belt_speed_jitter!r}")
        number("belt_stop_probability", low=0.0)
        if self.belt_stop_probability > 1.0:
            raise ValueError(
                f"belt_stop_probability must be <= 1, got {self.belt_stop_probability!r}"
            )
        if self.object not in OBJECTS:
            raise ValueError(f"object must be one of {', '.join(OBJECTS)}, got {self.object!r}")
        integer("horizon", 1)
        integer("n_substeps", 1)
        number("timestep_s", low=0.0, strict=True)
        number("max_gripper_speed_mps", low=0.0, strict=True)
        if self.max_gripper_speed_mps <= self.belt_speed_mps:
            raise ValueError(
                f"max_gripper_speed_mps must exceed belt_speed_mps ({self.belt_speed_mps}) or "
                f"the object cannot be caught, got {self.max_gripper_speed_mps!r}"
            )
        number("spawn_y_m")
        if not -0.8 <= self.spawn_y_m <= 0.8:
            raise ValueError(
                f"spawn_y_m must be in [-0.8, 0.8] (on the belt), got {self.spawn_y_m!r}"
            )
        number("spawn_lateral_range_m", low=0.0)
        if self.spawn_lateral_range_m > BELT_HALF_WIDTH - 0.03:
            raise ValueError(
                f"spawn_lateral_range_m must be <= {BELT_HALF_WIDTH - 0.03:.2f} (on the belt), "
                f"got {self.spawn_lateral_range_m!r}"
            )
        number("perception_noise_std_m", low=0.0)
        number("velocity_noise_std_mps", low=0.0)
        _validate_scenario_options(self, number)
        if not isinstance(self.perceive_velocity, bool):
            raise ValueError(f"perceive_velocity must be a bool, got {self.perceive_velocity!r}")
        number("lift_height_m", low=0.0, strict=True)
        number("success_distance_m", low=0.0, strict=True)
        integer("success_hold_steps", 1)
        if not isinstance(self.terminate_on_success, bool):
            raise ValueError(
                f"terminate_on_success must be a bool, got {self.terminate_on_success!r}"
            )
        number("grasp_force_n", low=0.0, strict=True)
        number("finger_speed_mps", low=0.0, strict=True)
        integer("osc_model_period", 1)
        integer("render_width", 16)
        integer("render_height", 16)
        check_range("horizon", self.horizon, cap=STEPS_CAP)
        check_range("n_substeps", self.n_substeps, cap=SUBSTEPS_CAP)
        check_range("render_width", self.render_width, cap=PIXELS_CAP)
        check_range("render_height", self.render_height, cap=PIXELS_CAP)

    @property
    def control_period_s(self) -> float:
        """Control period (s): ``n_substeps * timestep_s``."""
        return self.n_substeps * self.timestep_s

    def replace(self, **changes: Any) -> ConveyorConfig:
        """A copy with ``changes`` applied (and validated)."""
        return dataclasses.replace(self, **changes)


def observation_layout(config: ConveyorConfig | None = None) -> dict[str, slice]:
    """Named slices of the flat observation for ``config`` (see the module docstring)."""
    config = config or ConveyorConfig()
    layout = {
        "gripper_pos": slice(0, 3),
        "gripper_vel": slice(3, 6),
        "finger_width": slice(6, 7),
        "object_pos": slice(7, 10),
    }
    if config.perceive_velocity:
        layout["object_vel"] = slice(10, 13)
    return layout


def _validate_scenario_options(config: ConveyorConfig, number: Any) -> None:
    """Check the options beyond the paper's plant (ranges, disturbances, perception)."""
    speed_range = tuple(config.belt_speed_range_mps)
    if speed_range:
        if len(speed_range) != 2 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            for v in speed_range
        ):
            raise ValueError(
                f"belt_speed_range_mps must be empty or two numbers, got {speed_range!r}"
            )
        low, high = float(speed_range[0]), float(speed_range[1])
        if not 0.0 <= low <= high:
            raise ValueError(f"belt_speed_range_mps must be 0 <= low <= high, got {speed_range!r}")
        if high >= config.max_gripper_speed_mps:
            raise ValueError(
                f"belt_speed_range_mps must stay below max_gripper_speed_mps "
                f"({config.max_gripper_speed_mps}) or the object cannot be caught, "
                f"got {speed_range!r}"
            )
        speed_range = (low, high)
    object.__setattr__(config, "belt_speed_range_mps", speed_range)
    number("spawn_along_range_m", low=0.0)
    y = config.spawn_y_m
    if not -0.8 <= y - config.spawn_along_range_m <= y + config.spawn_along_range_m <= 0.8:
        raise ValueError(
            "spawn_along_range_m must keep the start on the belt (spawn_y_m +- it in "
            f"[-0.8, 0.8]), got {config.spawn_along_range_m!r}"
        )
    delay = tuple(config.spawn_delay_steps)
    if (
        len(delay) != 2
        or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in delay)
        or not 0 <= delay[0] <= delay[1] < config.horizon
    ):
        raise ValueError(
            "spawn_delay_steps must be two integers 0 <= min <= max < horizon, "
            f"got {config.spawn_delay_steps!r}"
        )
    object.__setattr__(config, "spawn_delay_steps", (int(delay[0]), int(delay[1])))
    for name in ("disturbance_probability", "perception_miss_probability"):
        number(name, low=0.0)
        if getattr(config, name) > 1.0:
            raise ValueError(f"{name} must be <= 1, got {getattr(config, name)!r}")
    number("disturbance_speed_std_mps", low=0.0)
    number("disturbance_spin_std_radps", low=0.0)
    number("perception_bias_std_m", low=0.0)
    bias = tuple(config.perception_bias_m)
    if len(bias) != 3 or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in bias
    ):
        raise ValueError(f"perception_bias_m must be 3 finite numbers, got {bias!r}")
    object.__setattr__(config, "perception_bias_m", tuple(float(v) for v in bias))
    if config.perception_model not in kinds("perception"):
        raise ValueError(
            f"perception_model must be one of {', '.join(kinds('perception'))}, "
            f"got {config.perception_model!r}"
        )
