"""What the MPC knows of the arm: joint limits through Pinocchio, the low level's ramp, the
terminal cost; each checked against an independent computation."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

from codesign_mb.control.mpc import OFF, MpcConfig, MpcQp, lag_discretisation
from codesign_mb.control.mpc_model import JointLimits, joint_linearisation, ramp_rows
from codesign_mb.robot.model import N_ARM, PandaModel
from codesign_mb.robot.simulator import home_configuration

DT = 0.04
LOW = (-1.0, -1.0, -0.5)
HIGH = (1.5, 1.0, 1.5)


def _plan_positions(qp: MpcQp, commands: np.ndarray, p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``p[1..N]`` by the model's recursion (not the QP's matrices)."""
    a, bp_v, bp_u = lag_discretisation(DT, qp.config.lag_time_constant_s, qp.config.position_blend)
    out = []
    for u in commands:
        p = p + bp_v * v + bp_u * u
        v = a * v + (1 - a) * u
        out.append(p)
    return np.array(out)


def _integrate_joints(robot: PandaModel, q: np.ndarray, path: np.ndarray, substeps: int = 20):
    """Joint positions along a TCP path, by small steps ``dq = J_v^+(q) dp`` (Pinocchio)."""
    q = q.copy()
    p = robot.tcp_pose(q)[0]
    out = []
    for target in path:
        for i in range(substeps):
            step = (target - p) / (substeps - i)
            q[:N_ARM] += joint_linearisation(robot, q, N_ARM) @ step
            p = robot.tcp_pose(q)[0]
        out.append(q[:N_ARM].copy())
    return np.array(out)


def test_joint_linearisation_matches_forward_kinematics() -> None:
    robot = PandaModel()
    rng = np.random.default_rng(0)
    q0 = np.array(home_configuration(), dtype=float)
    for _ in range(10):
        q = q0.copy()
        q[:N_ARM] += rng.normal(0.0, 0.2, N_ARM)
        p, R = robot.tcp_pose(q)
        pinv = joint_linearisation(robot, q, N_ARM)
        for size in (1e-3, 1e-2):
            dp = rng.normal(size=3)
            dp *= size / np.linalg.norm(dp)
            q1 = q.copy()
            q1[:N_ARM] += pinv @ dp
            p1, R1 = robot.tcp_pose(q1)
            # First order: the error is second order in the step, the orientation kept.
            assert np.linalg.norm(p1 - (p + dp)) <= 2.0 * size**2
            assert np.linalg.norm(R1 - R) <= 5.0 * size**2


def _joint_qp(limits: JointLimits, **kw) -> MpcQp:
    cfg = MpcConfig(horizon=10, workspace_low=LOW, workspace_high=HIGH, **kw)
    return MpcQp(cfg, dt=DT, max_speed_mps=1.0, joint_limits=limits)


def _theta(qp: MpcQp, p: np.ndarray, ref: np.ndarray, v: np.ndarray | None = None) -> np.ndarray:
    n = qp.n
    v = np.zeros(3) if v is None else v
    off = np.tile([0.0, 0.0, -OFF], (n, 1))
    return qp.pack(p, v, v, np.tile(ref, (n, 1)), np.zeros((n, 3)), off)


