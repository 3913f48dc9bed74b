"""Model predictive control of the conveyor pick: the phases and the controller.

The ideal controller ``pi_c`` of paper.tex sec. 4.A (``eq_control_ideal``), done model-based.
The model and the QP are in :mod:`codesign_mb.control.mpc_qp_problem`, the QP's solvers in
:mod:`codesign_mb.control.mpc_qp` (:class:`MpcQp`), the settings in
:mod:`codesign_mb.control.mpc_config` (:class:`MpcConfig`); both classes are re-exported here.

Phases (explicit, :class:`Phase`)
---------------------------------
APPROACH (reference: hover above the object's predicted path) -> DESCEND (reference: the grasp
point, once aligned laterally; back to APPROACH only if the lateral error grows beyond
:attr:`MpcConfig.abort_tolerance_m`, the funnel keeping the gripper high enough in between) ->
GRASP (close the fingers while tracking, for a few steps; with
:attr:`MpcConfig.grasp_std_gate_m` only once the estimate is certain enough, the gripper
tracking the object at the grasp point until then; with
:attr:`MpcConfig.grasp_abort_tolerance_m` the fingers reopen, back to DESCEND, when the
object moves away from under them) -> LIFT (reference: straight up; funnel off). A grasp that
closes on nothing (fingers shut) opens and goes back to APPROACH.
The defaults were tuned on the conveyor with perception noise and a variable belt speed.
"""

from __future__ import annotations

import dataclasses
import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.control.mpc_config import SOLVERS, MpcConfig, config_fields
from codesign_mb.control.mpc_kernels import fill_parameters
from codesign_mb.control.mpc_model import JointLimits, joint_linearisation
from codesign_mb.control.mpc_qp import MpcQp, MpcSolution
from codesign_mb.control.mpc_qp import _quiet_stdout as _quiet_stdout  # tests silence qpOASES
from codesign_mb.control.mpc_qp_problem import OFF, lag_discretisation
from codesign_mb.core.config import from_mapping

__all__ = [
    "OFF",
    "SOLVERS",
    "MpcConfig",
    "MpcController",
    "MpcQp",
    "MpcSolution",
    "Phase",
    "config_fields",
    "lag_discretisation",
]


class Phase(enum.IntEnum):
    """The pick's phases, in order."""

    APPROACH = 0
    DESCEND = 1
    GRASP = 2
    LIFT = 3


@dataclass
class _EpisodeLog:
    solve_times_s: list[float] = field(default_factory=list)
    cpu_times_s: list[float] = field(default_factory=list)
    failures: int = 0
    phases: list[int] = field(default_factory=list)


