"""The MPC's QP: bounds respected on random feasible instances, solver parity, fallback."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from codesign_mb.control.base import Controller
from codesign_mb.control.mpc import (
    OFF,
    MpcConfig,
    MpcController,
    MpcQp,
    Phase,
    lag_discretisation,
)

LAYOUT = {
    "gripper_pos": slice(0, 3),
    "gripper_vel": slice(3, 6),
    "finger_width": slice(6, 7),
    "object_pos": slice(7, 10),
    "object_vel": slice(10, 13),
}
DT = 0.04
V_MAX = 1.0
LOW = np.array([-0.4, -0.4, 0.0])
HIGH = np.array([0.8, 0.4, 0.6])


def _config(**kw) -> MpcConfig:
    base = dict(
        horizon=12,
        lag_time_constant_s=0.03,
        max_accel_mps2=6.0,
        workspace_low=tuple(LOW),
        workspace_high=tuple(HIGH),
    )
    base.update(kw)
    return MpcConfig(**base)


def _simulate(x_u: np.ndarray, p: np.ndarray, v: np.ndarray, cfg: MpcConfig):
    """Positions and velocities along the horizon, by the model's recursion (not the QP's A)."""
    a, bp_v, bp_u = lag_discretisation(DT, cfg.lag_time_constant_s, cfg.position_blend)
    ps, vs = [], [v]
    for u in x_u:
        p = p + bp_v * v + bp_u * u
        v = a * v + (1 - a) * u
        ps.append(p)
        vs.append(v)
    return np.array(ps), np.array(vs)


def _random_instance(qp: MpcQp, rng: np.random.Generator):
    n = qp.n
    margin = 0.12  # room to brake from full speed at max_accel (v^2 / 2a < 0.09 m)
    p = rng.uniform(LOW + margin, HIGH - margin)
    v = rng.uniform(-0.9, 0.9, 3) * qp.v_max
    u_prev = v.copy()
    obj = rng.uniform(LOW + 0.05, HIGH - 0.05)
    obj[2] = 0.05
    w = np.array([rng.uniform(0.0, 0.7), 0.0, 0.0])
    path = obj + DT * np.arange(1, n + 1)[:, None] * w
    ref = path + np.array([0, 0, rng.uniform(0.0, 0.1)])
    vref = np.tile(w, (n, 1))
    return qp.pack(p, v, u_prev, ref, vref, path), p, v


@pytest.mark.parametrize("solver", ["qpoases", "daqp", "osqp"])
def test_bounds_hold_on_random_feasible_instances(solver: str) -> None:
    cfg = _config(solver=solver)
    qp = MpcQp(cfg, dt=DT, max_speed_mps=V_MAX)
    rng = np.random.default_rng(0)
    tol = 1e-6 if solver != "osqp" else 1e-4
    for _ in range(40):
        theta, p, v = _random_instance(qp, rng)
        sol = qp.solve(theta)
        assert sol.success, sol.status
        u = sol.commands
        assert np.all(np.abs(u) <= qp.v_max + tol)
        ps, vs = _simulate(u, p, v, cfg)
        assert np.all(np.abs(np.diff(vs, axis=0)) <= cfg.max_accel_mps2 * DT + tol)
        assert np.all(ps >= LOW - tol) and np.all(ps <= HIGH + tol)
        assert sol.slack >= -tol


def test_solvers_agree_and_warm_start_equals_cold_start() -> None:
    rng = np.random.default_rng(1)
    qps = {s: MpcQp(_config(solver=s), dt=DT, max_speed_mps=V_MAX) for s in ("qpoases", "daqp")}
    warm = MpcQp(_config(), dt=DT, max_speed_mps=V_MAX)
    for _ in range(15):
        theta, _, _ = _random_instance(warm, rng)
        for qp in qps.values():
            qp.reset()  # cold
        a = qps["qpoases"].solve(theta).commands
        b = qps["daqp"].solve(theta).commands
        c = warm.solve(theta).commands  # hot-started from the previous instance
        np.testing.assert_allclose(a, b, atol=1e-6)
        np.testing.assert_allclose(a, c, atol=1e-6)


def test_clearance_plane_then_funnel_keep_the_gripper_above_until_aligned() -> None:
    cfg = _config(funnel_slope=2.0)
    qp = MpcQp(cfg, dt=DT, max_speed_mps=V_MAX)
    n = qp.n
    obj = np.array([0.3, 0.0, 0.05])
    path = np.tile(obj, (n, 1))
    off = np.tile([0.0, 0.0, -OFF], (n, 1))
    # Far away, the reference straight at the grasp point: the plane, not the cost, keeps it up.
    p = np.array([0.0, 0.0, 0.2])
    theta = qp.pack(p, np.zeros(3), np.zeros(3), path, np.zeros((n, 3)), off, obj[2] + 0.1)
    sol = qp.solve(theta)
    assert sol.success and sol.slack < 1e-6
    ps, _ = _simulate(sol.commands, p, np.zeros(3), cfg)
    assert np.all(ps[:, 2] >= obj[2] + 0.1 - 1e-6)
    # Close by: the funnel lets it descend only as far as its lateral offset allows.
    p = np.array([0.26, 0.02, 0.2])
    theta = qp.pack(p, np.zeros(3), np.zeros(3), path, np.zeros((n, 3)), path)
    sol = qp.solve(theta)
    assert sol.success and sol.slack < 1e-6
    ps, _ = _simulate(sol.commands, p, np.zeros(3), cfg)
    lateral = np.max(np.abs(ps[:, :2] - obj[:2]), axis=1)
    assert np.all(ps[:, 2] - obj[2] >= cfg.funnel_slope * lateral - 1e-6)
    assert ps[-1, 2] < 0.1  # and it does come down


def _obs(p, v=(0, 0, 0), width=0.08, obj=(0.3, 0.0, 0.05), w=(0.2, 0, 0)) -> np.ndarray:
    return np.concatenate([p, v, [width], obj, w]).astype(float)


def test_infeasible_start_falls_back_and_counts() -> None:
    ctl = MpcController(LAYOUT, control_period_s=DT, max_speed_mps=V_MAX, config=_config())
    assert isinstance(ctl, Controller)
    ctl.reset(seed=0)
    # 3x the speed limit: no admissible command brakes within one step's acceleration bound.
    action = ctl.act(_obs([0.2, 0.0, 0.3], v=(3.0, 0.0, 0.0)))
    assert ctl.failures == 1 and ctl.total_failures == 1
    assert np.all(np.abs(action) <= 1.0)
    np.testing.assert_allclose(action[:3], 0.0)  # inside the workspace: stop
    metrics = ctl.episode_metrics()
    assert metrics["mpc_failures"] == 1 and metrics["mpc_solves"] == 1
    # A feasible state again: the MPC takes over (from a fresh solver, not the failed one).
    ctl.act(_obs([0.2, 0.0, 0.3]))
    assert ctl.failures == 1 and ctl.last_solution is not None and ctl.last_solution.success
    ctl.reset()
    assert ctl.failures == 0 and ctl.total_failures == 1


def test_outside_the_workspace_stays_feasible_and_heads_back() -> None:
    """The box is widened to the braking path, so a gripper outside it is brought back."""
    ctl = MpcController(LAYOUT, control_period_s=DT, max_speed_mps=V_MAX, config=_config())
    ctl.reset()
    action = ctl.act(_obs([0.2, 0.0, HIGH[2] + 0.3]))  # 30 cm above the box
    assert ctl.failures == 0 and action[2] < -0.2
    action = ctl.act(_obs([0.2, HIGH[1] - 0.01, 0.3], v=(0.0, 0.9, 0.0)))  # too fast to stop
    assert ctl.failures == 0 and action[1] < 0.9
    # the fallback command of a failure outside the box points back into it, bounded
    np.testing.assert_allclose(ctl._safe_command(np.array([0.2, 0.0, 1.5]))[:2], 0.0)
    assert -0.25 * V_MAX <= ctl._safe_command(np.array([0.2, 0.0, 1.5]))[2] < 0


def test_phases_progress_on_a_kinematic_pick() -> None:
    """Approach, descend, grasp and lift on the MPC's own model with a belt-driven object."""
    cfg = _config()
    ctl = MpcController(LAYOUT, control_period_s=DT, max_speed_mps=V_MAX, config=cfg)
    ctl.reset(seed=0)
    a, bp_v, bp_u = lag_discretisation(DT, cfg.lag_time_constant_s, cfg.position_blend)
    p, v = np.array([0.3, 0.1, 0.35]), np.zeros(3)
    obj, w = np.array([-0.2, -0.05, 0.05]), np.array([0.4, 0.0, 0.0])
    seen = []
    for _ in range(80):
        action = ctl.act(_obs(p, v, 0.03 if action_closed(ctl) else 0.08, obj, w))
        seen.append(ctl.phase)
        u = action[:3] * V_MAX
        p, v = p + bp_v * v + bp_u * u, a * v + (1 - a) * u
        obj = p.copy() if ctl.phase == Phase.LIFT else obj + DT * w
    assert seen[0] == Phase.APPROACH and seen[-1] == Phase.LIFT
    assert [ph for i, ph in enumerate(seen) if i == 0 or ph != seen[i - 1]] == list(Phase)
    assert p[2] > 0.05 + 0.8 * cfg.lift_height_m
    assert ctl.failures == 0


