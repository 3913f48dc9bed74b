"""The one closed loop: plant behind its link, estimator, controller, QoS policy; per-step record.

:mod:`~codesign_mb.rollout.compose` holds the compositions that need two of the sibling
layers at once (a QoS rule on a predictor replica, LQG = LQR + Kalman filter).
"""

from codesign_mb.rollout.loop import ClosedLoop, Transition, rollout, rollout_shared

__all__ = ["ClosedLoop", "Transition", "rollout", "rollout_shared"]