class MpcController:
    """MPC ideal controller for the conveyor pick (a :class:`~codesign_mb.control.base.Controller`).

    Reads the gripper's position, velocity and finger width and the object's position and
    (if present) velocity from the plant-layout observation, runs the phase logic, solves the
    QP of :class:`MpcQp` and returns the action ``(u / max_speed, grip)`` in ``[-1, 1]^4``.

    On a solver failure (infeasible or not converged) it returns a safe command instead: no
    motion inside the workspace (a bounded push back towards it from outside), the grip kept.
    Failures are counted (:attr:`failures`, :meth:`episode_metrics`).

    Parameters
    ----------
    layout:
        Name -> slice of the observation (the plant's ``state_layout``, else its
        ``observation_layout``). An ``object_vel`` slot beyond the end of a given observation
        (an estimator that does not estimate the velocity) counts as absent.
    control_period_s:
        The plant's control period (40 ms).
    max_speed_mps:
        Cartesian speed of a unit action.
    config:
        :class:`MpcConfig`.
    belt_velocity:
        Object velocity assumed when the observation carries none (world frame, m/s): the
        plant's nominal belt velocity.
    joint_state:
        The arm's proprioception: returns its joint positions (the Panda's 7 arm joints
        first, as :meth:`~codesign_mb.robot.simulator.ConveyorSimulator.joint_positions`).
        A robot-side quantity, local and fresh, not sent over the link and not part of the
        observation (whose fixed layout learned checkpoints read); with it (and
        :attr:`MpcConfig.joint_limits`) the QP limits the joints, linearised through the
        Pinocchio Jacobian at each step (:mod:`~codesign_mb.control.mpc_model`).
        :meth:`from_env` binds the plant's; it is not pickled (a copy in another process
        has no joint limits until built there by :meth:`from_env`).
    """

    def __init__(
        self,
        layout: Mapping[str, slice],
        *,
        control_period_s: float,
        max_speed_mps: float,
        config: MpcConfig | None = None,
        belt_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0),
        joint_state: Callable[[], NDArray[np.float64]] | None = None,
    ) -> None:
        required = ("gripper_pos", "gripper_vel", "finger_width", "object_pos")
        missing = [k for k in required if k not in layout]
        if missing:
            raise ValueError(f"observation layout lacks {', '.join(missing)}")
        self.layout = dict(layout)
        self.config = config or MpcConfig()
        self.control_period_s = float(control_period_s)
        self.max_speed_mps = float(max_speed_mps)
        self.belt_velocity = np.asarray(belt_velocity, dtype=float).reshape(3)
        self._joint_state = joint_state if self.config.joint_limits else None
        limits, self._robot = None, None
        if self._joint_state is not None:
            from codesign_mb.robot.model import PandaModel  # its own Pinocchio data

            self._robot = PandaModel()
            limits = JointLimits.panda(
                margin_rad=self.config.joint_margin_rad,
                velocity_fraction=self.config.joint_velocity_fraction,
            )
        self.qp = MpcQp(
            self.config,
            dt=self.control_period_s,
            max_speed_mps=self.max_speed_mps,
            joint_limits=limits,
        )
        self._prepare()
        self.total_failures = 0
        self.recorder: list[tuple[NDArray[np.float64], Any]] | None = None
        """When a list, every QP solved, ``(theta, joints)``, is appended (benchmarks replay)."""
        self.reset()

    @classmethod
    def from_env(
        cls, env: Any, config: MpcConfig | Mapping[str, Any] | None = None
    ) -> MpcController:
        """Build for a conveyor env (wrapped or not); ``config`` may be a mapping of
        :class:`MpcConfig` fields (a table row's options).

        Layout, control period, maximum speed, belt velocity and (unless ``config`` sets it)
        the workspace box come from the plant.
        """
        plant = env.unwrapped
        plant_cfg = getattr(plant, "config", None)
        if isinstance(config, Mapping):
            config = from_mapping(MpcConfig, config, where="mpc config")
        config = config or MpcConfig()
        max_speed = _first_attr((plant_cfg, plant), ("max_gripper_speed_mps", "max_speed_mps"))
        period = _first_attr((plant, plant_cfg), ("control_period_s",))
        belt = getattr(plant, "belt_velocity", None)
        if belt is None and plant_cfg is not None and hasattr(plant_cfg, "belt_speed_mps"):
            belt = (0.0, float(plant_cfg.belt_speed_mps), 0.0)  # the belt runs along +y
        if config.workspace_low is None:
            margin = config.workspace_margin_m
            lo = np.asarray(_first_attr((plant,), ("workspace_low",)), dtype=float) + margin
            hi = np.asarray(_first_attr((plant,), ("workspace_high",)), dtype=float) - margin
            config = dataclasses.replace(
                config, workspace_low=tuple(lo.tolist()), workspace_high=tuple(hi.tolist())
            )
        sim = getattr(plant, "sim", None)  # the robot's own joint sensors (not observed)
        return cls(
            getattr(plant, "state_layout", None) or plant.observation_layout,
            control_period_s=float(period),
            max_speed_mps=float(max_speed),
            config=config,
            belt_velocity=tuple(np.asarray(belt if belt is not None else (0, 0, 0), dtype=float)),
            joint_state=getattr(sim, "joint_positions", None),
        )

    # -- Controller protocol -------------------------------------------------------------
    def reset(self, *, seed: int | None = None) -> None:
        self.qp.reset()
        self._linearisation: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        self.phase = Phase.APPROACH
        self._closing = 0
        self._lift_origin: NDArray[np.float64] | None = None
        self._u_prev = np.zeros(3)
        self._grip = -1.0
        self.failures = 0
        self.last_solution: MpcSolution | None = None
        self._log = _EpisodeLog()

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        obs = np.asarray(observation, dtype=float)
        grip_pos = obs[self.layout["gripper_pos"]]
        grip_vel = obs[self.layout["gripper_vel"]]
        if self._width_index is None:
            width = float(np.mean(obs[self.layout["finger_width"]]))
        else:  # one entry: its mean is itself
            width = float(obs[self._width_index])
        obj = obs[self.layout["object_pos"]]
        velocity = self._velocity_slot
        if velocity is not None and obs.shape[0] >= velocity.stop:
            obj_vel = obs[velocity]
        else:
            obj_vel = self.belt_velocity
        std_slot = self._std_index
        self._std = float(obs[std_slot]) if obs.shape[0] > std_slot else 0.0
        theta = self._parameters(grip_pos, grip_vel, width, obj, obj_vel)
        joints = self._joints()
        if self.recorder is not None:
            self.recorder.append((theta.copy(), joints))
        solution = self.qp.solve(theta, joints)
        self.last_solution = solution
        self._log.solve_times_s.append(solution.solve_time_s)
        self._log.cpu_times_s.append(solution.cpu_time_s)
        self._log.phases.append(int(self.phase))
        if solution.success:
            u = solution.commands[0]
        else:
            self.failures += 1
            self.total_failures += 1
            self._log.failures += 1
            u = self._safe_command(grip_pos)
        self._u_prev = u
        action = np.empty(4)
        np.minimum(np.maximum(u / self.max_speed_mps, -1.0), 1.0, out=action[:3])  # np.clip
        action[3] = self._grip
        return action

    def _joints(self) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        """The measured arm joints and ``J_v^+``, relinearised once they moved far enough."""
        if self._joint_state is None or self.qp.joint_limits is None:
            return None
        q = np.asarray(self._joint_state(), dtype=float)
        n_arm = self.qp.joint_limits.n
        lin = self._linearisation
        if lin is None or np.max(np.abs(q[:n_arm] - lin[0])) > self.config.joint_relinearise_rad:
            lin = self._linearisation = (
                q[:n_arm].copy(),
                joint_linearisation(self._robot, q, n_arm),
            )
        return q[:n_arm].copy(), lin[1]

    # -- phase logic ----------------------------------------------------------------------
    def _prepare(self) -> None:
        """Constants and the parameter vector's views, so a step allocates little."""
        cfg, n, dt = self.config, self.qp.n, self.control_period_s
        self._kdt = np.arange(1, n + 1)[:, None] * dt  # k dt, k = 1..N
        self._offset = np.asarray(cfg.grasp_offset_m)
        self._hover = np.array([0.0, 0.0, cfg.hover_height_m])
        self._lift = np.array([0.0, 0.0, cfg.lift_height_m])
        self._ws_low = np.asarray(cfg.workspace_low)
        self._ws_high = np.asarray(cfg.workspace_high)
        width = self.layout["finger_width"]
        indices = range(width.stop)[width] if width.stop is not None else range(0)
        self._width_index: int | None = indices[0] if len(indices) == 1 else None
        self._theta = np.empty(self.qp.n_theta)  # the layout of MpcQp.pack
        # An estimator may append its position uncertainty right after the state layout.
        self._std_index = max(s.stop or 0 for s in self.layout.values())
        self._std = 0.0
        velocity = self.layout.get("object_vel")
        self._velocity_slot: slice | None = (
            slice(*velocity.indices(velocity.stop)) if velocity is not None else None
        )

    def _parameters(
        self,
        p: NDArray[np.float64],
        v: NDArray[np.float64],
        width: float,
        obj: NDArray[np.float64],
        obj_vel: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """Advance the phase and return ``theta`` (:meth:`MpcQp.pack`), written in place."""
        cfg = self.config
        p0, p1, p2 = p.tolist()
        o0, o1, o2 = obj.tolist()
        g0, g1, g2 = self._offset.tolist()
        e0, e1, e2 = p0 - (o0 + g0), p1 - (o1 + g1), p2 - (o2 + g2)  # p - (obj + offset)
        lateral = float(np.hypot(e0, e1))
        if self.phase == Phase.APPROACH and lateral <= cfg.align_tolerance_m:
            self.phase = Phase.DESCEND
        elif self.phase == Phase.DESCEND:
            if self._off_object(e0, e1, lateral):
                self.phase = Phase.APPROACH
            elif (
                lateral <= cfg.grasp_tolerance_m
                and abs(e2) <= cfg.grasp_height_tolerance_m
                and (cfg.grasp_std_gate_m is None or self._std <= cfg.grasp_std_gate_m)
            ):
                self.phase = Phase.GRASP
                self._closing = 0
        elif self.phase == Phase.GRASP:
            abort = cfg.grasp_abort_tolerance_m
            self._closing += 1
            if abort is not None and lateral > abort:
                self.phase = Phase.DESCEND  # the object left the closing fingers: reopen
            elif self._closing > cfg.close_steps:
                if width < cfg.min_grip_width_m:
                    self.phase = Phase.APPROACH  # closed on nothing: open and retry
                else:
                    self.phase = Phase.LIFT
                    self._lift_origin = p.copy()
        elif self.phase == Phase.LIFT and width < cfg.min_grip_width_m:
            self.phase = Phase.APPROACH
            self._lift_origin = None
        self._grip = 1.0 if self.phase in (Phase.GRASP, Phase.LIFT) else -1.0
        origin = self._lift_origin if self._lift_origin is not None else p
        fill_parameters(
            self._theta, p, v, self._u_prev, obj, self._offset, obj_vel, self._kdt,
            int(self.phase), self._hover, cfg.clearance_m, cfg.funnel_apex_depth_m, self._lift,
            origin, self._ws_low, self._ws_high, OFF,
        )  # fmt: skip
        return self._theta

    def _off_object(self, e0: float, e1: float, lateral: float) -> bool:
        """DESCEND gives up (back to APPROACH): the lateral error beyond
        :attr:`MpcConfig.abort_tolerance_m`, or, with :attr:`MpcConfig.abort_tolerance_y_m`,
        across the belt (x) beyond the one and along it (y) beyond the other."""
        cfg = self.config
        if cfg.abort_tolerance_y_m is None:
            return lateral > cfg.abort_tolerance_m
        return abs(e0) > cfg.abort_tolerance_m or abs(e1) > cfg.abort_tolerance_y_m

    def _safe_command(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        lo = np.asarray(self.config.workspace_low)
        hi = np.asarray(self.config.workspace_high)
        back = (np.clip(p, lo, hi) - p) / self.control_period_s
        return np.clip(back, -0.25 * self.qp.v_max, 0.25 * self.qp.v_max)

    # -- metrics --------------------------------------------------------------------------
    def episode_metrics(self) -> dict[str, float]:
        """Per-episode solver statistics: solves, failures, solver-call times in ms.

        ``mpc_solve_ms_*`` are wall-clock times (what the control loop waits, including any
        preemption by other processes); ``mpc_solve_cpu_ms_*`` the thread's CPU time.
        """
        times = np.asarray(self._log.solve_times_s) * 1e3
        cpu = np.asarray(self._log.cpu_times_s) * 1e3
        if times.size == 0:
            times = cpu = np.array([np.nan])
        return {
            "mpc_solves": float(len(self._log.solve_times_s)),
            "mpc_failures": float(self._log.failures),
            "mpc_solve_ms_median": float(np.median(times)),
            "mpc_solve_ms_p99": float(np.percentile(times, 99)),
            "mpc_solve_ms_max": float(np.max(times)),
            "mpc_solve_cpu_ms_median": float(np.median(cpu)),
            "mpc_solve_cpu_ms_p99": float(np.percentile(cpu, 99)),
        }

    @property
    def solve_times_s(self) -> list[float]:
        """Wall times of this episode's solves."""
        return list(self._log.solve_times_s)

    def __getstate__(self) -> dict[str, Any]:
        return {
            "layout": self.layout,
            "control_period_s": self.control_period_s,
            "max_speed_mps": self.max_speed_mps,
            "config": self.config,
            "belt_velocity": tuple(self.belt_velocity),
        }

    def __setstate__(self, state: dict[str, Any]) -> None:
        layout = state.pop("layout")
        self.__init__(layout, **state)  # type: ignore[misc]


def _first_attr(objects: tuple[Any, ...], names: tuple[str, ...]) -> Any:
    for obj in objects:
        if obj is None:
            continue
        for name in names:
            if hasattr(obj, name):
                return getattr(obj, name)
    raise ValueError(f"the plant exposes none of {', '.join(names)}")