def test_qp_joint_rows_are_the_linearised_joints_of_the_plan() -> None:
    robot = PandaModel()
    q = np.array(home_configuration(), dtype=float)
    p0 = robot.tcp_pose(q)[0]
    qp = _joint_qp(JointLimits.panda())
    theta = _theta(qp, p0, p0 + np.array([0.05, -0.04, 0.03]), v=np.array([0.1, 0.0, -0.05]))
    joints = (q[:N_ARM].copy(), joint_linearisation(robot, q, N_ARM))
    sol = qp.solve(theta, joints)
    assert sol.success, sol.status
    data = qp.qp_data(theta, joints)
    w = np.concatenate([sol.commands.ravel(), [sol.slack]])
    rows = qp.rows["joint_position"]
    # The rows are J_v^+ times the planned motion beyond the one of zero commands, at the
    # limited steps: with the offsets, q0 + J_v^+ (p[k] - p[0]).
    path = _plan_positions(qp, sol.commands, p0, theta[3:6])
    drift = _plan_positions(qp, np.zeros_like(sol.commands), p0, theta[3:6])
    k = np.array(qp.joint_steps) - 1
    expected = ((path[k] - drift[k]) @ joints[1].T).ravel()
    np.testing.assert_allclose(data["a"][rows] @ w, expected, atol=1e-9)
    assert np.all(data["lba"][rows] <= data["a"][rows] @ w + 1e-9)
    assert np.all(data["a"][rows] @ w <= data["uba"][rows] + 1e-9)
    expected = q[:N_ARM] + (path[k] - p0) @ joints[1].T
    # ... and they match the joints Pinocchio integrates along the planned path, to second
    # order in the distance travelled (centimetres here).
    exact = _integrate_joints(robot, q, path)[k]
    travelled = np.linalg.norm(path[k] - p0, axis=1)
    assert np.all(np.max(np.abs(exact - expected), axis=1) <= 5.0 * travelled**2 + 1e-6)


def test_a_joint_at_its_limit_is_not_driven_across() -> None:
    robot = PandaModel()
    q = np.array(home_configuration(), dtype=float)
    p0 = robot.tcp_pose(q)[0]
    pinv = joint_linearisation(robot, q, N_ARM)
    panda = JointLimits.panda()
    j = 3  # the elbow
    margin = panda.margin_rad
    upper = list(panda.upper)
    upper[j] = float(q[j] + margin + 0.01)  # 1 cm-radian of room left before the margin
    limits = dataclasses.replace(panda, upper=tuple(upper))
    direction = pinv[j] / np.linalg.norm(pinv[j])  # the TCP motion that raises joint j
    qp = _joint_qp(limits)
    theta = _theta(qp, p0, p0 + 0.15 * direction)
    joints = (q[:N_ARM].copy(), pinv)
    sol = qp.solve(theta, joints)
    assert sol.success, sol.status
    path = _plan_positions(qp, sol.commands, p0, np.zeros(3))
    exact = _integrate_joints(robot, q, path)
    assert np.max(exact[:, j]) <= upper[j]  # the real limit is never crossed ...
    k = np.array(qp.joint_steps) - 1
    assert np.max(exact[k, j]) <= upper[j] - margin + 2e-3  # ... nor, nearly, the margin
    # Without the joint rows the same reference drives the joint past its limit.
    free = MpcQp(dataclasses.replace(qp.config), dt=DT, max_speed_mps=1.0).solve(theta)
    free_path = _plan_positions(qp, free.commands, p0, np.zeros(3))
    assert np.max(_integrate_joints(robot, q, free_path)[:, j]) > upper[j]


def test_a_state_past_a_joint_limit_keeps_a_feasible_problem() -> None:
    robot = PandaModel()
    q = np.array(home_configuration(), dtype=float)
    p0 = robot.tcp_pose(q)[0]
    pinv = joint_linearisation(robot, q, N_ARM)
    panda = JointLimits.panda()
    j = 3
    upper = list(panda.upper)
    upper[j] = float(q[j] - 0.02)  # already beyond it, moving further
    qp = _joint_qp(dataclasses.replace(panda, upper=tuple(upper)))
    velocity = 0.3 * pinv[j] / np.linalg.norm(pinv[j]) / np.linalg.norm(pinv[j])
    theta = _theta(qp, p0, p0, v=velocity)
    sol = qp.solve(theta, (q[:N_ARM].copy(), pinv))
    assert sol.success, sol.status
    # It brakes and heads back: the joint goes no further than the braking path takes it.
    speeds = sol.commands @ pinv[j]
    assert speeds[0] < velocity @ pinv[j] and speeds[-1] <= 1e-9
    brake = qp.stopping_path(p0, velocity)
    path = _plan_positions(qp, sol.commands, p0, velocity)
    assert np.max((path - p0) @ pinv[j]) <= np.max((brake - p0) @ pinv[j]) + 1e-9


