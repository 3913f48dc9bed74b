"""The one closed loop: plant behind its link, estimator, controller, QoS policy; per-step record.

:mod:`~codesign_mb.rollout.compose` holds the compositions that need two of the sibling
layers at once (a QoS rule on a predictor replica, LQG = LQR + Kalman filter);
:mod:`~codesign_mb.rollout.kinds` registers those of them that are QoS kinds. The loop is
imported when first named, so registering the kinds loads no estimator.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from codesign_mb.rollout.loop import ClosedLoop, Transition, rollout, rollout_shared

__all__ = ["ClosedLoop", "Transition", "rollout", "rollout_shared"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        return getattr(importlib.import_module("codesign_mb.rollout.loop"), name)
    raise AttributeError(f"module 'codesign_mb.rollout' has no attribute {name!r}")
