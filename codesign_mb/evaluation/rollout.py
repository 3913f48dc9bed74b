"""One rollout function composing plant, link, QoS policy, estimator and controller."""

from __future__ import annotations

import math
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
    record = _Record()
    t = 0
    while max_steps is None or t < max_steps:
        action = np.asarray(controller.act(estimate))
        error = np.asarray(estimate)[remote] - info["remote_true"]
        head = [info[k] for k in _RECORDED]
        head.append(math.sqrt(error.dot(error)))  # the norm of the estimation error
        obs, reward, terminated, truncated, info = env.step(action)
        record.append(t, head, float(reward), info)
        t += 1
        if terminated or truncated:
            break
        estimate = estimator.estimate(obs, action)
    return record.frame()


_HEAD = ("t", *_RECORDED, "estimation_error", "reward")
_SCALARS = (bool, int, float, np.bool_, np.float64, np.int64)
"""Types whose values are recorded without asking ``np.ndim`` (0-d by construction)."""


class _Record:
    """The per-step rows of :func:`rollout`, kept as columns (one DataFrame at the end).

    A row is ``t``, the QoS columns, ``estimation_error``, ``reward`` and every scalar,
    non-string ``info`` entry not among them. While every step has the same ``info`` columns
    the values go straight into lists; otherwise the rows fall back to dicts, which pandas
    aligns (a missing entry is NaN) as before.
    """

    def __init__(self) -> None:
        self.keys: tuple[str, ...] | None = None
        self.columns: list[list[Any]] = []
        self.rows: list[dict[str, Any]] | None = None

    def append(self, t: int, head: list[Any], reward: float, info: dict[str, Any]) -> None:
        keys = []
        values: list[Any] = [t, *head, reward]
        for k, v in info.items():
            if k in _HEAD:
                continue
            if type(v) in _SCALARS or (np.ndim(v) == 0 and not isinstance(v, str)):
                keys.append(k)
                values.append(v)
        if self.keys is None and self.rows is None:
            self.keys = tuple(keys)
            self.columns = [[] for _ in range(len(values))]
        if self.rows is None and tuple(keys) != self.keys:
            self.rows = self._as_rows()
        if self.rows is not None:
            self.rows.append(dict(zip((*_HEAD, *keys), values, strict=True)))
            return
        for column, value in zip(self.columns, values, strict=True):
            column.append(value)

    def _as_rows(self) -> list[dict[str, Any]]:
        names = (*_HEAD, *(self.keys or ()))
        return [dict(zip(names, row, strict=True)) for row in zip(*self.columns, strict=True)]

    def frame(self) -> pd.DataFrame:
        if self.rows is not None:
            return pd.DataFrame(self.rows)
        if self.keys is None:
            return pd.DataFrame([])
        names = (*_HEAD, *self.keys)
        return pd.DataFrame(dict(zip(names, self.columns, strict=True)))