def action_closed(ctl: MpcController) -> bool:
    return ctl.phase in (Phase.GRASP, Phase.LIFT)


def test_pickles_without_casadi_objects() -> None:
    ctl = MpcController(LAYOUT, control_period_s=DT, max_speed_mps=V_MAX, config=_config())
    clone = pickle.loads(pickle.dumps(ctl))
    obs = _obs([0.2, 0.0, 0.3])
    np.testing.assert_allclose(ctl.act(obs), clone.act(obs), atol=1e-9)


def test_config_errors_name_the_field() -> None:
    with pytest.raises(ValueError, match="horizon must be in"):
        MpcConfig(horizon=1)
    with pytest.raises(ValueError, match="solver must be one of"):
        MpcConfig(solver="gurobi")
    with pytest.raises(ValueError, match="workspace_low must be < workspace_high"):
        MpcConfig(workspace_low=(0, 0, 0), workspace_high=(1, 1, 0))
    with pytest.raises(ValueError, match="max_accel_mps2 must be > 0"):
        MpcConfig(max_accel_mps2=-1.0)
    with pytest.raises(ValueError, match="lacks finger_width"):
        MpcController(
            {"gripper_pos": slice(0, 3), "gripper_vel": slice(3, 6), "object_pos": slice(6, 9)},
            control_period_s=DT,
            max_speed_mps=1.0,
        )
    assert math.isclose(lag_discretisation(DT, 0.0)[2], DT)


