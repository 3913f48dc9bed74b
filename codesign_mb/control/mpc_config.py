"""Settings of the conveyor MPC (:class:`MpcConfig`), validated in one place."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

__all__ = ["SOLVERS", "MpcConfig", "config_fields"]

SOLVERS = ("qpoases", "osqp", "daqp", "daqp_native")
"""QP solvers of :attr:`MpcConfig.solver` (see :mod:`codesign_mb.control.mpc_qp`)."""


@dataclass(frozen=True)
class MpcConfig:
    """Settings of :class:`MpcController` (lengths in m, times in s).

    Parameters
    ----------
    horizon:
        Prediction horizon ``N`` in control steps (10-25 is sensible at 40 ms).
    lag_time_constant_s:
        Time constant ``T`` of the gripper velocity's response to the command (0: none).
    position_blend:
        With ``T = 0``: share of a step travelled at the previous velocity (see
        :func:`lag_discretisation`). The defaults are identified from the plant's
        operational-space loop, whose velocity reference slews at 8 m/s^2: with the change
        of the command kept inside that slew (:attr:`max_accel_mps2`) the TCP velocity
        reaches the command within one 40 ms step, on a ramp; ``0.31`` is the least-squares
        fit of ``p+ - p - dt u = beta dt (v - u)`` over closed-loop steps on the realistic
        scenario, dev seeds (``codesign bench mpc``: ``position_blend_fit``).
    max_accel_mps2:
        Bound on the norm of the predicted gripper acceleration (the velocity change per
        step over ``dt``), kept as the cuboctahedron inscribed in that ball
        (:func:`~codesign_mb.control.mpc_model.ramp_rows`). Below the low level's reference
        slew (:attr:`~codesign_mb.robot.osc.OscGains.max_accel_mps2`, 8 m/s^2), so the ramp
        to each command ends within the step, as the model ``v[k+1] = u[k]`` says; the margin
        covers the difference between the measured velocity and the low level's reference.
    speed_fraction:
        Fraction of the plant's maximum Cartesian speed the MPC may command, in (0, 1].
    workspace_low, workspace_high:
        Corners of the box the gripper must stay in, world frame; ``None``: the plant's box
        shrunk by :attr:`workspace_margin_m` (:meth:`MpcController.from_env`).
    workspace_margin_m:
        How far inside the plant's workspace box the MPC's box lies.
    funnel_slope:
        ``c``: height gained per metre of lateral offset from the object (approach funnel).
    funnel_slope_y:
        The funnel's slope along the belt (y); ``None``: :attr:`funnel_slope`. The fingers
        close across the belt (x): open, they straddle the object and may slide along it at
        the grasp height (``0``), so an object that stops or restarts under the gripper is
        followed low instead of from above.
    clearance_m:
        Height of the clearance plane above the grasp point while not aligned (APPROACH).
    hover_height_m:
        Height of the APPROACH reference above the grasp point.
    grasp_offset_m:
        Gripper position minus object position at the grasp (world frame, e.g. the fingertip
        centre slightly above the object's centre).
    lift_height_m:
        How far the LIFT reference rises above where the gripper closed.
    align_tolerance_m:
        Lateral error below which APPROACH becomes DESCEND.
    abort_tolerance_m:
        Lateral error above which DESCEND returns to APPROACH (in between, the funnel keeps
        the gripper high enough while it re-aligns).
    abort_tolerance_y_m:
        With it, :attr:`abort_tolerance_m` bounds the error across the belt (x) and this one
        the error along it (y), where the open fingers straddle the object; ``None``: one
        bound on the lateral error.
    grasp_tolerance_m, grasp_height_tolerance_m:
        Lateral and vertical distances to the grasp point below which the fingers close.
    funnel_apex_depth_m:
        How far below the grasp point the funnel's apex lies: room for the last centimetre
        of the descent despite a small lateral error (perception noise).
    close_steps:
        Steps the fingers get to close before LIFT.
    grasp_std_gate_m:
        Uncertainty-aware grasping: the fingers close only when the estimator's RMS position
        uncertainty (an entry it appends after the state layout, e.g.
        :class:`~codesign_mb.estimation.belt_imm.BeltImmPredictor` with ``output_std``) is at
        most this; until then the gripper tracks the object at the grasp point and waits.
        ``None``: close on position alone.
    grasp_abort_tolerance_m:
        Lateral error to the estimated grasp point above which closing fingers reopen and the
        pick goes back to DESCEND (the object moved from under them: a belt stop or restart
        the gripper could not follow within the closing steps; the cube is still grasped
        20 mm off centre, not 30 mm, measured on the variable belt with every packet);
        ``None``: a close, once begun, runs its :attr:`close_steps`.
    min_grip_width_m:
        A finger width below this after closing means the grasp missed (back to APPROACH).
    weight_position, weight_height, weight_velocity, weight_command, weight_rate, weight_terminal:
        Cost weights: lateral and vertical position error, velocity tracking, command
        deviation from the feed-forward, command rate, and the multiplier of the terminal
        cost (the per-axis LQ cost-to-go, :func:`~codesign_mb.control.mpc_model.terminal_weights`).
    joint_limits:
        Limit the arm's joint positions and speeds (linearised through the Pinocchio
        Jacobian at each step) when the controller knows the joints
        (:meth:`MpcController.from_env` on a plant with a robot).
    joint_margin_rad, joint_velocity_fraction:
        How far inside the joint position limits the predicted joints stay, and the share of
        the joint speed limits the MPC may use.
    joint_relinearise_rad:
        The Jacobian of the joint limits is recomputed once a joint moved this far from
        where it was last computed (the rows then change, and the solver redoes its matrix
        setup); in between, the joints' offsets still use the measured configuration.
    slack_linear, slack_quadratic:
        Penalties ``rho1, rho2`` on the slack of the soft constraints (plane and funnel).
    solver:
        ``"daqp_native"`` (default: DAQP on a workspace kept between solves, only the linear
        term and the bounds updated, hot-started), or a ``casadi.conic`` plugin given the whole
        QP every step: ``"qpoases"`` (hot-started), ``"daqp"`` or ``"osqp"`` (warm-started).
    """

    horizon: int = 15
    lag_time_constant_s: float = 0.0
    position_blend: float = 0.31
    max_accel_mps2: float = 7.5
    speed_fraction: float = 1.0
    workspace_low: tuple[float, float, float] | None = None
    workspace_high: tuple[float, float, float] | None = None
    workspace_margin_m: float = 0.005
    funnel_slope: float = 1.5
    funnel_slope_y: float | None = None
    abort_tolerance_y_m: float | None = None
    clearance_m: float = 0.04
    hover_height_m: float = 0.06
    grasp_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lift_height_m: float = 0.15
    align_tolerance_m: float = 0.01
    abort_tolerance_m: float = 0.04
    grasp_tolerance_m: float = 0.012
    grasp_height_tolerance_m: float = 0.015
    funnel_apex_depth_m: float = 0.015
    close_steps: int = 5
    grasp_std_gate_m: float | None = None
    grasp_abort_tolerance_m: float | None = None
    min_grip_width_m: float = 0.005
    weight_position: float = 100.0
    weight_height: float = 100.0
    weight_velocity: float = 1.0
    weight_command: float = 0.1
    weight_rate: float = 1.0
    weight_terminal: float = 1.0
    slack_linear: float = 1e3
    slack_quadratic: float = 1e4
    solver: str = "daqp_native"
    joint_limits: bool = True
    joint_margin_rad: float = 0.05
    joint_velocity_fraction: float = 0.9
    joint_relinearise_rad: float = 0.02

    def __post_init__(self) -> None:
        for name in ("horizon", "close_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if not 2 <= self.horizon <= 100:
            raise ValueError(f"horizon must be in [2, 100], got {self.horizon}")
        if self.close_steps < 0:
            raise ValueError(f"close_steps must be >= 0, got {self.close_steps}")
        for name in ("workspace_low", "workspace_high", "grasp_offset_m"):
            if getattr(self, name) is None and name != "grasp_offset_m":
                continue
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ValueError(f"{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        if (self.workspace_low is None) != (self.workspace_high is None):
            raise ValueError("workspace_low and workspace_high must be given together")
        if self.workspace_low is not None and any(
            lo >= hi for lo, hi in zip(self.workspace_low, self.workspace_high, strict=True)
        ):
            raise ValueError(
                f"workspace_low must be < workspace_high, got {self.workspace_low} and "
                f"{self.workspace_high}"
            )
        if not 0.0 <= self.position_blend <= 1.0:
            raise ValueError(f"position_blend must be in [0, 1], got {self.position_blend}")
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ValueError(f"speed_fraction must be in (0, 1], got {self.speed_fraction}")
        positive = (
            "max_accel_mps2",
            "align_tolerance_m",
            "abort_tolerance_m",
            "grasp_tolerance_m",
            "grasp_height_tolerance_m",
        )
        non_negative = (
            "lag_time_constant_s",
            "workspace_margin_m",
            "funnel_slope",
            "funnel_apex_depth_m",
            "clearance_m",
            "hover_height_m",
            "lift_height_m",
            "min_grip_width_m",
            "weight_position",
            "weight_height",
            "weight_velocity",
            "weight_command",
            "weight_terminal",
            "slack_linear",
            "slack_quadratic",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be > 0, got {value}")
        for name in non_negative:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0, got {value}")
        if not (math.isfinite(self.weight_rate) and self.weight_rate > 0):
            raise ValueError(f"weight_rate must be > 0, got {self.weight_rate}")
        for name in ("grasp_std_gate_m", "grasp_abort_tolerance_m", "abort_tolerance_y_m"):
            gate = getattr(self, name)
            if gate is not None and not (math.isfinite(gate) and gate > 0):
                raise ValueError(f"{name} must be > 0 or None, got {gate!r}")
        slope = self.funnel_slope_y
        if slope is not None and not (math.isfinite(slope) and slope >= 0):
            raise ValueError(f"funnel_slope_y must be >= 0 or None, got {slope!r}")
        if not isinstance(self.joint_limits, bool):
            raise ValueError(f"joint_limits must be a bool, got {self.joint_limits!r}")
        if not (math.isfinite(self.joint_margin_rad) and self.joint_margin_rad >= 0):
            raise ValueError(f"joint_margin_rad must be >= 0, got {self.joint_margin_rad}")
        if not (math.isfinite(self.joint_relinearise_rad) and self.joint_relinearise_rad >= 0):
            raise ValueError(
                f"joint_relinearise_rad must be >= 0, got {self.joint_relinearise_rad}"
            )
        if not 0.0 < self.joint_velocity_fraction <= 1.0:
            raise ValueError(
                f"joint_velocity_fraction must be in (0, 1], got {self.joint_velocity_fraction}"
            )
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got {self.solver!r}")


def config_fields() -> list[str]:
    """Names of :class:`MpcConfig`'s fields (for CLIs and docs)."""
    return [f.name for f in fields(MpcConfig)]
