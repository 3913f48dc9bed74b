"""One rollout function composing plant, link, QoS policy, estimator and controller."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.control.base import Controller
from codesign_mb.estimation.base import Estimator
from codesign_mb.network.wrapper import LinkObservationWrapper

__all__ = ["rollout"]

_RECORDED = (
    "qos_reliability",
    "qos_latency_steps",
    "qos_cost",
    "delivered",
    "age",
)


def rollout(
    env: LinkObservationWrapper,
    estimator: Estimator,
    controller: Controller,
    *,
    seed: int,
    max_steps: int | None = None,
) -> pd.DataFrame:
    """Run one seeded episode and return its per-step record (one row per control step).

    The data flow of one step is DESIGN.md's: the QoS policy and the link live in ``env``
    (a :class:`LinkObservationWrapper`); the robot computes ``x_hat_t = estimator(y_t, zeta_t)``
    and ``u_t = controller(x_hat_t)`` (``eq_c_pol2``). Columns: ``t``, ``reward``, the QoS
    request and its cost, ``delivered``, ``age``, ``estimation_error`` (norm of the remote
    estimate minus the truth), and every scalar entry of the plant's ``info`` (e.g. ``success``).
    Row ``t`` holds the action taken at ``t`` and what followed it; the QoS columns describe
    the packet that produced the observation acted on.
    """
    obs, info = env.reset(seed=seed)
    controller.reset(seed=seed)
    estimate = estimator.reset(obs)
    remote = env.remote_slice
    rows: list[dict[str, Any]] = []
    t = 0
    while max_steps is None or t < max_steps:
        action = np.asarray(controller.act(estimate))
        row: dict[str, Any] = {"t": t}
        row.update({k: info[k] for k in _RECORDED})
        row["estimation_error"] = float(
            np.linalg.norm(np.asarray(estimate)[remote] - info["remote_true"])
        )
        obs, reward, terminated, truncated, info = env.step(action)
        row["reward"] = float(reward)
        row.update(
            {
                k: v
                for k, v in info.items()
                if k not in row
                and k not in _RECORDED
                and np.ndim(v) == 0
                and not isinstance(v, str)
            }
        )
        rows.append(row)
        t += 1
        if terminated or truncated:
            break
        estimate = estimator.estimate(obs, action)
    return pd.DataFrame(rows)
