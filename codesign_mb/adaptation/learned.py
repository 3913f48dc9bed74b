"""The learned control-aware QoS policy of stage C (``eq_q_t_pol2``): a trained SB3 SAC actor.

The agent's observation and action are fixed by a :class:`QosInterface`, shared by the
training env (:class:`codesign_mb.stages.qos_env.QosAdaptationEnv`) and the deployed
:class:`LearnedQosPolicy`, so both see exactly the same numbers:

* observation: ``(y_{t-1}, zeta_{t-1} / age_scale)`` (``eq_q_pol``), then the optional extra
  features of a :class:`QosFeatures` (e.g. a model-based predictor's error covariance);
* action in ``[-1, 1]``: the reliability ``q_t = q_min + (a + 1) / 2 (q_max - q_min)`` and,
  when learned, the latency ``tau_t = round((a' + 1) / 2 * max_latency_steps)``; otherwise
  the latency is fixed (one step, as in the paper).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from codesign_mb.core import registry
from codesign_mb.core.checkpoints import reading_checkpoint
from codesign_mb.core.results import atomic_write
from codesign_mb.network.qos import QosRequest

__all__ = [
    "HYBRID_FEATURES",
    "QOS_FEATURES",
    "ElapsedTimeFeature",
    "LearnedQosPolicy",
    "PredictorStdFeature",
    "QosFeatures",
    "QosInterface",
    "make_features",
]


@runtime_checkable
class QosFeatures(Protocol):
    """Extra inputs of a learned QoS policy beyond ``(y_{t-1}, zeta_{t-1})``.

    Called once per packet with what the QoS policy is given; it may read any object it was
    built with (e.g. the estimator, for its covariance). ``dim`` is the feature length.
    """

    dim: int

    def reset(self) -> None:
        """Start an episode."""
        ...

    def __call__(self, observation: NDArray[np.float64], age: int) -> NDArray[np.float64]:
        """The features for the next request."""
        ...


class ElapsedTimeFeature:
    """The episode time ``t / horizon`` of the next packet: lets the policy know the phase."""

    dim = 1

    def __init__(self, horizon: int) -> None:
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        self.horizon = int(horizon)
        self._t = 0

    @classmethod
    def from_env(cls, env: Any) -> ElapsedTimeFeature:
        """For a plant with a ``horizon``."""
        horizon = getattr(env.unwrapped, "horizon", None)
        if horizon is None:
            raise ValueError("the elapsed_time feature needs a plant with a horizon")
        return cls(int(horizon))

    def reset(self) -> None:
        self._t = 0

    def __call__(self, observation: NDArray[np.float64], age: int) -> NDArray[np.float64]:
        t = self._t
        self._t += 1
        return np.array([t / self.horizon])


class PredictorStdFeature:
    """What the model-based stack knows, at the edge: the robot's predictor uncertainty.

    A replica of the robot's
    :class:`~codesign_mb.estimation.predictor.DelayCompensatingPredictor`
    (:class:`~codesign_mb.adaptation.rules.PredictorReplica`, the one the covariance rule
    uses) is fed the stream the QoS policy sees, ``(y_{t-1}, zeta_{t-1})``, so it holds the
    robot's error covariance ``P``. The features, in order:

    * ``log10(s / scale_m)`` with ``s = sqrt(tr P_oo)`` propagated ``1 + latency_steps``
      steps ahead without new data: the object's RMS position uncertainty when the packet
      sent now would be used (what :class:`~codesign_mb.adaptation.rules.CovarianceTriggeredQos`
      thresholds). On the conveyor: about -0.2 just after a delivery, 0.5 at age 10, 0.9
      at age 20, 1.3 for the prior;
    * if ``lift_indicator``: 1 once the held object has been lifted ``lift_margin_m`` above
      where it was first seen, else 0 (the pick's last phase, seen from ``y``);
    * if ``elapsed_time``: the packet's step over the horizon, ``t / T`` (the phase in time).

    The robot's MPC phase itself is not a feature: it lives on the robot and is not in
    ``(y, zeta)``; the two indicators above are its edge-side proxies.

    Parameters
    ----------
    replica:
        The edge's predictor replica.
    horizon:
        Episode length ``T`` (needed with ``elapsed_time``).
    latency_steps:
        ``tau`` of the requests (the paper's fixed one step).
    scale_m:
        Reference uncertainty of the log scale (m).
    lift_indicator, elapsed_time:
        Which optional features to append.
    """

    def __init__(
        self,
        replica: Any,
        *,
        horizon: int | None = None,
        latency_steps: int = 1,
        scale_m: float = 0.01,
        lift_indicator: bool = True,
        elapsed_time: bool = True,
    ) -> None:
        if latency_steps < 0:
            raise ValueError(f"latency_steps must be >= 0, got {latency_steps}")
        if not scale_m > 0:
            raise ValueError(f"scale_m must be > 0, got {scale_m!r}")
        if elapsed_time and (horizon is None or horizon < 1):
            raise ValueError(f"elapsed_time needs a horizon >= 1, got {horizon!r}")
        self.replica = replica
        self.horizon = None if horizon is None else int(horizon)
        self.latency_steps = int(latency_steps)
        self.scale_m = float(scale_m)
        self.lift_indicator = bool(lift_indicator)
        self.elapsed_time = bool(elapsed_time)
        self.dim = 1 + int(self.lift_indicator) + int(self.elapsed_time)

    def reset(self) -> None:
        self.replica.reset()

    def __call__(self, observation: NDArray[np.float64], age: int) -> NDArray[np.float64]:
        self.replica.observe(observation, age)
        t = self.replica.calls - 1  # the step of the packet these features are for
        std = self.replica.position_std_ahead(1 + self.latency_steps)
        out = [math.log10(std / self.scale_m)]
        if self.lift_indicator:
            out.append(float(self.replica.lifted))
        if self.elapsed_time:
            assert self.horizon is not None
            out.append(t / self.horizon)
        return np.array(out)


HYBRID_FEATURES = ("predictor_std",)
"""Feature kinds computed by a model-based replica at the edge: a policy reading them is a
*hybrid* (the others, ``held_history`` and ``elapsed_time``, need no model: model-free)."""

QOS_FEATURES = registry.kinds("qos_feature")
"""Feature kinds of the component registry, each built as ``factory(env, **options)``.

A feature is computed from what the QoS policy is given, ``(y, zeta)`` (and its own state,
e.g. a replica of a model-based predictor fed with the same stream), or, for ``belief``, from
the robot's own estimator, which the closed loop binds to it (:meth:`LearnedQosPolicy.bind_belief`).
"""


def make_features(
    kind: str | None, env: Any, options: dict[str, Any] | None = None
) -> QosFeatures | None:
    """Build the :class:`QosFeatures` of ``kind`` for the plant ``env`` (``None``: none)."""
    if kind is None or kind == "none":
        return None
    if kind not in QOS_FEATURES:
        raise ValueError(
            f"unknown QoS feature kind {kind!r}; expected one of none, {', '.join(QOS_FEATURES)}"
        )
    features: QosFeatures = registry.create("qos_feature", kind, env, **dict(options or {}))
    return features


@dataclass(frozen=True)
class QosInterface:
    """How a learned QoS policy sees the link and what its action means.

    Parameters
    ----------
    remote_dim:
        Length of ``y`` (the plant's remote part).
    feature_dim:
        Length of the extra features (0 without a :class:`QosFeatures`).
    latency_steps:
        The fixed latency ``tau`` when it is not learned (the paper: 1 step).
    learn_latency:
        Whether the action has a second entry choosing ``tau`` in ``[0, max_latency_steps]``.
    max_latency_steps:
        Largest learned latency.
    min_reliability, max_reliability:
        The range the reliability action is mapped onto.
    age_scale:
        The age enters the observation as ``zeta / age_scale``.
    """

    remote_dim: int
    feature_dim: int = 0
    latency_steps: int = 1
    learn_latency: bool = False
    max_latency_steps: int = 4
    min_reliability: float = 0.0
    max_reliability: float = 1.0
    age_scale: float = 10.0

    def __post_init__(self) -> None:
        if self.remote_dim < 1:
            raise ValueError(f"remote_dim must be >= 1, got {self.remote_dim}")
        if self.feature_dim < 0:
            raise ValueError(f"feature_dim must be >= 0, got {self.feature_dim}")
        if self.latency_steps < 0:
            raise ValueError(f"latency_steps must be >= 0, got {self.latency_steps}")
        if self.max_latency_steps < 0:
            raise ValueError(f"max_latency_steps must be >= 0, got {self.max_latency_steps}")
        if not 0.0 <= self.min_reliability <= self.max_reliability <= 1.0:
            raise ValueError(
                "need 0 <= min_reliability <= max_reliability <= 1, got "
                f"{self.min_reliability}, {self.max_reliability}"
            )
        if self.age_scale <= 0:
            raise ValueError(f"age_scale must be > 0, got {self.age_scale}")

    @property
    def observation_dim(self) -> int:
        return self.remote_dim + 1 + self.feature_dim

    @property
    def action_dim(self) -> int:
        return 2 if self.learn_latency else 1

    def observation(
        self,
        observation: NDArray[np.float64],
        age: int,
        features: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float32]:
        """The agent's observation for ``(y_{t-1}, zeta_{t-1})`` and the extra features."""
        y = np.asarray(observation, dtype=np.float32).reshape(-1)
        if y.shape[0] != self.remote_dim:
            raise ValueError(f"observation must have {self.remote_dim} entries, got {y.shape[0]}")
        parts = [y, np.array([age / self.age_scale], dtype=np.float32)]
        if self.feature_dim:
            if features is None:
                raise ValueError(f"this QoS policy needs {self.feature_dim} extra features")
            f = np.asarray(features, dtype=np.float32).reshape(-1)
            if f.shape[0] != self.feature_dim:
                raise ValueError(f"features must have {self.feature_dim} entries, got {f.shape[0]}")
            parts.append(f)
        return np.concatenate(parts)

    def request(self, action: NDArray) -> QosRequest:
        """The :class:`QosRequest` for an agent action in ``[-1, 1]``."""
        a = np.clip(np.asarray(action, dtype=float).reshape(-1), -1.0, 1.0)
        u = (a[0] + 1.0) / 2.0
        q = self.min_reliability + u * (self.max_reliability - self.min_reliability)
        tau = self.latency_steps
        if self.learn_latency:
            tau = round((a[1] + 1.0) / 2.0 * self.max_latency_steps)
        return QosRequest(float(np.clip(q, 0.0, 1.0)), int(tau))


class LearnedQosPolicy:
    """A :class:`~codesign_mb.adaptation.QosPolicy` from a trained SAC QoS agent (stage C).

    Parameters
    ----------
    model:
        The SB3 model (``predict``).
    interface:
        The :class:`QosInterface` it was trained with.
    features:
        The same kind of :class:`QosFeatures` it was trained with (bound to the deployed
        estimator if it reads one), or ``None`` when ``interface.feature_dim == 0``.
    deterministic:
        Use the actor's mean (default).
    """

    def __init__(
        self,
        model: Any,
        interface: QosInterface,
        *,
        features: QosFeatures | None = None,
        deterministic: bool = True,
    ) -> None:
        got = 0 if features is None else int(features.dim)
        if got != interface.feature_dim:
            raise ValueError(
                f"the QoS policy was trained with {interface.feature_dim} extra features, got {got}"
            )
        self.model = model
        self.interface = interface
        self.features = features
        self.deterministic = deterministic

    def reset(self, *, seed: int | None = None) -> None:
        if self.features is not None:
            self.features.reset()

    def bind_belief(self, belief: Any) -> None:
        """Give features that read the robot's estimator (``belief``) that estimator; the
        closed loop calls this with its estimator. Other features need none."""
        bind = getattr(self.features, "bind_belief", None)
        if bind is not None:
            bind(belief)

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        extra = None if self.features is None else self.features(observation, age)
        obs = self.interface.observation(observation, age, extra)
        action, _ = self.model.predict(obs, deterministic=self.deterministic)
        return self.interface.request(action)

    # -- persistence ------------------------------------------------------------------------
    def save(self, directory: str | Path, *, extra: dict[str, Any] | None = None) -> Path:
        """Write ``model.zip`` and ``qos_policy.json`` (the interface) into ``directory``."""

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        self.model.save(directory / "model.zip")
        meta = {"interface": dataclasses.asdict(self.interface), **(extra or {})}
        with atomic_write(directory / "qos_policy.json", "w") as fh:
            json.dump(meta, fh, indent=2)
        return directory

    @staticmethod
    def read_meta(directory: str | Path) -> dict[str, Any]:
        """The ``qos_policy.json`` of a saved policy."""
        directory = Path(directory)
        meta_path = directory / "qos_policy.json"
        if not meta_path.is_file() or not (directory / "model.zip").is_file():
            raise ValueError(
                f"{str(directory)!r} holds no QoS policy (model.zip + qos_policy.json); "
                "train one with `codesign train c`"
            )
        with reading_checkpoint(meta_path, remedy="train it again with `codesign train c`"):
            meta = json.loads(meta_path.read_text())
            if not isinstance(meta, dict):
                raise ValueError(f"a {type(meta).__name__}, not a table")
        return meta

    @classmethod
    def from_env(
        cls, env: Any, directory: str | Path, *, deterministic: bool = True
    ) -> LearnedQosPolicy:
        """Load a saved policy and rebuild its recorded features for the plant ``env``."""
        meta = cls.read_meta(directory)
        spec = meta.get("features") or {}
        features = make_features(spec.get("kind"), env, spec.get("options"))
        return cls.load(directory, features=features, deterministic=deterministic)

    @classmethod
    def load(
        cls,
        directory: str | Path,
        *,
        features: QosFeatures | None = None,
        deterministic: bool = True,
    ) -> LearnedQosPolicy:
        """Load a policy saved by :meth:`save` (or by ``codesign train c``)."""
        from stable_baselines3 import SAC

        directory = Path(directory)
        meta = cls.read_meta(directory)
        with reading_checkpoint(directory, remedy="train it again with `codesign train c`"):
            interface = QosInterface(**meta["interface"])
            model = SAC.load(directory / "model.zip", device="cpu")
        return cls(model, interface, features=features, deterministic=deterministic)
