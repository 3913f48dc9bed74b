"""Property tests of the numerical core (issue 35, item 3), each against theory or an
independent computation.

- The link (``eq_d``, ``eq_time``, ``eq_output``): the age is ``now - capture`` of the packet
  held, that packet is the freshest delivered so far, ``q = 1, tau = 0`` delivers at once,
  the delivery rate of :class:`BernoulliLink` is ``q`` within a binomial bound.
- Kalman and IMM: covariances stay symmetric positive definite, an update never increases
  the covariance (Loewner order), one step equals the textbook equations in numpy, delayed
  and out-of-sequence updates equal filtering the same data in time order, IMM mode
  probabilities stay a distribution.
- RU allocators: every layout is a set of disjoint RUs of the 802.11ax plan inside the
  channel (checked on tone positions, not on the code's bit masks), within the band, and
  only stations with something to send get one.
- Offline LP: its optimum bounds the frames every allocator delivers on the same trace.

``derandomize=True``: the same examples on every machine; the ``slow`` variants run more.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from codesign_mb.estimation.belt_imm import BeltImmPredictor
from codesign_mb.estimation.belt_model import MODES, BeltModel
from codesign_mb.estimation.kalman import IntermittentKalmanFilter
from codesign_mb.network.link import PRIOR_TIMESTAMP, BernoulliLink, ObservationBuffer, Packet
from codesign_mb.network.qos import QosRequest
from codesign_mb.wifi.allocators import TickDemand
from codesign_mb.wifi.cell import WifiLink, generate_trace
from codesign_mb.wifi.config import SCHEDULERS, WifiConfig, make_allocator
from codesign_mb.wifi.offline import offline_optimum
from codesign_mb.wifi.phy import PhyConfig, ru_plan
from codesign_mb.wifi.presets import CHANNEL_PRESETS
from codesign_mb.wifi.sim import Trace, replay


def _settings(max_examples: int) -> settings:
    return settings(
        max_examples=max_examples,
        deadline=None,  # solvers and first calls (numba caches) vary in time
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


PROPERTY = _settings(40)
SOLVER_PROPERTY = _settings(15)
SLOW = _settings(300)

FLOATS = {"allow_nan": False, "allow_infinity": False}


# =========================================================================== link


sends = st.lists(st.tuples(st.integers(0, 6), st.integers(0, 6)), max_size=3)
"""Per step, packets pushed: (how many steps old the packet is, steps until it arrives)."""


def _check_buffer(steps: list[list[tuple[int, int]]], with_prior: bool) -> None:
    buffer = ObservationBuffer([-7.0] if with_prior else None)
    pushed: list[tuple[int, int]] = []  # (timestamp, arrival step)
    held = PRIOR_TIMESTAMP
    for t, step in enumerate(steps):
        for back, delay in step:
            stamp = max(t - back, 0)
            buffer.push(Packet(stamp, np.array([float(stamp)])), t + delay)
            pushed.append((stamp, t + delay))
        rx = buffer.receive(t, delivered=bool(step), like=np.zeros(1))
        freshest = max((s for s, a in pushed if a <= t), default=PRIOR_TIMESTAMP)
        assert freshest >= held  # (the reference itself): what is held never gets older
        held = freshest
        assert rx.age >= 0
        assert rx.age == t - freshest and rx.timestamp == freshest  # eq_time
        if freshest >= 0:
            assert rx.observation.tolist() == [float(freshest)]  # eq_output
        else:
            assert rx.observation.tolist() == ([-7.0] if with_prior else [0.0])
        assert [p.timestamp for p in rx.arrivals] == sorted(s for s, a in pushed if a == t)
        assert buffer.in_flight == sum(a > t for _, a in pushed)


@PROPERTY
@given(steps=st.lists(sends, min_size=1, max_size=30), with_prior=st.booleans())
def test_buffer_holds_the_freshest_packet_delivered_so_far(steps, with_prior):
    """Packets of any age arriving in any order: the buffer holds the one with the largest
    timestamp among those arrived (``eq_time``: a late older packet never replaces a newer
    one), its age is ``t - timestamp >= 0`` and every arrival is reported, in stamp order."""
    _check_buffer(steps, with_prior)


qos_plans = st.lists(
    st.tuples(
        st.one_of(st.sampled_from([0.0, 1.0]), st.floats(0.0, 1.0)),
        st.integers(0, 5),
    ),
    min_size=1,
    max_size=40,
)


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1), plan=qos_plans)
def test_bernoulli_link_age_and_observation_follow_eq_time(seed, plan):
    """Random ``(q_t, tau_t)``: from the link's own ``delta_t`` the age must be
    ``t - max{t' <= t : delta_t' = 1, t' + tau_t' <= t}`` (``t + 1`` before any delivery) and
    the observation the state sent at that ``t'``; ``q = 0`` never, ``q = 1`` always
    delivers; the observation is fresh exactly when its timestamp changed."""
    link = BernoulliLink(seed=seed)
    link.reset(prior=[-1.0, -1.0])
    delivered: list[bool] = []
    before = PRIOR_TIMESTAMP
    for t, (q, tau) in enumerate(plan):
        rx = link.step([float(t), 2.0 * t], QosRequest(q, tau))
        delivered.append(rx.delivered)
        if q == 0.0:
            assert not rx.delivered
        if q == 1.0:
            assert rx.delivered
        stamp = max(
            (s for s in range(t + 1) if delivered[s] and s + plan[s][1] <= t),
            default=PRIOR_TIMESTAMP,
        )
        assert rx.age >= 0 and rx.age == t - stamp
        expected = [-1.0, -1.0] if stamp < 0 else [float(stamp), 2.0 * stamp]
        assert rx.observation.tolist() == expected
        arrived = [s for s in range(t + 1) if delivered[s] and s + plan[s][1] == t]
        assert [p.timestamp for p in rx.arrivals] == arrived
        assert rx.fresh == (stamp != before)
        before = stamp


@PROPERTY
@given(
    states=st.lists(
        hnp.arrays(
            np.float64, st.sampled_from([(1,), (3,), (2, 2)]), elements=st.floats(-1e6, 1e6)
        ),
        min_size=1,
        max_size=20,
    ),
    seed=st.integers(0, 2**32 - 1),
)
def test_a_perfect_link_delivers_every_packet_at_once(states, seed):
    """``q = 1``, ``tau = 0`` (the oracle): every packet is delivered and arrives at its own
    step, so the age is 0 and the observation is the state just sent, of any shape."""
    link = BernoulliLink(seed=seed)
    link.reset(prior=np.full(states[0].shape, 5.0))
    perfect = QosRequest(1.0, 0)
    sent = [x for x in states if x.shape == states[0].shape]
    for x in sent:
        rx = link.step(x, perfect)
        assert rx.delivered and rx.age == 0 and rx.fresh
        assert [p.timestamp for p in rx.arrivals] == [link.t - 1]
        np.testing.assert_array_equal(rx.observation, x)
    assert link.t == len(sent)  # one step per packet sent


N_DRAWS = 2000


@PROPERTY
@given(q=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_bernoulli_delivery_rate_is_q_within_a_binomial_bound(q, seed):
    """``delta_t ~ Bernoulli(q)`` independently (``eq_d``): of 2000 sends the number delivered
    is Binomial(2000, q), within 5 standard deviations (+1 for the lattice) of ``2000 q``
    (a false alarm has probability below 1e-6 per example; the examples are fixed)."""
    link = BernoulliLink(seed=seed)
    link.reset(prior=[0.0])
    qos = QosRequest(q, 0)
    k = sum(link.step([0.0], qos).delivered for _ in range(N_DRAWS))
    sd = math.sqrt(N_DRAWS * q * (1.0 - q))
    assert abs(k - N_DRAWS * q) <= 5.0 * sd + 1.0


@_settings(15)
@given(
    seed=st.integers(0, 2**16),
    plan=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 4)), min_size=1, max_size=25),
)
def test_wifi_link_age_is_the_age_of_the_packet_held(seed, plan):
    """The WiFi station link (a frame needs airtime, so ``tau >= 1``): the age is ``t`` minus
    the capture step of the state held (``t + 1`` on the prior), what is held never gets
    older, and every packet arrives by its own deadline, ``1 <= t - stamp <= tau``, and only
    if it was admitted to the queue (``delta_t``)."""
    link = WifiLink.single(seed=seed)
    link.reset(seed=seed, prior=[-1.0])
    admitted: list[bool] = []
    before = PRIOR_TIMESTAMP
    for t, (q, tau) in enumerate(plan):
        rx = link.step([float(t)], QosRequest(q, tau))
        admitted.append(rx.delivered)
        assert rx.age >= 0
        stamp = t - rx.age
        assert stamp >= before
        before = stamp
        assert rx.observation.tolist() == ([-1.0] if stamp < 0 else [float(stamp)])
        for p in rx.arrivals:
            assert admitted[p.timestamp]
            assert 1 <= t - p.timestamp <= plan[p.timestamp][1]
            assert p.timestamp <= stamp


@pytest.mark.slow
@SLOW
@given(steps=st.lists(sends, min_size=1, max_size=60), with_prior=st.booleans())
def test_buffer_holds_the_freshest_packet_slow(steps, with_prior):
    """:func:`test_buffer_holds_the_freshest_packet_delivered_so_far`, more examples."""
    _check_buffer(steps, with_prior)


# =========================================================================== Kalman


def _spd(draw: st.DrawFn, n: int, floor: float) -> np.ndarray:
    L = draw(hnp.arrays(np.float64, (n, n), elements=st.floats(-1.0, 1.0)))
    return L @ L.T + floor * np.eye(n)


@st.composite
def linear_models(draw: st.DrawFn) -> dict[str, np.ndarray | None]:
    """``x+ = A x + B u + w``, ``z = C x + v``: spectral radius of ``A`` at most 1.05, ``Q``,
    ``R`` and ``P0`` positive definite (so every covariance must be too), ``C`` any."""
    n = draw(st.integers(1, 3))
    p = draw(st.integers(1, n))
    m = draw(st.integers(0, 2))
    A = draw(hnp.arrays(np.float64, (n, n), elements=st.floats(-1.5, 1.5)))
    rho = float(np.max(np.abs(np.linalg.eigvals(A))))
    if rho > 1.05:
        A = A * (1.05 / rho)
    C = draw(hnp.arrays(np.float64, (p, n), elements=st.floats(-2.0, 2.0)))
    B = draw(hnp.arrays(np.float64, (n, m), elements=st.floats(-1.0, 1.0))) if m else None
    Q = _spd(draw, n, draw(st.floats(1e-3, 1.0)))
    R = _spd(draw, p, draw(st.floats(1e-3, 1.0)))
    P0 = _spd(draw, n, draw(st.floats(1e-3, 10.0)))
    x0 = draw(hnp.arrays(np.float64, (n,), elements=st.floats(-10.0, 10.0)))
    return {"A": A, "B": B, "C": C, "Q": Q, "R": R, "P0": P0, "x0": x0}


kalman_ops = st.lists(
    st.one_of(
        st.tuples(st.just("predict"), st.floats(-1.0, 1.0)),
        st.tuples(st.just("update"), st.integers(0, 8), st.floats(-10.0, 10.0)),
    ),
    min_size=1,
    max_size=30,
)
"""Predict steps (an input level) and updates (how many steps old, a measurement level);
the steps without an update are the lost packets."""


def _assert_covariance(P: np.ndarray, *, definite: bool = True) -> None:
    """Symmetric to 1e-9 relative and positive definite (semidefinite, up to rounding,
    when not ``definite``)."""
    assert np.all(np.isfinite(P))
    scale = max(float(np.max(np.abs(P))), 1e-300)
    assert float(np.max(np.abs(P - P.T))) <= 1e-9 * scale
    smallest = float(np.min(np.linalg.eigvalsh(0.5 * (P + P.T))))
    assert smallest > 0.0 if definite else smallest >= -1e-12 * scale


def _loewner_leq(smaller: np.ndarray, larger: np.ndarray) -> bool:
    gap = larger - smaller
    tol = 1e-9 * max(1.0, float(np.max(np.abs(larger))))
    return float(np.min(np.linalg.eigvalsh(0.5 * (gap + gap.T)))) >= -tol


def _textbook_update(x, P, z, C, R):
    """``K = P C' (C P C' + R)^-1``, ``x + K (z - C x)``, ``(I - K C) P``."""
    K = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    return x + K @ (z - C @ x), (np.eye(len(x)) - K @ C) @ P


def _textbook_predict(x, P, A, Q, B, u):
    x = A @ x if B is None else A @ x + B @ u
    return x, A @ P @ A.T + Q


def _run_filter(model, ops, window):
    """Run the ops; check each covariance and each update's shrinkage; return what the
    in-order reference needs."""
    kf = IntermittentKalmanFilter(
        model["A"], model["C"], model["Q"], model["R"], model["B"], max_delay_steps=window
    )
    kf.reset(model["x0"], model["P0"])
    n_in = 0 if model["B"] is None else model["B"].shape[1]
    p = model["C"].shape[0]
    inputs: list[np.ndarray] = []
    measurements: dict[int, list[np.ndarray]] = {}
    for op in ops:
        before = kf.P
        if op[0] == "predict":
            u = np.full(n_in, op[1])
            kf.predict(u if n_in else None)
            inputs.append(u)
        else:
            s = max(kf.t - op[1], 0)
            z = op[2] * np.linspace(1.0, -1.0, p) + 0.1 * s
            oldest = kf.oldest_timestamp
            accepted = kf.update(z, s)
            assert accepted == (s >= oldest)
            if accepted:
                measurements.setdefault(s, []).append(z)
                assert _loewner_leq(kf.P, before)  # information never increases P
            else:
                np.testing.assert_array_equal(kf.P, before)
        _assert_covariance(kf.P)
    return kf, inputs, measurements


@PROPERTY
@given(model=linear_models(), ops=kalman_ops, window=st.integers(0, 5))
def test_kalman_covariance_stays_positive_definite_and_updates_shrink_it(model, ops, window):
    """Any sequence of predictions, lost packets and delayed or out-of-sequence updates:
    ``P`` stays symmetric positive definite (``Q``, ``R``, ``P0`` are), and incorporating a
    measurement never increases it in the Loewner order (at its own step the update
    subtracts ``K S K'``; a delayed one is propagated by the monotone Riccati map); a
    measurement older than the window is refused and leaves ``P`` as it was."""
    _run_filter(model, ops, window)


@PROPERTY
@given(model=linear_models(), ops=kalman_ops, window=st.integers(0, 5))
def test_kalman_out_of_sequence_equals_filtering_in_time_order(model, ops, window):
    """The filter's contract: whatever order the measurements arrive in, the result equals
    the textbook filter (numpy) run over the accepted measurements in time order."""
    kf, inputs, measurements = _run_filter(model, ops, window)
    x, P = model["x0"], model["P0"]
    for k in range(kf.t + 1):
        for z in measurements.get(k, []):
            x, P = _textbook_update(x, P, z, model["C"], model["R"])
        if k < kf.t:
            x, P = _textbook_predict(x, P, model["A"], model["Q"], model["B"], inputs[k])
    scale = max(1.0, float(np.max(np.abs(P))))
    np.testing.assert_allclose(kf.P, P, rtol=1e-6, atol=1e-9 * scale)
    np.testing.assert_allclose(kf.x, x, rtol=1e-6, atol=1e-7 * (1.0 + float(np.max(np.abs(x)))))


@PROPERTY
@given(model=linear_models(), z_level=st.floats(-10.0, 10.0), u_level=st.floats(-1.0, 1.0))
def test_one_kalman_step_is_the_textbook_step(model, z_level, u_level):
    """One update then one prediction against an independent numpy computation of the
    textbook equations (gain with an explicit inverse, ``(I - K C) P``: the filter's Joseph
    form is the same matrix in exact arithmetic)."""
    A, B, C, Q, R = (model[k] for k in ("A", "B", "C", "Q", "R"))
    kf = IntermittentKalmanFilter(A, C, Q, R, B)
    kf.reset(model["x0"], model["P0"])
    z = z_level * np.linspace(1.0, 0.5, C.shape[0])
    kf.update(z, 0)
    x1, P1 = _textbook_update(model["x0"], model["P0"], z, C, R)
    scale = max(1.0, float(np.max(np.abs(P1))))
    np.testing.assert_allclose(kf.P, P1, rtol=1e-8, atol=1e-10 * scale)
    np.testing.assert_allclose(kf.x, x1, rtol=1e-8, atol=1e-9 * (1.0 + float(np.max(np.abs(x1)))))
    u = None if B is None else np.full(B.shape[1], u_level)
    kf.predict(u)
    x2, P2 = _textbook_predict(x1, P1, A, Q, B, u)
    scale = max(1.0, float(np.max(np.abs(P2))))
    np.testing.assert_allclose(kf.P, P2, rtol=1e-8, atol=1e-10 * scale)
    np.testing.assert_allclose(kf.x, x2, rtol=1e-8, atol=1e-9 * (1.0 + float(np.max(np.abs(x2)))))


@pytest.mark.slow
@SLOW
@given(model=linear_models(), ops=kalman_ops, window=st.integers(0, 5))
def test_kalman_out_of_sequence_equals_in_order_slow(model, ops, window):
    """:func:`test_kalman_out_of_sequence_equals_filtering_in_time_order`, more examples."""
    test_kalman_out_of_sequence_equals_filtering_in_time_order.hypothesis.inner_test(
        model, ops, window
    )


# =========================================================================== IMM

IMM_LAYOUT = {"object_pos": slice(0, 3)}

belt_models = st.builds(
    BeltModel,
    control_period_s=st.just(0.04),
    nominal_velocity_mps=st.tuples(st.just(0.0), st.floats(0.0, 0.5), st.just(0.0)),
    accel_std_mps2=st.floats(0.0, 1.0),
    start_speed_std_mps=st.one_of(st.just(0.0), st.floats(1e-3, 0.3)),
    change_probability=st.one_of(st.sampled_from([0.0, 1e-3]), st.floats(0.0, 0.5)),
    stop_fraction=st.one_of(st.sampled_from([0.0, 1.0]), st.floats(0.0, 1.0)),
    restart_probability=st.floats(0.0, 1.0),
    position_noise_std_m=st.floats(1e-4, 0.01),
    bias_std_m=st.one_of(st.just(0.0), st.floats(0.0, 0.01)),
)

point = hnp.arrays(np.float64, (3,), elements=st.floats(-1.0, 1.0))
imm_steps = st.lists(
    st.tuples(
        st.booleans(),  # a new packet held this step
        st.integers(0, 4),  # its age when it becomes the one held
        st.one_of(st.none(), st.just(np.zeros(3)), point),  # a spurious detection there
    ),
    min_size=1,
    max_size=30,
)


def _check_imm(imm: BeltImmPredictor) -> None:
    # A start speed known exactly (std 0) leaves the along-belt velocity of a (re)start
    # without variance: the covariance is then only semidefinite.
    definite = imm.model.start_speed_std_mps > 0
    mu = np.array([imm.mode_probabilities[m] for m in MODES])
    assert np.all(np.isfinite(mu)) and np.all(mu >= 0.0) and np.all(mu <= 1.0)
    assert abs(float(mu.sum()) - 1.0) <= 1e-9
    assert np.all(np.isfinite(imm.state))
    _assert_covariance(imm.covariance, definite=definite)


@PROPERTY
@given(
    model=belt_models,
    start=point,
    stopped=st.floats(0.0, 1.0),
    window=st.integers(1, 6),
    steps=imm_steps,
)
def test_imm_mode_probabilities_stay_a_distribution(model, start, stopped, window, steps):
    """The belt IMM through lost, delayed packets and outliers (a spurious detection, e.g.
    at the origin): the mode probabilities stay in [0, 1] and sum to 1, and the mixture's
    covariance stays symmetric positive definite (each mode's is: ``R``, the prior and the
    noise floors are, unless the start speed is known exactly)."""
    imm = BeltImmPredictor(
        IMM_LAYOUT, model=model, prior_stopped_probability=stopped, max_delay_steps=window
    )
    velocity = np.asarray(model.nominal_velocity_mps) * model.control_period_s
    truth = [start]
    detected = [start]
    imm.reset(np.append(start, 0.0))
    _check_imm(imm)
    stamp = 0
    for t, (fresh, age, outlier) in enumerate(steps, start=1):
        truth.append(truth[-1] + velocity)
        detected.append(truth[-1] if outlier is None else outlier)
        if fresh and t - age > stamp:
            stamp = t - age
        imm.estimate(np.append(detected[stamp], float(t - stamp)), np.zeros(0))
        _check_imm(imm)


# =========================================================================== allocators

N_SD = {26: 24, 52: 48, 106: 102, 242: 234, 484: 468, 996: 980}
"""Data subcarriers of each RU size (IEEE 802.11ax, Table 27-8 to 27-10 of 802.11-2021)."""
RU_COUNT = {
    20: {26: 9, 52: 4, 106: 2, 242: 1},
    40: {26: 18, 52: 8, 106: 4, 242: 2, 484: 1},
    80: {26: 37, 52: 16, 106: 8, 242: 4, 484: 2, 996: 1},
}
"""RUs of each size a channel holds (the standard's RU plan)."""
EDGE = {20: 122, 40: 244, 80: 500}
"""Outermost used subcarrier index of each channel width (DC is 0)."""
FULL_BAND = {20: 242, 40: 484, 80: 996}


def _tones(ranges: tuple[tuple[int, int], ...]) -> set[int]:
    return {k for lo, hi in ranges for k in range(lo, hi + 1)}


def _check_layout(bw: int, layout: np.ndarray, n_stations: int) -> int:
    """An independent [layout] check on tone positions; returns the data subcarriers used."""
    plan = ru_plan(bw)
    layout = np.asarray(layout)
    assert layout.shape == (n_stations,)
    assert np.issubdtype(layout.dtype, np.integer)
    used: set[int] = set()
    data = 0
    for r in layout.tolist():
        if r == -1:
            continue
        assert 0 <= r < len(plan.units)
        ru = plan.units[r]
        tones = _tones(ru.tone_ranges)
        assert ru.tones in RU_COUNT[bw] and len(tones) == ru.tones
        assert 0 not in tones and max(abs(k) for k in tones) <= EDGE[bw]  # inside the channel
        assert not tones & used  # no overlap
        used |= tones
        data += N_SD[ru.tones]
    assert data <= N_SD[FULL_BAND[bw]]  # never more than the band
    assert plan.is_valid_layout(layout)  # the code's own checker agrees
    return data


@pytest.mark.parametrize("bw", sorted(RU_COUNT))
def test_ru_plan_is_the_standards(bw):
    """The RU plan the checker reads: the standard's RU counts, each RU its tone count, the
    RUs of one size disjoint and inside the channel, every RU inside the full-band one."""
    plan = ru_plan(bw)
    assert {t: plan.count(t) for t in plan.sizes} == RU_COUNT[bw]
    full = _tones(plan.of_size(FULL_BAND[bw])[0].tone_ranges)
    for size in plan.sizes:
        seen: set[int] = set()
        for ru in plan.of_size(size):
            tones = _tones(ru.tone_ranges)
            assert len(tones) == size and not tones & seen and tones <= full
            seen |= tones
    assert max(abs(k) for k in full) == EDGE[bw]


MAX_STATIONS = 12


@st.composite
def demands(draw: st.DrawFn) -> TickDemand:
    """A tick's demand: idle stations, stations out of rate (``e = 0``), small and huge
    frames, tight and loose deadlines, optional frame values."""
    n = draw(st.integers(1, MAX_STATIONS))
    backlog = np.array(
        draw(st.lists(st.one_of(st.just(0.0), st.floats(1.0, 400_000.0)), min_size=n, max_size=n))
    )
    share = np.array(draw(st.lists(st.floats(1e-3, 1.0), min_size=n, max_size=n)))
    slack = np.array(draw(st.lists(st.integers(1, 40), min_size=n, max_size=n)), dtype=float)
    rates = st.sampled_from([0.0, 6.0, 12.0, 24.0, 48.0, 100.0, 200.0, 400.0])
    e = np.array(draw(st.lists(rates, min_size=n, max_size=n)))
    weights = draw(st.one_of(st.none(), st.lists(st.floats(0.1, 10.0), min_size=n, max_size=n)))
    return TickDemand(
        backlog, backlog * share, slack, e, None if weights is None else np.array(weights)
    )


@functools.cache
def _allocator(bw: int, kind: str):
    return make_allocator(WifiConfig(phy=PhyConfig(bandwidth_mhz=bw)), MAX_STATIONS, kind)


def _check_allocators(bw: int, demand: TickDemand) -> None:
    idle = (demand.backlog_bits <= 0) | (demand.bits_per_subcarrier <= 0)
    for kind in SCHEDULERS:
        layout = _allocator(bw, kind).allocate(demand)
        _check_layout(bw, layout, demand.n_stations)
        assert np.all(layout[idle] == -1), kind  # nothing to send (or no rate): no RU


@PROPERTY
@given(bw=st.sampled_from(sorted(RU_COUNT)), demand=demands())
def test_every_allocator_returns_a_valid_layout_within_the_band(bw, demand):
    """Every registered allocator, random demands and channel states: disjoint RUs of the
    802.11ax plan inside the channel, at most the full band's data subcarriers, and no RU
    for a station with nothing to send or no rate."""
    _check_allocators(bw, demand)


@pytest.mark.slow
@SLOW
@given(bw=st.sampled_from(sorted(RU_COUNT)), demand=demands())
def test_every_allocator_returns_a_valid_layout_slow(bw, demand):
    """:func:`test_every_allocator_returns_a_valid_layout_within_the_band`, more examples."""
    _check_allocators(bw, demand)


# =========================================================================== offline LP

REPLAYED = ("greedy", "greedy-admit", "convex", "tick-optimal")


@st.composite
def generated_traces(draw: st.DrawFn) -> Trace:
    """The family of ``tests/test_offline_windows.py``: a preset cell, 2-12 robots, a few
    steps, static ``q`` and ``tau`` (light to overloaded)."""
    return generate_trace(
        CHANNEL_PRESETS[draw(st.sampled_from(["paper", "better"]))],
        draw(st.integers(2, 12)),
        steps=draw(st.integers(2, 4)),
        reliability=draw(st.floats(0.05, 1.0)),
        latency_steps=draw(st.integers(1, 2)),
        seed=draw(st.integers(0, 10_000)),
    )


@st.composite
def drawn_traces(draw: st.DrawFn) -> Trace:
    """Hand-made traces: rates changing per tick and per station (MCS 0 to 11, one or two
    streams), frames of random sizes, lifetimes (some too short to make it) and fates."""
    n = draw(st.integers(1, 5))
    horizon = draw(st.integers(8, 60))
    rates = st.sampled_from([0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.666667, 8.333333, 16.666667])
    ul = np.empty((n, horizon))
    dl = np.empty((n, horizon))
    for m in (ul, dl):
        for i in range(n):
            cut = draw(st.integers(0, horizon))
            m[i, :cut], m[i, cut:] = draw(rates), draw(rates)
    rows = draw(
        st.lists(
            st.tuples(
                st.integers(0, n - 1),
                st.integers(0, horizon - 2),
                st.integers(1, 50),
                st.integers(1_000, 150_000),
                st.integers(100, 5_000),
                st.sampled_from([1, 1, 1, 0]),
                st.sampled_from([1, 1, 1, 0]),
            ),
            max_size=12,
        )
    )
    rows.sort(key=lambda r: (r[0], r[1]))
    step = [sum(1 for q in rows[:j] if q[0] == r[0]) for j, r in enumerate(rows)]
    frames = pd.DataFrame(
        {
            "station": [r[0] for r in rows],
            "step": step,
            "capture_tick": [r[1] for r in rows],
            "deadline_tick": [min(r[1] + r[2], horizon) for r in rows],
            "ul_bits": [r[3] for r in rows],
            "dl_bits": [r[4] for r in rows],
            "ul_ok": [r[5] for r in rows],
            "dl_ok": [r[6] for r in rows],
        },
        columns=list(Trace.COLUMNS),
        dtype=np.int64,
    )
    return Trace(CHANNEL_PRESETS["paper"], horizon, ul, dl, frames)


def _check_bound(trace: Trace) -> None:
    bound = offline_optimum(trace, solver="highs")
    assert bound.status == "optimal", bound.status
    f = trace.frames
    deliverable = ((f["ul_ok"] != 0) & (f["dl_ok"] != 0)).to_numpy()
    assert -1e-6 <= bound.optimum <= deliverable.sum() + 1e-6
    per_station = np.bincount(f["station"][deliverable], minlength=trace.n_stations)
    bw = trace.config.phy.bandwidth_mhz
    for kind in REPLAYED:
        result = replay(trace, kind, record_layouts=True)
        assert result.delivered <= bound.optimum + 1e-6, (kind, result.delivered, bound.optimum)
        s = result.summary
        assert np.all(s["delivered"].to_numpy() <= per_station)  # only what was sent
        assert np.all(s["delivered"] + s["late"] + s["lost"] == s["frames"])
        assert s["frames"].sum() == len(f)
        for _, _, layout in result.layouts or []:
            _check_layout(bw, layout, trace.n_stations)


@SOLVER_PROPERTY
@given(trace=generated_traces())
def test_offline_optimum_bounds_every_allocator_on_generated_traces(trace):
    """[lp] relaxes every schedule the simulator can run (module docstring of
    ``codesign_mb.wifi.offline``), so its optimum is >= the frames each allocator delivers in
    time on the same trace (and <= the frames both hops deliver); each replay's layouts are
    valid and a station gets delivered at most the frames it sent."""
    _check_bound(trace)


@SOLVER_PROPERTY
@given(trace=drawn_traces())
def test_offline_optimum_bounds_every_allocator_on_drawn_traces(trace):
    """:func:`test_offline_optimum_bounds_every_allocator_on_generated_traces` on traces the
    cell would not generate: rates that change every few ticks, frames of any size and
    lifetime, lost hops."""
    _check_bound(trace)


@pytest.mark.slow
@_settings(100)
@given(trace=st.one_of(generated_traces(), drawn_traces()))
def test_offline_optimum_bounds_every_allocator_slow(trace):
    """The two bounds above, more examples."""
    _check_bound(trace)
