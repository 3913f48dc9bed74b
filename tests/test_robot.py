"""The Panda: Pinocchio equals MuJoCo, and the operational-space inner loop tracks."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from codesign_mb.robot.assets import PANDA_URDF, asset_path
from codesign_mb.robot.model import ARM_JOINTS, FINGER_JOINTS, GRIPPER_DOWN, N_ARM, PandaModel
from codesign_mb.robot.osc import OperationalSpaceController, OscGains
from codesign_mb.robot.scene import ROBOT_PREFIX, build_scene, robot_only_model
from codesign_mb.robot.simulator import HOME_TCP_POSITION, ConveyorSimulator


@pytest.fixture(scope="module")
def robot() -> PandaModel:
    return PandaModel()


@pytest.fixture(scope="module", params=["urdf_only", "conveyor_scene"])
def mj_model(request: pytest.FixtureRequest) -> tuple[mujoco.MjModel, int]:
    """The MuJoCo arm alone (URDF import) and inside the plant's scene, with the TCP site."""
    if request.param == "urdf_only":
        model = robot_only_model()
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "tcp")
    else:
        model = build_scene("cube").model
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ROBOT_PREFIX + "tcp")
    return model, site


def _random_configurations(robot: PandaModel, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(robot.lower, robot.upper, size=(n, robot.model.nq))


def test_joint_order_and_limits_agree(robot: PandaModel, mj_model) -> None:
    model, _ = mj_model
    names = [model.joint(i).name.removeprefix(ROBOT_PREFIX) for i in range(9)]
    assert names == list(ARM_JOINTS + FINGER_JOINTS)
    np.testing.assert_allclose(model.jnt_range[:9, 0], robot.lower)
    np.testing.assert_allclose(model.jnt_range[:9, 1], robot.upper)
    np.testing.assert_allclose(model.dof_armature[:9], robot.armature)


def test_gripper_pose_agrees(robot: PandaModel, mj_model) -> None:
    model, site = mj_model
    data = mujoco.MjData(model)
    worst = 0.0
    for q in _random_configurations(robot, 25, seed=1):
        data.qpos[:9] = q
        mujoco.mj_kinematics(model, data)
        position, rotation = robot.tcp_pose(q)
        worst = max(
            worst,
            np.abs(position - data.site_xpos[site]).max(),
            np.abs(rotation - data.site_xmat[site].reshape(3, 3)).max(),
        )
    assert worst < 1e-6


def test_mass_matrix_and_bias_agree(robot: PandaModel, mj_model) -> None:
    model, _ = mj_model
    data = mujoco.MjData(model)
    rng = np.random.default_rng(2)
    full = np.zeros((model.nv, model.nv))
    worst_m = worst_h = 0.0
    for q in _random_configurations(robot, 25, seed=2):
        v = rng.normal(size=9)
        data.qpos[:9] = q
        data.qvel[:9] = v
        mujoco.mj_forward(model, data)
        mujoco.mj_fullM(model, data, full)
        M_mj = full[:9, :9]
        M_pin = robot.mass_matrix(q)
        worst_m = max(worst_m, np.abs(M_mj - M_pin).max() / np.abs(M_mj).max())
        h_pin = robot.nonlinear_effects(q, v)
        worst_h = max(worst_h, np.abs(data.qfrc_bias[:9] - h_pin).max())
    assert worst_m < 1e-6
    assert worst_h < 1e-6


def test_jacobian_agrees(robot: PandaModel, mj_model) -> None:
    model, site = mj_model
    data = mujoco.MjData(model)
    jacp = np.zeros((3, model.nv))
    jacr = np.zeros((3, model.nv))
    for q in _random_configurations(robot, 10, seed=3):
        data.qpos[:9] = q
        mujoco.mj_forward(model, data)
        mujoco.mj_jacSite(model, data, jacp, jacr, site)
        J = robot.tcp_jacobian(q)
        np.testing.assert_allclose(J[:3], jacp[:, :9], atol=1e-9)
        np.testing.assert_allclose(J[3:], jacr[:, :9], atol=1e-9)


def test_moving_mass_agrees(mj_model) -> None:
    model, _ = mj_model
    pin_model = pin.buildModelFromUrdf(str(asset_path(PANDA_URDF)))
    pin_mass = sum(inertia.mass for inertia in pin_model.inertias[1:])
    moving = [
        b
        for b in range(model.nbody)
        if model.body(b).name.removeprefix(ROBOT_PREFIX).startswith("panda_")
        and model.body_weldid[b] != 0  # not welded to the world (the base link is)
    ]
    assert pin_mass == pytest.approx(float(model.body_mass[moving].sum()), abs=1e-9)
    assert pin_mass == pytest.approx(16.822132, abs=1e-6)  # URDF links 1-7, hand, fingers


def test_missing_asset_says_how_to_fix() -> None:
    with pytest.raises(FileNotFoundError, match="pip install -e"):
        asset_path("panda/nope.urdf")


def test_inverse_kinematics_reaches_home(robot: PandaModel) -> None:
    q = robot.inverse_kinematics(HOME_TCP_POSITION, GRIPPER_DOWN)
    position, rotation = robot.tcp_pose(q)
    np.testing.assert_allclose(position, HOME_TCP_POSITION, atol=1e-8)
    np.testing.assert_allclose(rotation, GRIPPER_DOWN, atol=1e-8)
    assert np.all(q >= robot.lower) and np.all(q <= robot.upper)
    with pytest.raises(ValueError, match="did not converge"):
        robot.inverse_kinematics([2.0, 0.0, 0.3], GRIPPER_DOWN)


def test_actuator_limits_are_urdf_limits(robot: PandaModel) -> None:
    scene = build_scene("cube")
    model = scene.model
    np.testing.assert_allclose(
        model.actuator_ctrlrange[scene.arm_actuators, 1], robot.arm_effort_limit
    )
    assert np.all(model.actuator_ctrllimited[scene.arm_actuators])


def test_torque_is_clipped_to_limits(robot: PandaModel) -> None:
    osc = OperationalSpaceController(robot, OscGains(kp_pos=1e6, kd_pos=1e4), model_period=1)
    q = np.array(robot.inverse_kinematics(HOME_TCP_POSITION, GRIPPER_DOWN))
    osc.reset(q)
    osc.set_velocity_command([5.0, 5.0, 5.0])
    tau = None
    for _ in range(10):
        tau = osc.torque(q, np.zeros(9))
    assert np.all(np.abs(tau) <= robot.arm_effort_limit + 1e-12)
    assert np.isclose(np.abs(tau).max(), 87.0)


def test_gains_are_validated() -> None:
    with pytest.raises(ValueError, match="kp_pos"):
        OscGains(kp_pos=-1.0)
    with pytest.raises(ValueError, match="max_lag_m"):
        OscGains(max_lag_m=0.0)
    with pytest.raises(ValueError, match="model_period"):
        OperationalSpaceController(PandaModel(), model_period=0)


def circle_tracking(
    speed: float, radius: float, model_period: int = 10, turns: float = 1.0
) -> dict[str, float]:
    """Track a vertical circle (y-z plane) at ``speed`` after a 0.3 s speed ramp.

    Returns the TCP's distance to the OSC's own reference (inner-loop tracking) and to the
    ideal integrator ``x_{t+1} = x_t + v_t dt`` of the commands (what a policy assumes),
    max and mean over the control steps (m), and the worst orientation error (rad).
    """
    sim = ConveyorSimulator(model_period=model_period)
    sim.reset(object_position=[0.5, -0.7, 0.0825], belt_speed=0.0)
    period = sim.control_period_s
    omega = speed / radius
    n = round(turns * 2 * np.pi / omega / period) + 8
    x_cmd = sim.tcp_position()
    to_ref, to_cmd, rot = [], [], []
    angle = 0.0
    for k in range(n):
        ramp = min(1.0, k * period / 0.3)
        velocity = ramp * speed * np.array([0.0, np.cos(angle), np.sin(angle)])
        angle += ramp * omega * period
        sim.step(velocity, close=False)
        x_cmd = x_cmd + velocity * period
        tcp = sim.tcp_position()
        to_ref.append(np.linalg.norm(tcp - sim.osc.position_reference))
        to_cmd.append(np.linalg.norm(tcp - x_cmd))
        _, rotation = sim.robot.tcp_pose(sim.joint_positions())
        rot.append(np.linalg.norm(pin.log3(GRIPPER_DOWN.T @ rotation)))
    return {
        "ref_max": max(to_ref),
        "ref_mean": float(np.mean(to_ref)),
        "cmd_max": max(to_cmd),
        "cmd_mean": float(np.mean(to_cmd)),
        "rot_max": max(rot),
    }


def test_operational_space_tracking_error() -> None:
    exact = circle_tracking(0.4, 0.2, model_period=1)
    default = circle_tracking(0.4, 0.2)
    fast = circle_tracking(0.8, 0.1)
    assert default["ref_max"] < 2e-3, default  # inner loop: ~1 mm at 0.4 m/s
    assert default["cmd_max"] < 3e-3, default  # vs the ideal integrator of the commands
    assert abs(default["cmd_max"] - exact["cmd_max"]) < 5e-4  # G refreshed every 20 ms
    assert fast["ref_max"] < 4e-3, fast
    # 0.8 m/s on a 10 cm circle turns the command by 0.26 m/s per step: the acceleration
    # bound (8 m/s^2) makes the TCP lag the ideal integrator by ~1.5 cm.
    assert fast["cmd_max"] < 0.025, fast
    assert max(default["rot_max"], fast["rot_max"]) < np.radians(1.0)


def test_run_equals_repeated_torque() -> None:
    """The hot path (run, actuators clamp) equals the reference path (torque + mj_step)."""
    a, b = ConveyorSimulator(), ConveyorSimulator()
    for sim in (a, b):
        sim.reset(object_position=[0.5, -0.45, 0.0825], belt_speed=0.2)
    rng = np.random.default_rng(0)
    for _ in range(5):
        velocity = rng.uniform(-0.5, 0.5, 3)
        a.step(velocity, close=False)
        b.osc.set_velocity_command(velocity)
        b.data.ctrl[b.scene.finger_actuators] = b.finger_speed
        for _ in range(b.n_substeps):
            b.data.ctrl[b.scene.arm_actuators] = b.osc.torque(b._q, b._v)
            mujoco.mj_step(b.model, b.data)
    np.testing.assert_allclose(a.data.qpos, b.data.qpos, atol=1e-12)
    np.testing.assert_allclose(a.data.qvel, b.data.qvel, atol=1e-9)


def test_arm_holds_still_at_home() -> None:
    sim = ConveyorSimulator()
    sim.reset(object_position=[0.5, -0.45, 0.0825], belt_speed=0.2)
    for _ in range(10):
        sim.step(np.zeros(3), close=False)
    np.testing.assert_allclose(sim.tcp_position(), HOME_TCP_POSITION, atol=1e-6)
    assert np.abs(sim.joint_velocities()[:N_ARM]).max() < 1e-4


def test_orientation_error_map_is_sin_theta_axis() -> None:
    from codesign_mb.robot.osc import _orientation_error_map

    L = _orientation_error_map(GRIPPER_DOWN)
    rng = np.random.default_rng(4)
    for _ in range(10):
        w = rng.normal(size=3) * rng.uniform(0.0, 1.0)
        R = pin.exp3(-w) @ GRIPPER_DOWN  # the reference is reached by rotating w
        theta = np.linalg.norm(w)
        np.testing.assert_allclose(L @ R.ravel(), np.sin(theta) * w / theta, atol=1e-12)


def test_compiled_substeps_equal_the_python_loop() -> None:
    """The numba loop (mj_step1/mj_step2 through ctypes) computes what the Python loop does."""
    from codesign_mb.robot.native import run_substeps

    if run_substeps is None:
        pytest.skip("libmujoco not found next to the bindings")
    a, b = ConveyorSimulator(), ConveyorSimulator(compiled=False)
    for sim in (a, b):
        sim.reset(object_position=[0.5, -0.45, 0.0825], belt_speed=0.2)
    rng = np.random.default_rng(1)
    for k in range(12):
        velocity, close = rng.uniform(-0.4, 0.4, 3), k > 6
        a.step(velocity, close=close)
        b.step(velocity, close=close)
    np.testing.assert_array_equal(a.data.qpos, b.data.qpos)
    np.testing.assert_array_equal(a.data.qvel, b.data.qvel)
    np.testing.assert_array_equal(a.data.ctrl, b.data.ctrl)


def test_leash_kernel_equals_the_numpy_expression() -> None:
    """native.leash_reference is the numpy leash bit for bit (np.dot rounds like e @ e)."""
    from codesign_mb.robot.native import leash_reference

    rng = np.random.default_rng(5)
    moved = 0
    for _ in range(2000):
        refs = rng.normal(size=(20, 6)) * 0.05
        pos, start, max_lag = rng.normal(size=3) * 0.05, int(rng.integers(0, 20)), 0.05
        expected = refs.copy()
        error = expected[start, :3] - pos
        dist = math.sqrt(error @ error)
        if dist > max_lag:
            expected[start:, :3] -= error * (1.0 - max_lag / dist)
            moved += 1
        leash_reference(refs, start, pos, max_lag)
        np.testing.assert_array_equal(refs, expected)
    assert 0 < moved < 2000


def test_operational_space_map_equals_its_formula_and_keeps_no_state() -> None:
    """native.operational_space_map (preallocated workspace) is G = J^T Lambda P + N^T M Q."""
    robot = PandaModel()
    osc = OperationalSpaceController(robot)
    rng = np.random.default_rng(6)
    qs = [robot.neutral() + 0.3 * rng.normal(size=robot.model.nv) for _ in range(3)]
    first = None
    for q in [*qs, qs[0]]:
        osc._update_model(q)
        J = pin.computeFrameJacobian(
            robot.model, robot.data, q, robot.tcp_id, pin.LOCAL_WORLD_ALIGNED
        )
        J, M = J[:, :N_ARM], pin.crba(robot.model, robot.data, q)[:N_ARM, :N_ARM]
        lam = np.linalg.inv(J @ np.linalg.solve(M, J.T))
        expected = J.T @ lam @ osc._P + (M - J.T @ lam @ J) @ osc._Q
        np.testing.assert_allclose(osc._G, expected, rtol=1e-9, atol=1e-9)
        if first is None:
            first = osc._G.copy()
    np.testing.assert_array_equal(osc._G, first)  # the same q again: the same G, bit for bit
