"""The conveyor pick-and-place plant (paper.tex sec. 6) as a Gymnasium environment.

A Panda arm (MuJoCo physics, Pinocchio operational-space inner loop, see
:mod:`codesign_mb.robot`) must lift an object off a moving conveyor belt within ``T = 100``
control steps of 40 ms. The object's state is perceived at the edge and reaches the robot
over the wireless link; the robot's proprioception is local and always fresh. Wrap the env
in :class:`~codesign_mb.network.LinkObservationWrapper` to put the perceived part behind a
link: :attr:`ConveyorPickPlace.remote_slice` selects it.

Observation (flat ``Box``, float64, clipped to generous finite bounds;
:attr:`ConveyorPickPlace.observation_layout` names the slices)::

    gripper_pos   (3)  TCP position, m (robot base frame: x across the belt, y along it, z up)
    gripper_vel   (3)  TCP linear velocity, m/s
    finger_width  (1)  distance between the finger pads, m (0.08 open)
    object_pos    (3)  perceived object centre, m, + N(0, perception_noise_std_m^2)  [remote]
    object_vel    (3)  perceived object velocity, m/s (if ``perceive_velocity``)    [remote]

Action (``Box(4)`` in [-1, 1], float32): the TCP velocity command divided by
``max_gripper_speed_mps`` (3), and the grip (> 0 close, <= 0 open). Out-of-range actions are
clipped; a non-finite action raises ``ValueError``. The gripper is kept inside a workspace
(``workspace_low/high``: x in [0.32, 0.72], y in [-0.55, 0.55], z from 1.2 cm to 34 cm above
the belt, and within 0.72 m of the base axis; all reachable with the gripper down): near a
face the speed towards it is capped by a braking law (``ConveyorPickPlace._keep_in_workspace``)
so the gripper stops at the boundary; in the interior ``x_{t+1} ~ x_t + v_t dt``.

Success (the paper's ``J``, ``eq_robot``): at step ``t`` the object is *held* when its
centre is at least ``lift_height_m`` above its resting height on the belt and within
``success_distance_m`` of the TCP; the episode succeeds once it has been held for
``success_hold_steps`` consecutive steps. ``info["success"]`` is latched (true from then
on) and is what evaluations count; by default the episode still runs to the horizon
(``terminate_on_success=False``) so that every episode has ``T`` steps, as in the paper
(whose QoS policy keeps acting after the lift), and a learner sees the holding phase.

Reward (dense, for learning; evaluations use ``success``): with ``d`` the TCP-object
distance, ``g`` = both fingers touch the object, ``l`` = clip(lift / lift_height_m, 0, 1)::

    r = (1 - tanh(10 d)) + 0.25 g + g l + 1[held]        in [0, 3.25]

Examples
--------
>>> import gymnasium as gym, codesign_mb.plants
>>> env = gym.make("codesign_mb/ConveyorPickPlace-v0", config=ConveyorConfig(belt_speed_mps=0.6))
>>> obs, info = env.reset(seed=0)
>>> obs.shape
(13,)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.core.config import from_mapping
from codesign_mb.plants.braking import keep_in_workspace
from codesign_mb.robot.render import OffscreenRenderer
from codesign_mb.robot.scene import BELT_HALF_WIDTH, BELT_SURFACE_Z, BELT_X, OBJECTS
from codesign_mb.robot.simulator import ConveyorSimulator

__all__ = [
    "BELT_PROFILES",
    "ConveyorConfig",
    "ConveyorPickPlace",
    "belt_speed_schedule",
    "observation_layout",
]

BELT_PROFILES = ("constant", "variable")


@dataclass(frozen=True)
class ConveyorConfig:
    """Configuration of :class:`ConveyorPickPlace` (validated on construction).

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
    perception_noise_std_m, velocity_noise_std_mps:
        Standard deviations of the Gaussian noise on the perceived position and velocity.
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
    object: str = "cube"
    horizon: int = 100
    n_substeps: int = 20
    timestep_s: float = 0.002
    max_gripper_speed_mps: float = 1.0
    spawn_y_m: float = -0.45
    spawn_lateral_range_m: float = 0.08
    perception_noise_std_m: float = 0.0
    velocity_noise_std_mps: float = 0.0
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


def belt_speed_schedule(config: ConveyorConfig, rng: np.random.Generator) -> NDArray[np.float64]:
    """Belt speed at each control step ``0..horizon`` (m/s) for one episode.

    Constant profile: ``belt_speed_mps`` throughout (``rng`` is not used). Variable profile:
    piecewise constant, starting at the nominal speed, changing after seeded random
    intervals drawn from ``belt_change_steps`` (see :class:`ConveyorConfig`).
    """
    n = config.horizon + 1
    speeds = np.full(n, config.belt_speed_mps)
    if config.belt_profile == "constant":
        return speeds
    lo, hi = config.belt_change_steps
    t = int(rng.integers(lo, hi + 1))
    while t < n:
        if rng.random() < config.belt_stop_probability:
            speed = 0.0
        else:
            j = config.belt_speed_jitter
            speed = config.belt_speed_mps * float(rng.uniform(1.0 - j, 1.0 + j))
        speeds[t:] = speed
        t += int(rng.integers(lo, hi + 1))
    return speeds