def test_joint_speed_limits_bound_the_commands() -> None:
    robot = PandaModel()
    q = np.array(home_configuration(), dtype=float)
    p0 = robot.tcp_pose(q)[0]
    pinv = joint_linearisation(robot, q, N_ARM)
    limits = JointLimits.panda(velocity_fraction=0.2)
    qp = _joint_qp(limits)
    sol = qp.solve(_theta(qp, p0, p0 + np.array([0.3, 0.3, 0.3])), (q[:N_ARM].copy(), pinv))
    assert sol.success, sol.status
    k = np.array(qp.joint_steps) - 1
    joint_speeds = np.abs(sol.commands[k] @ pinv.T)  # v[k+1] = u[k] (no lag)
    assert np.all(joint_speeds <= limits.speed_bound() + 1e-6)
    assert np.max(joint_speeds / limits.speed_bound()) > 0.99  # and the limit was binding


def test_ramp_polytope_is_inscribed_in_the_low_levels_ball() -> None:
    F, b = ramp_rows(8.0, DT)
    radius = 8.0 * DT
    rng = np.random.default_rng(1)
    samples = rng.uniform(-radius, radius, (20000, 3))
    inside = np.all(np.abs(samples @ F.T) <= b, axis=1)
    assert np.all(np.linalg.norm(samples[inside], axis=1) <= radius + 1e-12)
    c = b[0]
    vertex = np.array([c, c, 0.0])  # a vertex: on the sphere, so nothing larger fits
    assert np.all(np.abs(F @ vertex) <= b + 1e-12)
    assert np.linalg.norm(vertex) == pytest.approx(radius)


def test_bounds_keep_the_velocity_change_inside_the_ramp() -> None:
    cfg = MpcConfig(horizon=8, workspace_low=LOW, workspace_high=HIGH)
    qp = MpcQp(cfg, dt=DT, max_speed_mps=1.0)
    rng = np.random.default_rng(2)
    for _ in range(20):
        p = rng.uniform(0.0, 0.5, 3)
        v = rng.uniform(-0.3, 0.3, 3)
        sol = qp.solve(_theta(qp, p, p + rng.normal(0.0, 0.3, 3), v=v))
        assert sol.success
        velocities = np.vstack([v, sol.commands])  # v[k+1] = u[k]
        steps = np.linalg.norm(np.diff(velocities, axis=0), axis=1)
        assert np.all(steps <= cfg.max_accel_mps2 * DT + 1e-9)


def test_terminal_cost_makes_a_short_horizon_the_infinite_one() -> None:
    # Constraints inactive: horizon 5 with the Riccati terminal cost gives the plan of
    # horizon 80 without one (whose truncated tail is negligible).
    base = MpcConfig(horizon=5, workspace_low=LOW, workspace_high=HIGH)
    short = MpcQp(base, dt=DT, max_speed_mps=1.0)
    long = MpcQp(
        dataclasses.replace(base, horizon=80, weight_terminal=0.0), dt=DT, max_speed_mps=1.0
    )
    no_terminal = MpcQp(dataclasses.replace(base, weight_terminal=0.0), dt=DT, max_speed_mps=1.0)
    p = np.array([0.3, 0.1, 0.4])
    ref = p + np.array([0.004, -0.003, 0.002])
    v = np.array([0.01, 0.0, -0.01])
    u_short = short.solve(_theta(short, p, ref, v)).commands
    u_long = long.solve(_theta(long, p, ref, v)).commands
    u_none = no_terminal.solve(_theta(no_terminal, p, ref, v)).commands
    np.testing.assert_allclose(u_short, u_long[:5], atol=1e-7)
    assert np.max(np.abs(u_none - u_long[:5])) > 1e-3  # without it, visibly different


def test_qp_with_joint_limits_pickles() -> None:
    qp = _joint_qp(JointLimits.panda())
    clone = pickle.loads(pickle.dumps(qp))
    assert clone.joint_limits == qp.joint_limits and clone.n_con == qp.n_con


@pytest.mark.slow
def test_one_step_model_error_against_mujoco() -> None:
    from codesign_mb.bench.mpc import one_step_model_error

    result = one_step_model_error(episodes=2)
    assert result["steps"] == 198
    assert result["p99_mm"] <= 3.0, result
    # The identified blend stays what the model uses (to the fit's spread on two episodes).
    assert abs(result["position_blend_fit"] - MpcConfig().position_blend) <= 0.1
