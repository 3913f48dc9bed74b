"""The model-based QoS planner: when it asks, against the covariance recursion it plans with."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from codesign_mb.adaptation.planner import REASONS, QosPlanner
from codesign_mb.estimation.belt_imm import BeltImmPredictor
from codesign_mb.estimation.belt_model import BeltModel
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.qos import QosRequest
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.toy import ToyConveyor

DT = 0.04
LAYOUT = {"gripper_pos": slice(0, 3), "object_pos": slice(3, 6)}
MODEL = BeltModel(DT, nominal_velocity_mps=(0.0, 0.3, 0.0), position_noise_std_m=0.002)


def _planner(**options: object) -> QosPlanner:
    replica = BeltImmPredictor(LAYOUT, model=MODEL, prior_position_std_m=0.02)
    return QosPlanner(replica, LAYOUT, **options)  # type: ignore[arg-type]


def _held(gripper: list[float], obj: list[float]) -> np.ndarray:
    return np.array(gripper + obj, dtype=float)


def test_asks_until_the_first_packet_then_waits_for_the_grasp() -> None:
    """Far from the object and certain of it, nothing is asked; close to the grasp with an
    uncertainty above the tolerance, a packet is."""
    planner = _planner(grasp_std_m=0.01)
    planner.reset()
    far = [0.5, -0.4, 0.3]
    obj = [0.5, 0.1, 0.02]
    assert planner.request(_held(far, obj), 0).reliability == 1.0  # t = 0: the prior
    assert planner.request(_held(far, obj), 1).reliability == 1.0  # nothing measured yet
    asked = []
    for t in range(2, 6):  # packets of every step arrive, one step late
        obj = [0.5, 0.1 + 0.3 * DT * (t - 1), 0.02]
        asked.append(planner.request(_held(far, obj), 1).reliability)
    assert asked[-1] == 0.0  # 50 cm away, the object known: the grasp is far, wait
    assert planner.grasp_steps(_held(far, obj)) > 10
    for age in range(2, 12):  # no packet for a while; the gripper over the estimate
        above = (planner.replica.state[:3] + np.array([0.0, 0.0, 0.005])).tolist()
        q = planner.request(_held(above, obj), age).reliability
        if planner.replica.position_std_ahead(2) > 0.01:  # the std the packet would meet
            assert q == 1.0
            break
    else:
        pytest.fail("the uncertainty never grew beyond the tolerance")


def test_the_cheapest_schedule_meets_the_grasp_tolerance() -> None:
    """When the planner waits, some schedule of later packets meets the tolerance on the
    covariance recursion of the model (an independent recursion over every schedule); when
    no schedule without the current step does, it asks now."""
    planner = _planner(grasp_std_m=0.006)
    planner.reset()
    gripper = [0.5, -0.05, 0.09]  # a few steps from the grasp: every schedule can be listed
    obj = [0.5, 0.0, 0.02]
    planner.request(_held(gripper, obj), 0)
    planner.request(_held(gripper, obj), 0)  # the first packet, at t = 0
    replica = planner.replica
    A, Q = MODEL.average_dynamics(np.array(list(replica.mode_probabilities.values())))
    H, R = MODEL.measurement(velocity=False)
    steps = planner.grasp_steps(_held(gripper, obj))
    last = steps - planner.latency_steps

    def std(schedule: tuple[int, ...]) -> float:
        P = replica.covariance
        for k in range(1, steps + 1):
            P = A @ P @ A.T + Q
            if k in schedule:
                S = H @ P @ H.T + R
                P = P - P @ H.T @ np.linalg.solve(S, H @ P)
        return math.sqrt(P[0, 0] + P[1, 1])  # lateral

    later = range(2, last + 1)
    assert len(later) <= 12
    feasible_later = [
        s for m in range(len(later) + 1) for s in itertools.combinations(later, m)
        if std(s) <= 0.006
    ]  # fmt: skip
    asks = planner._needed(_held(gripper, obj))
    if not feasible_later:
        assert asks
    else:
        fewest = min(len(s) for s in feasible_later)
        with_now = min(
            (len(s) + 1 for m in range(len(later) + 1)
             for s in itertools.combinations(later, m) if std((1, *s)) <= 0.006),
            default=math.inf,
        )  # fmt: skip
        # The planner's restricted search asks only when now makes it cheaper.
        assert not asks or with_now <= fewest
        assert std(tuple(later)[len(later) - fewest :]) <= 0.006 or asks


def test_nothing_is_asked_for_a_carried_object() -> None:
    layout = {
        "gripper_pos": slice(0, 3), "finger_width": slice(3, 4), "object_pos": slice(4, 7)
    }  # fmt: skip
    replica = BeltImmPredictor(layout, model=MODEL, prior_position_std_m=0.01)
    planner = QosPlanner(replica, layout, grasp_std_m=0.001)
    planner.reset()
    gripper, obj = [0.5, 0.0, 0.03], [0.5, 0.0, 0.02]
    planner.request(np.array([*gripper, 0.08, *obj]), 0)
    for _ in range(3):
        q = planner.request(np.array([*gripper, 0.045, *obj]), 1)
    assert replica.carried and q.reliability == 0.0


class _Recorder:
    """A policy that keeps what it is given."""

    reads_robot_state = True

    def __init__(self) -> None:
        self.seen: list[np.ndarray] = []

    def reset(self, *, seed: int | None = None) -> None:
        self.seen.clear()

    def request(self, observation: np.ndarray, age: int) -> QosRequest:
        self.seen.append(np.array(observation))
        return QosRequest(1.0, 1)


def test_a_policy_reading_the_robot_state_gets_the_whole_held_observation() -> None:
    """``reads_robot_state``: the robot's state at ``t - 1`` with ``y_{t-1}`` (what it held),
    not only the remote part."""
    policy = _Recorder()
    env = LinkObservationWrapper(ToyConveyor(), BernoulliLink(), policy)
    obs, _ = env.reset(seed=0)
    outputs = [obs]
    for _ in range(3):
        obs, *_ = env.step(env.action_space.sample())
        outputs.append(obs)
    assert len(policy.seen) == 4
    for seen, held in zip(policy.seen[1:], outputs[:-1], strict=True):
        np.testing.assert_array_equal(seen, held[:-1])  # the observation without its age


def test_episode_metrics_count_each_high_request_under_its_reason() -> None:
    """The per-reason counts add up to the requests that asked ``high``, each under the
    reason the planner gave for it, and start from zero each episode."""
    planner = _planner(grasp_std_m=0.01, far_std_m=0.02)
    far, obj = [0.5, -0.4, 0.3], [0.5, 0.1, 0.02]
    for _episode in range(2):
        planner.reset()
        expected = dict.fromkeys(REASONS, 0)
        for t in range(12):
            age = 1 if t < 4 else t - 2  # packets until t = 3, then none
            obj = [0.5, 0.1 + 0.3 * DT * t, 0.02]
            request = planner.request(_held(far, obj), age)
            assert (request.reliability > 0) == (planner.reason is not None)
            if planner.reason is not None:
                expected[planner.reason] += 1
        counts = planner.episode_metrics()
        assert counts == {f"qos_asked_{r.replace(' ', '_')}": float(n) for r, n in expected.items()}
        assert counts["qos_asked_nothing_measured_yet"] == 2.0  # t = 0 and t = 1
        assert counts["qos_asked_far"] > 0  # the uncertainty outgrows far_std_m without packets


def test_closing_packets_only_while_the_fingers_can_still_reopen() -> None:
    """Fingers closing over the object, no packet arriving: the planner asks ("closing")
    while they are wider than ``closing_useful_width_m``; narrower, a packet would come when
    they are on the object already, and nothing is asked; without the option it asks on."""
    layout = {
        "gripper_pos": slice(0, 3), "finger_width": slice(3, 4), "object_pos": slice(4, 7)
    }  # fmt: skip

    def reasons(useful: float) -> list[tuple[float, str | None]]:
        replica = BeltImmPredictor(layout, model=MODEL, prior_position_std_m=0.01)
        planner = QosPlanner(replica, layout, grasp_std_m=0.01, closing_std_m=0.004,
                             closing_useful_width_m=useful)  # fmt: skip
        planner.reset()
        obj = [0.5, 0.0, 0.02]
        planner.request(np.array([*obj[:2], 0.03, 0.08, *obj]), 0)
        for _ in range(3):  # measured, the gripper over it
            planner.request(np.array([*obj[:2], 0.03, 0.08, *obj]), 1)
        seen = []
        for age, width in enumerate((0.074, 0.066, 0.058, 0.050), start=2):  # no packet
            over = replica.state[:3] + np.array([0.0, 0.0, 0.005])
            planner.request(np.array([*over, width, *obj]), age)
            seen.append((width, planner.reason))
        return seen

    assert [r for _, r in reasons(0.0)] == ["closing"] * 4
    assert reasons(0.06) == [(0.074, "closing"), (0.066, "closing"), (0.058, None), (0.05, None)]