class ConveyorPickPlace(gym.Env):
    """Pick an object off a moving conveyor with a Panda arm (see the module docstring).

    Parameters
    ----------
    config:
        :class:`ConveyorConfig` (default settings if None).
    render_mode:
        None or ``"rgb_array"`` (headless, EGL or OSMesa).

    Attributes
    ----------
    observation_layout:
        Named slices of the observation.
    remote_slice:
        The perceived object part, sent over the link (:class:`NetworkedPlant`).
    horizon, control_period_s:
        ``T`` and the control period (s).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self, config: ConveyorConfig | None = None, render_mode: str | None = None
    ) -> None:
        if config is None:
            config = ConveyorConfig()
        if not isinstance(config, ConveyorConfig):
            raise TypeError(f"config must be a ConveyorConfig, got {type(config).__name__}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.config = config
        self.render_mode = render_mode
        self.horizon: int = config.horizon
        self.control_period_s: float = config.control_period_s
        self.sim = ConveyorSimulator(
            config.object,
            n_substeps=config.n_substeps,
            timestep_s=config.timestep_s,
            model_period=config.osc_model_period,
            grasp_force_n=config.grasp_force_n,
            finger_speed_mps=config.finger_speed_mps,
        )
        self.object_shape = OBJECTS[config.object]
        self.rest_height = BELT_SURFACE_Z + self.object_shape.half_height
        self.observation_layout: dict[str, slice] = observation_layout(config)
        n_obs = max(s.stop for s in self.observation_layout.values())
        self.remote_slice: slice = slice(7, n_obs)
        # Generous finite bounds (the scene's extent, velocities far above the arm's);
        # observations are clipped into them.
        bounds = {
            "gripper_pos": ([-2.0, -2.0, -1.0], [2.0, 2.0, 2.0]),
            "gripper_vel": ([-5.0] * 3, [5.0] * 3),
            "finger_width": ([0.0], [0.081]),
            "object_pos": ([-5.0, -5.0, -2.0], [5.0, 5.0, 3.0]),
            "object_vel": ([-10.0] * 3, [10.0] * 3),
        }
        low, high = np.empty(n_obs), np.empty(n_obs)
        for name, where in self.observation_layout.items():
            low[where], high[where] = bounds[name]
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float64)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        # Where the gripper may go: a box cut by a cylinder around the base, all of it
        # reachable with the gripper pointing down, away from singularities and joint limits.
        self.workspace_low = np.array([0.35, -0.55, BELT_SURFACE_Z + 0.02])
        self.workspace_high = np.array([0.70, 0.55, BELT_SURFACE_Z + 0.34])
        self.workspace_radius = 0.72
        self.sim.osc.set_workspace(self.workspace_low, self.workspace_high, self.workspace_radius)
        self._brake_accel = 0.5 * self.sim.osc.gains.max_accel_mps2
        # Farther than this from every face, the braking cap exceeds any commanded speed
        # (the norm of a velocity whose components are at the limit).
        T, a = self.control_period_s, self._brake_accel
        v = math.sqrt(3.0) * config.max_gripper_speed_mps
        self._brake_distance = 0.5 * a * ((v / a + T) ** 2 - T * T)
        self._renderer = None
        self._t = 0
        self._speeds = np.full(config.horizon + 1, config.belt_speed_mps)
        self._held_steps = 0
        self._success = False
        self._spawn = np.array([BELT_X, config.spawn_y_m, self.rest_height])

    @classmethod
    def from_options(cls, options: Mapping[str, Any] | None = None) -> ConveyorPickPlace:
        """The env from the fields of its :class:`ConveyorConfig` (unknown ones are an error)."""
        config = from_mapping(ConveyorConfig, dict(options or {}), where="plant.options")
        return cls(config=config)

    @property
    def belt_speeds(self) -> NDArray[np.float64]:
        """This episode's belt speed at each control step ``0..horizon`` (m/s)."""
        return self._speeds.copy()

    @property
    def belt_velocity(self) -> NDArray[np.float64]:
        """The *nominal* belt velocity (m/s, along +y): what the robot may assume.

        Under the variable profile the actual speed changes (``belt_speeds``, ``info``); that
        is ground truth, not something the robot knows.
        """
        return np.array([0.0, self.config.belt_speed_mps, 0.0])

    # -------------------------------------------------------------------- NetworkedPlant
    def remote_prior(self) -> NDArray[np.float64]:
        """The robot's knowledge of the object before any packet: nominal spawn, belt speed."""
        prior = np.array([BELT_X, self.config.spawn_y_m, self.rest_height])
        if self.config.perceive_velocity:
            prior = np.concatenate([prior, [0.0, self.config.belt_speed_mps, 0.0]])
        return prior

    # -------------------------------------------------------------------- gym API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[NDArray[np.float64], dict[str, Any]]:
        super().reset(seed=seed)
        cfg = self.config
        rng = self.np_random
        lateral = float(rng.uniform(-cfg.spawn_lateral_range_m, cfg.spawn_lateral_range_m))
        self._spawn = np.array([BELT_X + lateral, cfg.spawn_y_m, self.rest_height])
        self._speeds = belt_speed_schedule(cfg, rng)
        self.sim.reset(object_position=self._spawn, belt_speed=float(self._speeds[0]))
        self._t = 0
        self._held_steps = 0
        self._success = False
        obs = self._observation()
        return obs, self._info(*self._evaluate())

    def step(
        self, action: NDArray[np.floating]
    ) -> tuple[NDArray[np.float64], float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (4,):
            raise ValueError(f"action must have shape (4,), got {action.shape}")
        if not all(map(math.isfinite, action.tolist())):
            raise ValueError(f"action must be finite, got {action.tolist()}")
        action = np.minimum(np.maximum(action, -1.0), 1.0)  # np.clip, without its dispatch
        velocity = action[:3] * self.config.max_gripper_speed_mps
        self._keep_in_workspace(velocity)
        self.sim.step(velocity, close=bool(action[3] > 0.0))
        self._t += 1
        self.sim.set_belt_speed(float(self._speeds[min(self._t, self.horizon)]))

        terms = self._evaluate()
        distance, grasped, _, held, lift = terms
        self._held_steps = self._held_steps + 1 if held else 0
        if self._held_steps >= self.config.success_hold_steps:
            self._success = True
        reward = (1.0 - math.tanh(10.0 * distance)) + 0.25 * grasped + grasped * lift + float(held)
        terminated = bool(self.config.terminate_on_success and self._success)
        truncated = self._t >= self.horizon and not terminated
        return self._observation(), float(reward), terminated, truncated, self._info(*terms)

    def render(self) -> NDArray[np.uint8] | None:
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            cfg = self.config
            self._renderer = OffscreenRenderer(
                self.sim.model, cfg.render_width, cfg.render_height, cfg.render_camera
            )
        return self._renderer.render(self.sim.data)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()

    # -------------------------------------------------------------------- internals
    def _keep_in_workspace(self, velocity: NDArray[np.float64]) -> None:
        # Brake before the workspace boundary: towards a face at distance d (from the
        # inner loop's position reference), the speed is capped by the discrete braking law
        # v <= a (sqrt(T^2 + 2 d / a) - T), so the reference stops at the face without
        # exceeding the deceleration a (below the inner loop's bound). In the interior this
        # does nothing.
        x = self.sim.osc.position_reference
        keep_in_workspace(
            velocity, x, math.hypot(x[0], x[1]), self.workspace_low, self.workspace_high,
            self.workspace_radius, self._brake_distance, self.control_period_s,
            self._brake_accel, self.config.max_gripper_speed_mps,
        )  # fmt: skip

    def _observation(self) -> NDArray[np.float64]:
        cfg, sim, rng = self.config, self.sim, self.np_random
        obs = np.empty(self.observation_space.shape[0])
        obs[0:3] = sim.tcp_position()
        obs[3:6] = sim.tcp_velocity()
        obs[6] = sim.finger_width()
        obs[7:10] = sim.object_position()
        if cfg.perception_noise_std_m > 0:
            obs[7:10] += rng.normal(0.0, cfg.perception_noise_std_m, 3)
        if cfg.perceive_velocity:
            obs[10:13] = sim.object_velocity()
            if cfg.velocity_noise_std_mps > 0:
                obs[10:13] += rng.normal(0.0, cfg.velocity_noise_std_mps, 3)
        space = self.observation_space  # np.clip into the bounds, without its dispatch
        return np.minimum(np.maximum(obs, space.low, out=obs), space.high, out=obs)

    def _evaluate(self) -> tuple[float, bool, bool, bool, float]:
        gripper = self.sim.tcp_position()
        obj = self.sim.object_position()
        distance = math.dist(obj.tolist(), gripper.tolist())  # lists: 1 us, not 5
        left, right = self.sim.finger_contacts()
        grasped = left and right
        rise = float(obj[2] - self.rest_height)
        lifted = rise >= self.config.lift_height_m
        held = lifted and distance <= self.config.success_distance_m
        lift = min(max(rise / self.config.lift_height_m, 0.0), 1.0)
        return distance, grasped, lifted, held, lift

    def _info(
        self, distance: float, grasped: bool, lifted: bool, held: bool, lift: float
    ) -> dict[str, Any]:
        return {
            "success": self._success,
            "held": held,
            "lifted": lifted,
            "grasped": grasped,
            "gripper_object_distance": distance,
            "object_pos": self.sim.object_position(),
            "object_vel": self.sim.object_velocity(),
            "gripper_pos": self.sim.tcp_position(),
            "belt_speed": self.sim.belt_speed,
        }
