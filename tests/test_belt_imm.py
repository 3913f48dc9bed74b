"""The belt-aware IMM predictor against a Kalman filter, its own model's data, and the gripper."""

from __future__ import annotations

import numpy as np
import pytest

from codesign_mb.estimation.belt_imm import BeltImmPredictor
from codesign_mb.estimation.belt_model import MODES, BeltModel
from codesign_mb.estimation.kalman import IntermittentKalmanFilter

DT = 0.04
LAYOUT = {"object_pos": slice(0, 3)}


def _wrapped(z: np.ndarray, age: int) -> np.ndarray:
    return np.append(z, float(age))


def test_one_mode_is_the_kalman_filter_through_loss_and_delay() -> None:
    """With no mode switch possible the IMM is one Kalman filter on (o, w, b): equal to the
    tested intermittent filter, fed the same lost and delayed packets."""
    model = BeltModel(
        DT, nominal_velocity_mps=(0.0, 0.3, 0.0), change_probability=0.0, bias_std_m=0.002,
        position_noise_std_m=0.003,
    )  # fmt: skip
    imm = BeltImmPredictor(LAYOUT, model=model, prior_position_std_m=(0.02, 0.03, 0.004))
    rng = np.random.default_rng(3)
    truth = np.cumsum(np.tile([0.0, 0.3 * DT, 0.0], (40, 1)), axis=0)
    ages = [0, 1, 1, 2, 3, 1, 1, 1, 4, 5, 1, 2, 1, 1, 1] + [1] * 25
    held = truth[0] + rng.normal(0, 0.003, 3)
    imm.reset(_wrapped(held, 0))
    A, _, Q = model.dynamics()
    H, R = model.measurement(velocity=False)
    kf = IntermittentKalmanFilter(A[0], H, Q[0], R, max_delay_steps=64)
    x0 = np.concatenate([held, model.nominal_velocity_mps, np.zeros(3)])
    P0 = np.zeros((9, 9))
    P0[:3, :3] = np.diag([0.02**2, 0.03**2, 0.004**2])
    P0[3:6, 3:6] = np.diag([0.01**2, model.start_speed_std_mps**2, 0.01**2])
    P0[6:, 6:] = 0.002**2 * np.eye(3)
    kf.reset(x0, P0)
    kf.update(held, 0)
    packets = {t: truth[t] + rng.normal(0, 0.003, 3) for t in range(40)}
    last = 0
    for t in range(1, 40):
        stamp = t - ages[t]
        z = packets[stamp] if stamp > last else held
        kf.predict()
        if stamp > last:
            kf.update(z, stamp)
            last, held = stamp, z
        imm.estimate(_wrapped(held, t - last), np.zeros(0))
        np.testing.assert_allclose(imm.state, kf.x, atol=1e-9)
        np.testing.assert_allclose(imm.covariance, kf.P, atol=1e-12)


def test_nees_on_data_of_its_own_model_is_chi_square() -> None:
    """On belts drawn from the switching model (runs, speed steps, stops, restarts, bias), the
    average NEES of the position lies near its 3 degrees of freedom (an IMM's moment-matched
    Gaussian is an approximation: a loose band)."""
    model = BeltModel(
        DT, nominal_velocity_mps=(0.0, 0.35, 0.0), change_probability=0.05, stop_fraction=0.2,
        restart_probability=0.08, position_noise_std_m=0.003, bias_std_m=0.002,
        start_speed_std_mps=0.1,
    )  # fmt: skip
    A, c, Q = model.dynamics()
    Pi = model.transitions
    rng = np.random.default_rng(0)
    values = []
    for _ in range(60):
        imm = BeltImmPredictor(LAYOUT, model=model, prior_position_std_m=0.01)
        x = np.zeros(9)
        x[:3] = rng.normal(0, 0.01, 3)
        x[3:6] = model.nominal_velocity_mps + np.array([0, rng.normal(0, 0.1), 0])
        x[6:] = rng.normal(0, 0.002, 3)
        mode = 0
        z = x[:3] + x[6:] + rng.normal(0, 0.003, 3)
        imm.reset(_wrapped(z, 0))  # the first packet, at t = 0
        held, last = z, 0
        for t in range(1, 60):
            mode = rng.choice(4, p=Pi[mode])
            x = A[mode] @ x + c[mode] + rng.multivariate_normal(np.zeros(9), Q[mode])
            if rng.random() < 0.5:  # delivered with one step of latency
                held, last = x[:3] + x[6:] + rng.normal(0, 0.003, 3), t
            imm.estimate(_wrapped(held, t - last), np.zeros(0))
            if t > 5:
                e = imm.state[:3] - x[:3]
                values.append(float(e @ np.linalg.solve(imm.covariance[:3, :3], e)))
    assert 2.4 < np.mean(values) < 3.8


