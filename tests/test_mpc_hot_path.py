"""The MPC's hot path (QP data written in place, solver called through its buffer) equals the
old path (``qp_data`` dicts through ``casadi.Function.call``) on random and recorded problems;
DAQP on its kept workspace (``"daqp_native"``, the default) gives qpOASES' solutions."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from codesign_mb.control.mpc import MpcConfig, MpcController, MpcQp, _quiet_stdout

LOW = (-0.4, -0.4, 0.0)
HIGH = (0.8, 0.4, 0.6)


class ReferenceQp:
    """The solve of the MPC before the hot path: ``qp_data`` dicts, ``Function.call``, stats."""

    def __init__(self, qp: MpcQp) -> None:
        self.qp = qp
        self.reset()

    def reset(self) -> None:
        qp = self.qp
        self.solver = qp._make_solver()
        self.warm = qp.config.solver != "qpoases"
        self.x0, self.lam_x0, self.lam_a0 = np.zeros(qp.n_var), np.zeros(qp.n_var), None

    def solve(self, theta: np.ndarray, joints: Any = None) -> tuple[bool, np.ndarray]:
        qp = self.qp
        data = qp.qp_data(theta, joints)
        args: dict[str, Any] = {"h": qp._H_dm, "a": data["a"]}
        args.update({k: data[k] for k in ("g", "lba", "uba", "lbx", "ubx")})
        if self.warm:
            lam_a0 = np.zeros(qp.n_con) if self.lam_a0 is None else self.lam_a0
            args.update(x0=self.x0, lam_x0=self.lam_x0, lam_a0=lam_a0)
        with _quiet_stdout():
            out = self.solver.call(args)
        x = np.array(out["x"]).ravel()
        ax = data["a"] @ x
        worst = max(
            np.max(data["lbx"] - x),
            np.max(x - data["ubx"]),
            np.max(data["lba"] - ax),
            np.max(ax - data["uba"]),
        )
        ok = bool(self.solver.stats()["success"]) and np.isfinite(x).all() and worst <= 1e-5
        if not ok:
            self.reset()
            return False, np.zeros(qp.n_var)
        if self.warm:
            n = qp.n
            self.x0 = np.concatenate([x[3 : 3 * n], x[3 * n - 3 : 3 * n], x[3 * n :]])
            self.lam_x0 = np.array(out["lam_x"]).ravel()
            self.lam_a0 = np.array(out["lam_a"]).ravel()
        return True, x


def _random_theta(qp: MpcQp, rng: np.random.Generator) -> np.ndarray:
    """Parameters over the whole range the MPC meets, some outside the box or too fast."""
    n = qp.n
    p = rng.uniform(np.array(LOW) - 0.05, np.array(HIGH) + 0.05)
    v = rng.uniform(-1.8, 1.8, 3) * qp.v_max  # beyond v_max + a_max dt (1.4): infeasible
    u_prev = rng.uniform(-1.0, 1.0, 3) * qp.v_max
    w = np.array([0.0, rng.uniform(0.0, 0.7), 0.0])
    obj = rng.uniform(LOW, HIGH)
    path = obj + 0.04 * np.arange(1, n + 1)[:, None] * w
    ref = np.clip(path + np.array([0.0, 0.0, rng.uniform(0.0, 0.1)]), LOW, HIGH)
    apex = path.copy()
    plane = path[:, 2] + 0.04
    if rng.random() < 0.5:
        apex[:, 2] = -1e3
    else:
        plane[:] = -1e3
    return qp.pack(p, v, u_prev, ref, np.tile(w, (n, 1)), apex, plane)


@pytest.mark.parametrize("solver", ["qpoases", "daqp", "osqp"])
def test_hot_path_equals_function_call_on_random_parameters(solver: str) -> None:
    cfg = MpcConfig(workspace_low=LOW, workspace_high=HIGH, solver=solver)
    qp = MpcQp(cfg, dt=0.04, max_speed_mps=1.0)
    ref = ReferenceQp(MpcQp(cfg, dt=0.04, max_speed_mps=1.0))
    rng = np.random.default_rng(3)
    outcomes = []
    for _ in range(60):  # one warm-started sequence, failures (and resets) included
        theta = _random_theta(qp, rng)
        ok, x = ref.solve(theta)
        sol = qp.solve(theta)
        outcomes.append(ok)
        assert sol.success == ok
        if ok:
            if solver == "qpoases":  # same solver, same data: the same bits
                np.testing.assert_array_equal(sol.commands.ravel(), x[: 3 * qp.n])
            else:
                np.testing.assert_allclose(sol.commands.ravel(), x[: 3 * qp.n], atol=1e-9)
    assert 0 < sum(outcomes) < len(outcomes)  # both outcomes were exercised


def test_hot_path_data_equals_qp_data() -> None:
    cfg = MpcConfig(workspace_low=LOW, workspace_high=HIGH)
    qp = MpcQp(cfg, dt=0.04, max_speed_mps=1.0)
    rng = np.random.default_rng(4)
    g, lba, uba = np.empty(qp.n_var), np.empty(qp.n_con), np.empty(qp.n_con)
    for _ in range(50):
        theta = _random_theta(qp, rng)
        data = qp.qp_data(theta)
        qp._fill(theta, g, lba, uba)
        np.testing.assert_array_equal(g, data["g"])
        np.testing.assert_array_equal(lba, data["lba"])
        np.testing.assert_array_equal(uba, data["uba"])


@pytest.mark.parametrize("solver", ["qpoases", "daqp_native"])
def test_hot_path_equals_function_call_on_recorded_episodes(solver: str) -> None:
    from codesign_mb.bench.mpc import record_problems

    problems, args = record_problems(episodes_per_speed=1)
    assert args["config"].solver == "daqp_native"  # the default records the problems
    config = dataclasses.replace(args["config"], solver=solver)
    reference = dataclasses.replace(args["config"], solver="qpoases")
    kw = {"dt": args["dt"], "max_speed_mps": args["max_speed_mps"]}
    qp = MpcQp(config, joint_limits=args["joint_limits"], **kw)
    ref = ReferenceQp(MpcQp(reference, joint_limits=args["joint_limits"], **kw))
    assert args["joint_limits"] is not None  # the conveyor's controller knows the joints
    for episode in problems:
        qp.reset()
        ref.reset()
        for theta, joints in episode:
            assert joints is not None
            ok, x = ref.solve(theta, joints)
            sol = qp.solve(theta, joints)
            assert ok and sol.success
            if solver == "qpoases":
                np.testing.assert_array_equal(sol.commands.ravel(), x[: 3 * qp.n])
            else:  # another active-set solver: the same vertex, to rounding
                np.testing.assert_allclose(sol.commands.ravel(), x[: 3 * qp.n], atol=1e-12)
                assert sol.slack == pytest.approx(x[3 * qp.n], abs=1e-12)


def test_native_daqp_equals_qpoases_on_random_parameters() -> None:
    cfg = MpcConfig(workspace_low=LOW, workspace_high=HIGH, solver="daqp_native")
    qp = MpcQp(cfg, dt=0.04, max_speed_mps=1.0)
    reference = dataclasses.replace(cfg, solver="qpoases")
    ref = ReferenceQp(MpcQp(reference, dt=0.04, max_speed_mps=1.0))
    rng = np.random.default_rng(3)
    outcomes = []
    for _ in range(200):  # one hot-started sequence, failures (and resets) included
        theta = _random_theta(qp, rng)
        ok, x = ref.solve(theta)
        sol = qp.solve(theta)
        outcomes.append(ok)
        assert sol.success == ok, sol.status
        if ok:
            np.testing.assert_allclose(sol.commands.ravel(), x[: 3 * qp.n], atol=1e-9)
        else:
            assert not sol.commands.any()
    assert 0 < sum(outcomes) < len(outcomes)  # both outcomes were exercised


def test_native_daqp_reset_forgets_the_working_set() -> None:
    cfg = MpcConfig(workspace_low=LOW, workspace_high=HIGH, solver="daqp_native")
    qp = MpcQp(cfg, dt=0.04, max_speed_mps=1.0)
    rng = np.random.default_rng(6)
    thetas = [_random_theta(qp, rng) for _ in range(30)]
    first = [qp.solve(t).commands.copy() for t in thetas]
    qp.reset()
    again = [qp.solve(t).commands.copy() for t in thetas]
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)


def test_parameters_written_in_place_equal_pack() -> None:
    from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace

    plant = ConveyorPickPlace(ConveyorConfig())
    ctl = MpcController.from_env(plant)
    rng = np.random.default_rng(5)
    for phase in range(4):
        ctl.reset()
        ctl.phase = type(ctl.phase)(phase)
        ctl._lift_origin = np.array([0.5, 0.0, 0.2]) if phase == 3 else None
        p, v, obj, w = (rng.normal(0.0, 0.2, 3) for _ in range(4))
        if phase == 1:  # DESCEND stays while the lateral error is within the abort tolerance
            p = obj + np.array([0.02, 0.0, 0.1])
        theta = ctl._parameters(p, v, 0.03, obj, w).copy()
        assert int(ctl.phase) == phase  # far from the object: no transition
        n, cfg = ctl.qp.n, ctl.config
        path = obj + cfg.grasp_offset_m + np.arange(1, n + 1)[:, None] * ctl.control_period_s * w
        apex = path.copy()
        apex[:, 2] -= cfg.funnel_apex_depth_m
        plane = np.full(n, -1e3)
        if phase == 0:
            ref, vref, plane, apex[:, 2] = (
                path + np.array([0.0, 0.0, cfg.hover_height_m]),
                np.tile(w, (n, 1)),
                path[:, 2] + cfg.clearance_m,
                -1e3,
            )
        elif phase in (1, 2):
            ref, vref = path, np.tile(w, (n, 1))
        else:
            ref, vref, apex[:, 2] = (
                np.tile(ctl._lift_origin + np.array([0.0, 0.0, cfg.lift_height_m]), (n, 1)),
                np.zeros((n, 3)),
                -1e3,
            )
        ref = np.clip(ref, cfg.workspace_low, cfg.workspace_high)
        expected = ctl.qp.pack(p, v, np.zeros(3), ref, vref, apex, plane)
        np.testing.assert_array_equal(theta, expected)