def test_the_fingers_close_only_on_a_certain_estimate() -> None:
    """Uncertainty-aware grasping: at the grasp point with the estimator's uncertainty (the
    entry after the state layout) above the gate the gripper keeps tracking with the fingers
    open; once the uncertainty is below it, it closes."""
    cfg = _config(grasp_std_gate_m=0.01)
    ctl = MpcController(LAYOUT, control_period_s=DT, max_speed_mps=V_MAX, config=cfg)
    ctl.reset(seed=0)
    a, bp_v, bp_u = lag_discretisation(DT, cfg.lag_time_constant_s, cfg.position_blend)
    p, v = np.array([0.3, 0.0, 0.2]), np.zeros(3)
    obj, w = np.array([0.3, 0.0, 0.05]), np.zeros(3)
    uncertain = []
    for step in range(60):
        std = 0.05 if step < 40 else 0.002
        action = ctl.act(np.append(_obs(p, v, 0.08, obj, w), std))
        uncertain.append((step, ctl.phase, action[3]))
        if step == 39:
            waiting = p.copy()
        u = action[:3] * V_MAX
        p, v = p + bp_v * v + bp_u * u, a * v + (1 - a) * u
    assert all(ph < Phase.GRASP and grip < 0 for step, ph, grip in uncertain if step < 40)
    assert np.hypot(*(waiting - obj)[:2]) < cfg.grasp_tolerance_m  # waiting over the object
    assert any(ph == Phase.GRASP and grip > 0 for step, ph, grip in uncertain if step >= 40)


