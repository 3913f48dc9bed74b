"""The memoised covariance recursion of IntermittentKalmanFilter equals the plain one, bitwise."""

from __future__ import annotations

import numpy as np

from codesign_mb.estimation.kalman import IntermittentKalmanFilter, _correct, _predict
from codesign_mb.estimation.predictor import constant_velocity_model


class PlainFilter(IntermittentKalmanFilter):
    """The filter without the memo: every update computed with _predict/_correct."""

    def _time_update(self, x, P, A, Q, u):  # type: ignore[no-untyped-def]
        return _predict(x, P, A, Q, self.B, u)

    def _measurement_update(self, x, P, z):  # type: ignore[no-untyped-def]
        return _correct(x, P, z, self.C, self.R, self._eye)


def test_memoised_filter_equals_plain_filter_on_lossy_delayed_streams() -> None:
    A, Q = constant_velocity_model(0.04, 0.5)
    C, R = np.eye(6), np.diag([4e-6] * 3 + [4e-4] * 3)
    P0 = np.diag([0.01] * 3 + [0.25] * 3)
    memo = IntermittentKalmanFilter(A, C, Q, R, max_delay_steps=8)
    plain = PlainFilter(A, C, Q, R, max_delay_steps=8)
    rng = np.random.default_rng(0)
    for episode in range(6):
        q = (1.0, 0.3)[episode % 2]  # repeated patterns (hits) and random ones
        x0 = rng.normal(size=6)
        memo.reset(x0, P0)
        plain.reset(x0, P0)
        for t in range(120):
            if t:
                memo.predict()
                plain.predict()
            if rng.random() < q:
                stamp = max(0, t - int(rng.integers(0, 4)))  # delayed, out of sequence
                z = rng.normal(size=6)
                assert memo.update(z, stamp) == plain.update(z, stamp)
            np.testing.assert_array_equal(memo.x, plain.x)
            np.testing.assert_array_equal(memo.P, plain.P)
    assert len(memo._memo_correct) > 0 and len(memo._memo_predict) > 0


def test_time_varying_model_bypasses_the_memo() -> None:
    A, Q = constant_velocity_model(0.04, 0.5)
    kf = IntermittentKalmanFilter(A, np.eye(6), Q, np.eye(6))
    ref = PlainFilter(A, np.eye(6), Q, np.eye(6))
    for f in (kf, ref):
        f.reset(np.ones(6), np.eye(6))
        f.predict(A=2 * A, Q=3 * Q)
        f.predict()
    np.testing.assert_array_equal(kf.P, ref.P)
    np.testing.assert_array_equal(kf.x, ref.x)
