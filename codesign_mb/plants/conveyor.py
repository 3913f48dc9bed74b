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
    object_pos    (3)  perceived object centre, m (perception error model)      [remote]
    object_vel    (3)  perceived object velocity, m/s (if ``perceive_velocity``)    [remote]

Perception at the edge (:mod:`codesign_mb.plants.perception`): the paper's plant perceives the
true state; a config may add noise, a bias and missed detections. On a missed detection (or
before the object spawned) ``info["perceived"]`` is False, the edge sends nothing that step
(the link wrapper asks the link for ``q = 0``) and ``object_pos`` keeps the last perceived
position. ``info["remote_true"]`` is the true remote state (what estimation errors are
measured against; before the object spawned: its start, at rest). The scenario options (belt
speed range, random start and spawn time, disturbances) are in
:mod:`codesign_mb.plants.conveyor_config`; the named presets in
:mod:`codesign_mb.plants.scenarios`; why a failed episode failed in
:mod:`codesign_mb.plants.outcomes` (``info``: ``missed_grasp``, ``dropped``, ``off_belt``,
``time_to_grasp_s``); the phase of the episode (belt, grasp, carried: where an estimation
error matters) in :mod:`codesign_mb.plants.phases` (``info["phase"]``).

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

import math
from collections.abc import Mapping
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from codesign_mb.core.config import from_mapping
from codesign_mb.plants.belt_profiles import belt_speed_schedule
from codesign_mb.plants.braking import keep_in_workspace
from codesign_mb.plants.conveyor_config import BELT_PROFILES, ConveyorConfig, observation_layout
from codesign_mb.plants.object_events import ObjectEvents
from codesign_mb.plants.outcomes import OutcomeTracker
from codesign_mb.plants.perception import (
    GaussianPerception,
    PerceptionErrorModel,
    make_perception,
    reset_perception,
)
from codesign_mb.plants.phases import episode_phase
from codesign_mb.robot.render import OffscreenRenderer
from codesign_mb.robot.scene import BELT_SURFACE_Z, BELT_X, OBJECTS
from codesign_mb.robot.simulator import ConveyorSimulator

_Terms = tuple[float, bool, bool, bool, float, NDArray[np.float64], NDArray[np.float64]]
"""What :meth:`ConveyorPickPlace._evaluate` measures after a step."""

__all__ = [
    "BELT_PROFILES",
    "ConveyorConfig",
    "ConveyorPickPlace",
    "belt_speed_schedule",
    "observation_layout",
]


