"""QoS features from the robot's own belief: what its estimator says it knows.

A learned QoS policy (``eq_q_t_pol2``) that should ask for a packet when the robot is unsure
reads the robot's estimate and its uncertainty. :class:`BeliefFeature` is bound to the robot's
estimator by the closed loop (:meth:`bind_belief`; any object exposing ``state`` and a
``covariance`` over the object's position then velocity, as
:class:`~codesign_mb.estimation.sequence.GaussianSequenceEstimator` and the model-based filters
do) and gives, for the next request:

* the elapsed time ``t / T``;
* ``log10(std_i / scale)`` of each estimated entry's standard deviation (position in m over
  ``position_scale_m``, velocity in m/s over ``speed_scale_mps``);
* the estimated velocity over ``speed_scale_mps``;
* the estimate's offset from the held position ``x_hat - y`` over ``position_scale_m``;
* on a plant with a gripper (``gripper``, ``finger``): the estimated object relative to the
  gripper ``x_hat - g`` over ``position_scale_m`` and the finger opening over ``finger_scale_m``,
  read from the estimator's ``output`` (the controller's input, the robot's own sensors in it):
  how close the grasp is, which decides when a packet matters.

Bound to the learned estimator it is the model-free row's feature (no Kalman or IMM anywhere);
bound to a filter it would be a hybrid one. At the first request of an episode (made with the
link's reset, before the estimator has seen a packet) there is no belief yet: the feature is
the prior's, a fixed vector (``prior_std_m``), the same in training and deployment.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from codesign_mb.adaptation.model_free_features import object_position_in_y

__all__ = ["Belief", "BeliefFeature"]


class Belief(Protocol):
    """What a belief-reading feature needs of an estimator."""

    @property
    def state(self) -> NDArray[np.float64]: ...

    @property
    def covariance(self) -> NDArray[np.float64]: ...

    @property
    def output(self) -> NDArray[np.float64]: ...


class BeliefFeature:
    """The belief features (see the module docstring); ``dim = 1 + 6 + 3 + 3`` (``+ 3 + 1``
    with a gripper).

    Parameters
    ----------
    position:
        Indices of the object's position inside ``y`` (the plant's remote part).
    horizon:
        Episode length ``T``.
    position_scale_m, speed_scale_mps:
        Scales of the position and velocity entries.
    prior_std_m:
        The standard deviation reported before the first belief (every entry, in its scale).
    gripper, finger:
        Where the gripper position (3) and the finger opening (1) are in the estimator's
        ``output``, or ``None`` (no gripper features).
    finger_scale_m:
        Scale of the finger opening.

    Examples
    --------
    >>> class Est:
    ...     state = np.array([0.5, 0.1, 0.0, 0.0, 0.3, 0.0])
    ...     covariance = np.diag([1e-4, 1e-4, 1e-4, 1e-2, 1e-2, 1e-2])
    >>> f = BeliefFeature(slice(0, 3), horizon=10)
    >>> f.bind_belief(Est())
    >>> f.reset()
    >>> f(np.zeros(3), 0)[1:4].round(2).tolist()  # the prior's, before the first belief
    [1.0, 1.0, 1.0]
    >>> f(np.array([0.5, 0.09, 0.0]), 1)[[0, 1, 8, 11]].round(2).tolist()
    [0.1, -0.7, 0.6, 0.2]
    """

    def __init__(
        self,
        position: slice,
        *,
        horizon: int,
        position_scale_m: float = 0.05,
        speed_scale_mps: float = 0.5,
        prior_std_m: float = 0.5,
        gripper: slice | None = None,
        finger: slice | None = None,
        finger_scale_m: float = 0.08,
    ) -> None:
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        for name, value in (
            ("position_scale_m", position_scale_m),
            ("speed_scale_mps", speed_scale_mps),
            ("prior_std_m", prior_std_m),
            ("finger_scale_m", finger_scale_m),
        ):
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if position.stop - position.start != 3:
            raise ValueError(f"position must have 3 entries, got {position}")
        if (gripper is None) != (finger is None):
            raise ValueError("gripper and finger go together (both slices or both None)")
        self.position = position
        self.gripper, self.finger = gripper, finger
        self.finger_scale_m = float(finger_scale_m)
        self.dim = 13 + (4 if gripper is not None else 0)
        self.horizon = int(horizon)
        self.position_scale_m = float(position_scale_m)
        self.speed_scale_mps = float(speed_scale_mps)
        self._scales = np.array([position_scale_m] * 3 + [speed_scale_mps] * 3)
        self._prior = np.log10(np.full(6, prior_std_m) / position_scale_m)
        self._belief: Belief | None = None
        self._t = 0

    @classmethod
    def from_env(cls, env: Any, **options: Any) -> BeliefFeature:
        """For a plant with an ``object_pos`` in its remote part and a horizon."""
        position = object_position_in_y(env, "belief")
        plant = env.unwrapped
        layout = plant.observation_layout
        hand = {"gripper": layout.get("gripper_pos"), "finger": layout.get("finger_width")}
        if hand["gripper"] is None or hand["finger"] is None:
            hand = {}
        return cls(position, horizon=int(plant.horizon), **hand, **options)

    def bind_belief(self, belief: Any) -> None:
        """Read ``belief`` (the robot's estimator) from now on."""
        if getattr(belief, "covariance", None) is None or getattr(belief, "state", None) is None:
            raise ValueError(
                f"belief features need an estimator exposing state and covariance, got "
                f"{type(belief).__name__} (use the learned kind 'sequence' or a filter)"
            )
        if self.gripper is not None and getattr(belief, "output", None) is None:
            raise ValueError(
                f"belief features with a gripper read the estimator's output; "
                f"{type(belief).__name__} has none"
            )
        self._belief = belief

    def reset(self) -> None:
        self._t = 0

    def __call__(self, observation: NDArray[np.float64], age: int) -> NDArray[np.float64]:
        if self._belief is None:
            raise RuntimeError("belief features read the robot's estimator: bind_belief() first")
        t = self._t
        self._t += 1
        out = np.zeros(self.dim)
        out[0] = t / self.horizon
        if t == 0:  # the request sent with the link's reset: no belief yet
            out[1:7] = self._prior
            return out
        mean = np.asarray(self._belief.state, dtype=float)[:6]
        var = np.diag(np.asarray(self._belief.covariance, dtype=float))[:6]
        std = np.sqrt(np.maximum(var, 1e-12))
        out[1 : 1 + len(std)] = np.log10(std / self._scales[: len(std)])
        if len(mean) >= 6:
            out[7:10] = mean[3:6] / self.speed_scale_mps
        y = np.asarray(observation, dtype=float)[self.position]
        out[10:13] = (mean[:3] - y) / self.position_scale_m
        if self.gripper is not None and self.finger is not None:
            robot = np.asarray(self._belief.output, dtype=float)
            out[13:16] = (mean[:3] - robot[self.gripper]) / self.position_scale_m
            out[16] = float(robot[self.finger][0]) / self.finger_scale_m
        return out