def test_a_stop_is_found_from_positions_alone() -> None:
    model = BeltModel(DT, nominal_velocity_mps=(0.0, 0.3, 0.0), position_noise_std_m=0.001)
    imm = BeltImmPredictor(LAYOUT, model=model, prior_position_std_m=0.01)
    imm.reset(_wrapped(np.zeros(3), 0))
    position = np.zeros(3)
    for t in range(1, 40):
        if t < 20:
            position = position + np.array([0.0, 0.3 * DT, 0.0])
        imm.estimate(_wrapped(position, 0), np.zeros(0))
        if t == 15:
            assert imm.mode_probabilities["run"] > 0.9
            assert imm.state[4] == pytest.approx(0.3, abs=0.02)
    assert imm.mode_probabilities["stop"] > 0.9
    assert abs(imm.state[4]) < 0.05  # the mixture: a little weight left on moving modes
    assert set(imm.mode_probabilities) == set(MODES)


def _over_the_object() -> tuple[BeltImmPredictor, np.ndarray, np.ndarray]:
    """An IMM whose layout has the gripper and the fingers, the gripper just over the object."""
    layout = {
        "gripper_pos": slice(0, 3), "finger_width": slice(3, 4), "object_pos": slice(4, 7)
    }  # fmt: skip
    model = BeltModel(DT, nominal_velocity_mps=(0.0, 0.3, 0.0))
    imm = BeltImmPredictor(layout, model=model, prior_position_std_m=0.01)
    return imm, np.array([0.5, 0.0, 0.03]), np.array([0.5, 0.0, 0.02])


def test_a_carried_object_follows_the_gripper() -> None:
    """Held (fingers closed at an object's width), the object moves as the gripper does."""
    imm, gripper, obj = _over_the_object()
    obs = np.concatenate([gripper, [0.08], obj])
    imm.reset(_wrapped(obs, 0))
    closed = np.array([0.0, 0.0, 0.0, 1.0])
    for _ in range(1, 4):  # closing on the object: width settles at 4.5 cm
        obs = np.concatenate([gripper, [0.045], obj])
        imm.estimate(_wrapped(obs, 0), closed)
    assert imm.carried
    start = imm.state[:3].copy()
    for t in range(4, 10):  # lifted without packets (age grows)
        gripper = gripper + np.array([0.0, 0.0, 0.02])
        obs = np.concatenate([gripper, [0.045], obj])
        imm.estimate(_wrapped(obs, t - 3), closed)
    np.testing.assert_allclose(imm.state[:3] - start, [0.0, 0.0, 0.12], atol=1e-9)
    assert imm.position_std < 0.02


def test_the_likeliest_velocity_is_the_stopped_belt_s_while_the_mixture_creeps() -> None:
    """A stopped belt with no packet for a few steps: the mixture's velocity creeps towards a
    restart (a likely STOP, an unlikely START at the nominal speed), the most probable mode's
    stays at rest; position and covariance are the mixture's in both outputs."""
    model = BeltModel(DT, nominal_velocity_mps=(0.0, 0.6, 0.0), position_noise_std_m=0.001)
    layout = {"object_pos": slice(0, 3)}
    out = {}
    for choice in ("mixture", "likeliest"):
        imm = BeltImmPredictor(
            layout, model=model, prior_position_std_m=0.01, output_velocity=True,
            velocity_output=choice,
        )  # fmt: skip
        imm.reset(_wrapped(np.zeros(3), 0))
        for _ in range(1, 20):  # at rest, seen every step
            imm.estimate(_wrapped(np.zeros(3), 0), np.zeros(0))
        for age in range(1, 5):  # then no packet
            y = imm.estimate(_wrapped(np.zeros(3), age), np.zeros(0))
        assert imm.mode_probabilities["stop"] > 0.5
        out[choice] = (y, imm.state.copy())
    mixture, likeliest = out["mixture"], out["likeliest"]
    assert mixture[0][4] > 0.03  # the mixture's velocity output creeps
    assert likeliest[0][4] == pytest.approx(0.0, abs=1e-3)  # STOP's
    np.testing.assert_allclose(mixture[0][:3], likeliest[0][:3])  # same position
    np.testing.assert_allclose(mixture[1], likeliest[1])  # same mixture state (NEES)
    with pytest.raises(ValueError, match="velocity_output must be"):
        BeltImmPredictor(layout, model=model, velocity_output="mode")


def test_reopening_fingers_carry_nothing_even_for_an_edge_replica() -> None:
    """The edge's replica does not see the grip command: fingers that reverse after a close
    (width growing by 1.5 mm, then more) are not taken for a held object."""
    imm, gripper, obj = _over_the_object()
    imm.reset(_wrapped(np.concatenate([gripper, [0.08], obj]), 0))
    carried = []
    for width in (0.066, 0.058, 0.050, 0.045, 0.0465, 0.054, 0.062):  # closes, then reopens
        imm.estimate(_wrapped(np.concatenate([gripper, [width], obj]), 0), np.zeros(0))
        carried.append(imm.carried)
    assert not any(carried)
    for _ in range(3):  # closed on the object: steady at its width
        imm.estimate(_wrapped(np.concatenate([gripper, [0.044], obj]), 0), np.zeros(0))
    assert imm.carried