class ConveyorPickPlace(gym.Env):
    """Pick an object off a moving conveyor with a Panda arm (see the module docstring).

    Parameters
    ----------
    config:
        :class:`ConveyorConfig` (default settings if None).
    render_mode:
        None or ``"rgb_array"`` (headless, EGL or OSMesa).
    perception:
        The edge's :class:`~codesign_mb.plants.perception.PerceptionErrorModel`; default: the
        one ``config.perception_model`` names (Gaussian noise, bias and misses of the config).

    Attributes
    ----------
    observation_layout:
        Named slices of the observation.
    remote_slice:
        The perceived object part, sent over the link (:class:`NetworkedPlant`).
    state_layout:
        Named slices of the state a controller acts on: the observation's, plus ``object_vel``
        after them when the velocity is not perceived (an estimator estimates it; the
        delay-compensating predictor appends its estimate there).
    horizon, control_period_s:
        ``T`` and the control period (s).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 25}

    def __init__(
        self,
        config: ConveyorConfig | None = None,
        render_mode: str | None = None,
        perception: PerceptionErrorModel | None = None,
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
        self.state_layout: dict[str, slice] = {
            "object_vel": slice(n_obs, n_obs + 3),
            **self.observation_layout,
        }
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
        self.perception = perception if perception is not None else make_perception(config)
        self._exact_perception = (  # the paper's: the true centre, from the first step on
            isinstance(self.perception, GaussianPerception)
            and self.perception.exact
            and config.spawn_delay_steps[1] == 0
        )
        self._perceived = True
        self._last_perceived = self._spawn.copy()
        self.events = ObjectEvents(config, self.sim, self.rest_height)
        self.outcomes = OutcomeTracker(
            object_half_width_m=self.object_shape.size[0],
            lift_height_m=config.lift_height_m,
            reach_y_m=float(self.workspace_high[1]),
            control_period_s=self.control_period_s,
        )

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
        self._speeds = belt_speed_schedule(cfg, rng)
        position = self.events.reset(rng, lateral)
        self._spawn = self.events.start
        reset_perception(self.perception, rng)
        self.outcomes.reset()
        self.sim.reset(object_position=position, belt_speed=float(self._speeds[0]))
        self._t = 0
        self._held_steps = 0
        self._success = False
        self._last_perceived = self.remote_prior()[:3]
        obs = self._observation()
        return obs, self._info(self._evaluate())

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
        events = self.events
        if self.config.disturbance_probability > 0:
            events.before_step(self._t, self.np_random, any(self.sim.finger_contacts()))
        self.sim.step(velocity, close=bool(action[3] > 0.0))
        self._t += 1
        speed = float(self._speeds[min(self._t, self.horizon)])
        self.sim.set_belt_speed(speed)
        if self._t <= events.spawn_step:
            events.after_step(self._t, speed)

        terms = self._evaluate()
        distance, grasped, _, held, lift = terms[:5]
        self._held_steps = self._held_steps + 1 if held else 0
        if self._held_steps >= self.config.success_hold_steps:
            self._success = True
        reward = (1.0 - math.tanh(10.0 * distance)) + 0.25 * grasped + grasped * lift + float(held)
        terminated = bool(self.config.terminate_on_success and self._success)
        truncated = self._t >= self.horizon and not terminated
        return self._observation(), float(reward), terminated, truncated, self._info(terms)

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
        if self._exact_perception:  # the paper's perception: the true centre
            obs[7:10] = sim.object_position()
        else:
            self._perceive()
            obs[7:10] = self._last_perceived
        if cfg.perceive_velocity:
            obs[10:13] = sim.object_velocity()
            if cfg.velocity_noise_std_mps > 0:
                obs[10:13] += rng.normal(0.0, cfg.velocity_noise_std_mps, 3)
        space = self.observation_space  # np.clip into the bounds, without its dispatch
        return np.minimum(np.maximum(obs, space.low, out=obs), space.high, out=obs)

    def _perceive(self) -> None:
        """Ask the perception model for this step's measurement (none before the spawn)."""
        measured = None
        if self.events.spawned(self._t):
            measured = self.perception.sample(self.sim.object_position(), self.np_random)
        self._perceived = measured is not None
        if measured is not None:
            self._last_perceived = np.asarray(measured, dtype=float).reshape(3)

    def _evaluate(self) -> _Terms:
        """``(distance, grasped, lifted, held, lift, object position, gripper position)``."""
        gripper = self.sim.tcp_position()
        obj = self.sim.object_position()
        distance = math.dist(obj.tolist(), gripper.tolist())  # lists: 1 us, not 5
        left, right = self.sim.finger_contacts()
        grasped = left and right
        rise = float(obj[2] - self.rest_height)
        lifted = rise >= self.config.lift_height_m
        held = lifted and distance <= self.config.success_distance_m
        lift = min(max(rise / self.config.lift_height_m, 0.0), 1.0)
        if self.events.spawned(self._t):
            self.outcomes.update(
                self._t, object_pos=obj, rise=rise, touched=left or right, grasped=grasped,
                closed=self.sim.gripper_closed, finger_width=self.sim.finger_width(),
            )  # fmt: skip
        return distance, grasped, lifted, held, lift, obj, gripper

    def _info(self, terms: _Terms) -> dict[str, Any]:
        distance, grasped, lifted, held, _, obj, gripper = terms
        velocity = self.sim.object_velocity()
        return {
            "success": self._success,
            "held": held,
            "lifted": lifted,
            "grasped": grasped,
            "gripper_object_distance": distance,
            "object_pos": obj,
            "object_vel": velocity,
            "gripper_pos": gripper,
            "belt_speed": self.sim.belt_speed,
            "perceived": self._perceived,
            "remote_true": self._remote_true(obj, velocity),
            "phase": episode_phase(
                obj, gripper, grasped=grasped, lifted=lifted, spawned=self.events.spawned(self._t)
            ),
            **self.outcomes.info(),
        }

    def _remote_true(
        self, position: NDArray[np.float64], velocity: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        """The true remote state (object position, and velocity if perceived); before the
        object spawned, where it will appear, at rest. A new array (``info`` keeps its own)."""
        if not self.events.spawned(self._t):
            position, velocity = self.events.start, np.zeros(3)
        if not self.config.perceive_velocity:
            return position.copy()
        return np.concatenate([position, velocity])