def test_closing_fingers_reopen_when_the_object_leaves_them() -> None:
    """A belt stop under closing fingers: the estimate jumps 3 cm ahead of the gripper; with
    ``grasp_abort_tolerance_m`` the fingers reopen (DESCEND) and close again once over it,
    without it the close runs its steps into LIFT on nothing."""

    def run(abort: float | None) -> list[tuple[Phase, float]]:
        cfg = _config(grasp_abort_tolerance_m=abort)
        ctl = MpcController(LAYOUT, control_period_s=DT, max_speed_mps=V_MAX, config=cfg)
        ctl.reset(seed=0)
        a, bp_v, bp_u = lag_discretisation(DT, cfg.lag_time_constant_s, cfg.position_blend)
        p, v = np.array([0.3, 0.0, 0.06]), np.zeros(3)
        obj = np.array([0.3, 0.0, 0.05])
        seen = []
        for step in range(40):
            if step == 3:
                obj = obj + np.array([0.03, 0.0, 0.0])  # moved while the fingers close
            action = ctl.act(_obs(p, v, 0.08, obj, (0, 0, 0)))
            seen.append((ctl.phase, action[3]))
            u = action[:3] * V_MAX
            p, v = p + bp_v * v + bp_u * u, a * v + (1 - a) * u
        return seen

    kept = run(None)
    assert kept[2][0] == Phase.GRASP and Phase.DESCEND not in [ph for ph, _ in kept[3:]]
    reopened = run(0.02)
    assert reopened[2][0] == Phase.GRASP
    assert reopened[3] == (Phase.DESCEND, -1.0)  # the fingers open at once
    assert any(ph == Phase.GRASP for ph, _ in reopened[4:])  # and close over it again


def test_a_flat_funnel_along_the_belt_lets_the_open_fingers_slide_low() -> None:
    """``funnel_slope_y = 0``: with the gripper 5 cm along the belt (y) from the object at
    its grasp height, the QP keeps it low (no slack); the default pyramid lifts it."""
    obj = np.array([0.3, 0.0, 0.05])
    p = np.array([0.3, 0.05, 0.05])
    for slope_y, low in ((None, False), (0.0, True)):
        cfg = _config(funnel_slope=2.0, funnel_slope_y=slope_y)
        qp = MpcQp(cfg, dt=DT, max_speed_mps=V_MAX)
        path = np.tile(obj, (qp.n, 1))
        theta = qp.pack(p, np.zeros(3), np.zeros(3), path, np.zeros((qp.n, 3)), path)
        sol = qp.solve(theta)
        assert sol.success
        ps, _ = _simulate(sol.commands, p, np.zeros(3), cfg)
        if low:
            assert sol.slack < 1e-6 and np.max(ps[:, 2]) < obj[2] + 0.01
        else:  # the pyramid wants 2 x 5 cm above the apex at once: up, or slack
            assert np.max(ps[:, 2]) > obj[2] + 0.02 or sol.slack > 1e-3
    with pytest.raises(ValueError, match="funnel_slope_y must be >= 0"):
        MpcConfig(funnel_slope_y=-1.0)
    with pytest.raises(ValueError, match="abort_tolerance_y_m must be > 0"):
        MpcConfig(abort_tolerance_y_m=0.0)
