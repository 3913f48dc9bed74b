"""Per-step estimation error of the object the controller acts on, by phase, and its NEES.

Recorded by :class:`~codesign_mb.rollout.loop.ClosedLoop` for a plant whose remote part holds
``object_pos`` and whose ``info`` reports the episode's ``phase``
(:mod:`codesign_mb.plants.phases`; the conveyor): per step, from the ``info`` the estimate
was made at,

``phase``
    The step's phase (an index into :data:`~codesign_mb.plants.phases.PHASES`, -1 before the
    object spawned).
``position_error_m``
    ``|o_hat - o|``: the object position the controller is given (the estimator's output: the
    held stale observation for ``none``, the prediction for the predictor, a network's
    output) minus the true one (``info["remote_true"]``), m.
``nees_position``, ``nees_state``
    With an estimator exposing its Gaussian (``state`` and ``covariance`` over the object's
    position then velocity, :func:`~codesign_mb.estimation.consistency.has_covariance`): the
    NEES of its position (3 degrees of freedom) and, when the plant gives the true velocity
    (in the remote state, or ``info["object_vel"]``), of its position and velocity (6).

The step keeps references to the arrays it is given (the remote error, ``info``'s truth, the
estimator's ``state`` and ``covariance``, all fresh arrays each step, never modified later)
and the errors and NEES are computed for the whole episode at the end, batched: a step costs
a few list appends and, with a covariance, the estimator's copies.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.estimation.consistency import has_covariance, nees

__all__ = ["ObjectErrors"]


class ObjectErrors:
    """The object's per-step estimation errors of one closed loop (see the module docstring).

    Parameters
    ----------
    position:
        Where ``object_pos`` is in the remote part (``info["remote_true"]``).
    velocity:
        Where ``object_vel`` is in the remote part, if it is perceived.
    estimator:
        The loop's estimator (``None``: ideal control); whether it exposes its Gaussian is
        asked at :meth:`reset`.
    """

    names = ("phase",)
    """The columns :meth:`step` gives, in order; :meth:`columns` gives the others."""

    def __init__(self, position: slice, velocity: slice | None, estimator: Any) -> None:
        self.position = position
        self.velocity = velocity
        self.inner = estimator
        self.estimator: Any = None  # the estimator if it exposes its Gaussian (reset())
        self._remote_errors: list[NDArray[np.float64]] = []
        self._truths: list[NDArray[np.float64]] = []
        self._velocities: list[NDArray[np.float64]] = []
        self._means: list[NDArray[np.float64]] = []
        self._covariances: list[NDArray[np.float64]] = []

    @classmethod
    def of(cls, env: Any, estimator: Any) -> ObjectErrors | None:
        """For the loop of ``env`` (wrapped plant) and ``estimator``; ``None`` when the plant's
        remote part holds no ``object_pos``."""
        layout = getattr(env.unwrapped, "observation_layout", None) or {}
        remote = env.remote_slice
        inside = {
            name: slice(s.start - remote.start, s.stop - remote.start)
            for name, s in layout.items()
            if name in ("object_pos", "object_vel")
            and remote.start <= s.start
            and s.stop <= remote.stop
        }
        if "object_pos" not in inside:
            return None
        return cls(inside["object_pos"], inside.get("object_vel"), estimator)

    def reset(self) -> None:
        """Start an episode (after the estimator's reset: its covariance may be read then)."""
        inner = self.inner
        self.estimator = inner if inner is not None and has_covariance(inner) else None
        for kept in (
            self._remote_errors, self._truths, self._velocities, self._means, self._covariances
        ):  # fmt: skip
            kept.clear()

    def step(self, info: dict[str, Any], remote_error: NDArray[np.float64]) -> list[Any]:
        """The :attr:`names` columns of a step, from the ``info`` the estimate was made at and
        the error of the remote part the controller is given (estimate minus truth)."""
        self._remote_errors.append(remote_error)
        if self.estimator is not None:
            self._truths.append(info["remote_true"])
            if self.velocity is None and "object_vel" in info:
                self._velocities.append(info["object_vel"])
            self._means.append(self.estimator.state)
            self._covariances.append(self.estimator.covariance)
        return [info["phase"]]

    def columns(self) -> dict[str, NDArray[np.float64]]:
        """The episode's ``position_error_m`` and, with an estimator exposing its covariance,
        ``nees_position`` and (the true velocity known) ``nees_state``."""
        if not self._remote_errors:
            return {}
        position = np.array(self._remote_errors)[:, self.position]
        out = {"position_error_m": np.sqrt(np.einsum("ki,ki->k", position, position))}
        if self.estimator is None:
            return out
        truths, means = np.array(self._truths), np.array(self._means)
        covariances = np.array(self._covariances)
        errors = means[:, :3] - truths[:, self.position]
        out["nees_position"] = nees(errors, covariances[:, :3, :3])
        if self.velocity is not None:
            velocities = truths[:, self.velocity]
        elif len(self._velocities) == len(truths):
            velocities = np.array(self._velocities)
        else:
            return out
        errors = np.hstack([errors, means[:, 3:6] - velocities])
        out["nees_state"] = nees(errors, covariances[:, :6, :6])
        return out
