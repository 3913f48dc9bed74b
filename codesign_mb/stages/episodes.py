"""Recorded episodes of the robot behind its link: stage B's (and D's) estimator data.

Episodes run through THE closed loop (:class:`~codesign_mb.rollout.ClosedLoop`) with the
plant behind a :class:`~codesign_mb.network.BernoulliLink` whose QoS comes from a policy,
by default a :class:`RandomQos` drawing from the :class:`DelayDistribution` ``T`` of
``eq_control_estimation``. An :class:`EpisodeRecorder` observer keeps, per step, the networked
observation ``(y_t, zeta_t)``, the previous action, the true remote state ``x_t`` (with the
object's true velocity appended where the packet carries none, :func:`estimates_velocity`),
the object's phase (:mod:`codesign_mb.plants.phases`), the requested reliability and whether
the episode succeeded. :func:`estimator_mse` scores any
:class:`~codesign_mb.estimation.base.Estimator` on recorded episodes, overall and per phase.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from codesign_mb.control.base import Controller
from codesign_mb.core.config import LATENCY_STEPS_CAP, check_range
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.core.results import atomic_write
from codesign_mb.estimation.base import Estimator
from codesign_mb.estimation.consistency import has_covariance, nees
from codesign_mb.evaluation.pool import imap, single_threaded_worker
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.qos import QosPolicy, QosRequest
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.phases import NOT_SPAWNED, PHASES
from codesign_mb.rollout.loop import (
    ClosedLoop,
    Transition,
    packet_lacks_velocity,
    true_velocity,
)
from codesign_mb.stages.training import stage_seeds

__all__ = [
    "DelayDistribution",
    "EpisodeData",
    "EpisodeRecorder",
    "RandomQos",
    "cached_episodes",
    "collect_episodes",
    "estimates_velocity",
    "estimator_mse",
    "position_slice",
    "velocity_slice",
]


@dataclass(frozen=True)
class DelayDistribution:
    """The QoS distribution ``T`` the estimators are trained under.

    Each episode draws its reliability ``q ~ U[reliability_low, reliability_high]``; each
    packet is delivered with probability ``q`` (Bernoulli loss, ``eq_d``) after a latency
    ``tau ~ U{latency_low, ..., latency_high}`` steps. The age ``zeta_t`` follows from both.
    With probability ``perfect_probability`` an episode instead has the perfect link (``q = 1``,
    ``tau = 0``, the tables' oracle), which a uniform ``q`` almost never draws.
    """

    reliability_low: float = 0.0
    reliability_high: float = 1.0
    latency_low: int = 0
    latency_high: int = 4
    perfect_probability: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.reliability_low <= self.reliability_high <= 1.0:
            raise ValueError(
                "need 0 <= reliability_low <= reliability_high <= 1, got "
                f"{self.reliability_low}, {self.reliability_high}"
            )
        if not 0 <= self.latency_low <= self.latency_high:
            raise ValueError(
                "need 0 <= latency_low <= latency_high, got "
                f"{self.latency_low}, {self.latency_high}"
            )
        check_range("latency_high", self.latency_high, cap=LATENCY_STEPS_CAP)
        check_range("perfect_probability", self.perfect_probability, ge=0.0, le=1.0)


class RandomQos:
    """A :class:`~codesign_mb.adaptation.QosPolicy` drawing from a :class:`DelayDistribution`."""

    def __init__(self, distribution: DelayDistribution, seed: int | None = None) -> None:
        self.distribution = distribution
        self._rng = np.random.default_rng(seed)
        self.reliability = distribution.reliability_high
        self.perfect = False

    def reset(self, *, seed: int | None = None) -> None:
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        d = self.distribution
        self.reliability = float(self._rng.uniform(d.reliability_low, d.reliability_high))
        # Drawn only when asked for, so the streams of the uniform recipe stay as they were.
        self.perfect = bool(d.perfect_probability and self._rng.random() < d.perfect_probability)
        if self.perfect:
            self.reliability = 1.0

    def request(self, observation: NDArray[np.float64], age: int) -> QosRequest:
        d = self.distribution
        if self.perfect:
            return QosRequest(1.0, 0)
        tau = int(self._rng.integers(d.latency_low, d.latency_high + 1))
        return QosRequest(self.reliability, tau)


@dataclass
class EpisodeData:
    """Recorded episodes, one array per episode (``T_i + 1`` steps each, from the reset on).

    ``networked[i][t]`` is the wrapped observation (plant layout with ``y_t``, then
    ``zeta_t``), ``prev_actions[i][t]`` the action applied before it (zeros at ``t = 0``),
    ``truth[i][t]`` the true remote state ``x_t`` (then the object's true velocity, where the
    packet carries none), ``reliability[i][t]`` the requested ``q``, ``phase[i][t]`` the
    object's phase (an index into :data:`~codesign_mb.plants.phases.PHASES`; -1 before it
    spawned or on a plant without phases).
    """

    networked: list[np.ndarray] = field(default_factory=list)
    prev_actions: list[np.ndarray] = field(default_factory=list)
    truth: list[np.ndarray] = field(default_factory=list)
    reliability: list[np.ndarray] = field(default_factory=list)
    success: list[bool] = field(default_factory=list)
    phase: list[np.ndarray] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.networked)

    @property
    def steps(self) -> int:
        return int(sum(len(x) for x in self.networked))

    def extend(self, other: EpisodeData) -> EpisodeData:
        for name in ("networked", "prev_actions", "truth", "reliability", "success", "phase"):
            getattr(self, name).extend(getattr(other, name))
        return self

    def save(self, path: str | Path) -> None:
        """Write to one ``.npz`` (episodes concatenated, with their lengths)."""

        lengths = np.array([len(x) for x in self.networked], dtype=np.int64)
        with atomic_write(path) as fh:
            np.savez_compressed(
                fh,
                lengths=lengths,
                networked=np.concatenate(self.networked),
                prev_actions=np.concatenate(self.prev_actions),
                truth=np.concatenate(self.truth),
                reliability=np.concatenate(self.reliability),
                success=np.asarray(self.success, dtype=bool),
                phase=np.concatenate(self.phase),
            )

    @classmethod
    def load(cls, path: str | Path) -> EpisodeData:
        with np.load(path) as z:
            cuts = np.cumsum(z["lengths"])[:-1]
            phase = z["phase"] if "phase" in z else np.full(int(z["lengths"].sum()), NOT_SPAWNED)
            return cls(
                networked=list(np.split(z["networked"], cuts)),
                prev_actions=list(np.split(z["prev_actions"], cuts)),
                truth=list(np.split(z["truth"], cuts)),
                reliability=list(np.split(z["reliability"], cuts)),
                success=[bool(s) for s in z["success"]],
                phase=list(np.split(phase, cuts)),
            )


class EpisodeRecorder:
    """A :class:`~codesign_mb.rollout.loop.Transition` observer recording :class:`EpisodeData`.

    :meth:`start` takes the reset's networked observation and ``info``; every step appends
    the next observation, the action that led to it, the true remote state (with
    ``velocity``: then the object's true velocity, zero before it spawned, as the plant's
    ``remote_true`` gives it when perceived), the object's phase and the requested
    reliability; :meth:`finish` appends the episode to ``data``.
    """

    def __init__(self, action_dim: int, *, velocity: bool = False) -> None:
        self.action_dim = int(action_dim)
        self.velocity = bool(velocity)
        self.networked: list[NDArray[Any]] = []
        self.prev_actions: list[NDArray[np.float64]] = []
        self.truth: list[NDArray[np.float64]] = []
        self.reliability: list[float] = []
        self.phase: list[int] = []
        self.success = False

    def start(self, observation: NDArray[Any], info: dict[str, Any]) -> None:
        """Begin an episode from the reset's networked observation and ``info``."""
        self.networked = [np.array(observation)]
        self.prev_actions = [np.zeros(self.action_dim)]
        self.truth, self.reliability, self.phase = [], [], []
        self._record(info)
        self.success = bool(info.get("success", False))

    def __call__(self, step: Transition) -> None:
        self.networked.append(step.next_observation)
        self.prev_actions.append(step.action)
        self._record(step.info)
        self.success = self.success or bool(step.info.get("success", False))

    def _record(self, info: dict[str, Any]) -> None:
        truth = np.asarray(info["remote_true"], dtype=float)
        if self.velocity:
            truth = np.concatenate([truth, true_velocity(info)])
        self.truth.append(truth)
        self.reliability.append(info["qos_reliability"])
        self.phase.append(int(info.get("phase", NOT_SPAWNED)))

    def finish(self, data: EpisodeData) -> None:
        """Append the episode to ``data`` (float32 arrays, one row per step from the reset)."""
        data.networked.append(np.asarray(self.networked, dtype=np.float32))
        data.prev_actions.append(np.asarray(self.prev_actions, dtype=np.float32))
        data.truth.append(np.asarray(self.truth, dtype=np.float32))
        data.reliability.append(np.asarray(self.reliability, dtype=np.float32))
        data.success.append(self.success)
        data.phase.append(np.asarray(self.phase, dtype=np.int8))


def collect_episodes(
    plant: PlantSpec,
    controller: ComponentSpec | Controller,
    qos_policy: QosPolicy,
    *,
    episodes: int,
    seed: int,
    behaviour: Estimator | None = None,
    workers: int = 1,
) -> EpisodeData:
    """Roll ``controller`` out through a Bernoulli link with ``qos_policy`` and record it.

    ``controller`` given as a spec is built on the plant the episodes step (a controller that
    reads its own plant's sensors, as the arm-aware MPC reads the joints, must be); an
    instance is used as given. ``behaviour`` is the estimator the controller acts through
    (``None``: ideal control on the true state, i.e. the ideal trajectories). Episode ``i``
    is seeded from ``SeedSequence(seed)`` (:func:`~codesign_mb.stages.training.stage_seeds`).
    With ``workers > 1`` the episodes run in the process pool, in chunks of consecutive seeds
    (each worker builds its own controller and copies of the policy and the behaviour): the
    data are the same as with one worker, in the same order.
    """
    seeds = stage_seeds(seed, episodes)
    if workers <= 1:
        return _collect(plant, controller, qos_policy, seeds, behaviour)
    parts = max(1, min(len(seeds), 4 * workers))
    chunks = [list(c) for c in np.array_split(np.asarray(seeds, dtype=np.int64), parts) if len(c)]
    tasks = [(plant, controller, qos_policy, [int(s) for s in c], behaviour) for c in chunks]
    results = dict(imap(_collect, tasks, workers=workers, initializer=single_threaded_worker))
    data = EpisodeData()
    for i in range(len(tasks)):
        data.extend(results[i])
    return data


def _collect(
    plant: PlantSpec,
    controller: ComponentSpec | Controller,
    qos_policy: QosPolicy,
    seeds: list[int],
    behaviour: Estimator | None,
) -> EpisodeData:
    """The episodes of ``seeds``, one after the other (see :func:`collect_episodes`)."""
    env = LinkObservationWrapper(make_plant(plant), BernoulliLink(), qos_policy)
    if isinstance(controller, ComponentSpec):
        controller = build("controller", controller, env)
    recorder = EpisodeRecorder(
        int(np.prod(env.action_space.shape)), velocity=estimates_velocity(env)
    )
    loop = ClosedLoop(env, behaviour, controller, observer=recorder, record=False)
    data = EpisodeData()
    for s in seeds:
        info = loop.reset(seed=s)
        assert loop.observation is not None
        recorder.start(loop.observation, info)
        while not loop.done:
            loop.step()
        recorder.finish(data)
    env.close()
    return data


def estimator_mse(
    estimator: Any,
    data: EpisodeData,
    *,
    remote: slice,
    position: slice | None = None,
    velocity: slice | None = None,
) -> dict[str, float]:
    """Score any :class:`~codesign_mb.estimation.base.Estimator` on recorded episodes.

    Runs ``reset``/``estimate`` along each episode exactly as a rollout does and returns the
    mean squared error of the remote estimate over all steps (``mse``, summed over the remote
    entries of the observation). With ``position`` (the ``object_pos`` slice) also the object
    position's ``mse_position`` (m^2) and RMSE; with ``velocity`` (the ``object_vel`` slice of
    the plant's *state* layout: inside the remote part, or appended after the observation
    where the packet carries none) the velocity's RMSE, for an estimator whose output has it.
    Both are also given per phase of :data:`~codesign_mb.plants.phases.PHASES`
    (``rmse_position_<phase>_m``, ``rmse_velocity_<phase>_mps``, ``steps_<phase>``): the
    phases have different dynamics, and an error matters most while grasping. An estimator
    exposing its Gaussian (``state``, ``covariance``, position first) also gets
    ``coverage_position`` (and ``coverage_position_<phase>``): the share of steps with the true
    position inside its 95 % ellipsoid, the tables' ``nees_inside``.
    """
    sq, n = 0.0, 0
    parts = {"position": position, "velocity": velocity}
    sums = {name: np.zeros(len(PHASES) + 1) for name, where in parts.items() if where is not None}
    inside = np.zeros(len(PHASES) + 1)
    gaussian = position is not None
    counts = np.zeros(len(PHASES) + 1)
    remote_dim = remote.stop - remote.start
    phases = data.phase if len(data.phase) == len(data) else [None] * len(data)
    for nets, prevs, truth, phase in zip(
        data.networked, data.prev_actions, data.truth, phases, strict=True
    ):
        est, beliefs = _estimates(estimator, nets, prevs)
        sq += float(np.sum((est[:, remote] - truth[:, :remote_dim]) ** 2))
        n += len(est)
        labels = np.full(len(est), NOT_SPAWNED) if phase is None else np.asarray(phase)
        masks = [np.ones(len(est), dtype=bool), *(labels == k for k in range(len(PHASES)))]
        counts += [m.sum() for m in masks]
        gaussian = gaussian and beliefs is not None
        if position is not None and beliefs is not None:
            cols = slice(position.start - remote.start, position.stop - remote.start)
            means, covariances = beliefs
            ok = nees(means[:, :3] - truth[:, cols], covariances[:, :3, :3]) <= _INSIDE_LIMIT
            inside += [float(ok[m].sum()) for m in masks]
        for name in list(sums):
            where = parts[name]
            assert where is not None
            if est.shape[1] < where.stop:  # this estimator does not output it
                del sums[name]
                continue
            cols = slice(where.start - remote.start, where.stop - remote.start)
            err = np.sum((est[:, where] - truth[:, cols]) ** 2, axis=1)
            sums[name] += [float(err[m].sum()) for m in masks]
    out = _mse_summary(sq / max(n, 1), sums, counts)
    if gaussian and n:
        out["coverage_position"] = float(inside[0] / max(counts[0], 1))
        for k, name in enumerate(PHASES, start=1):
            if counts[k]:
                out[f"coverage_position_{name}"] = float(inside[k] / counts[k])
    return out


_INSIDE_LIMIT = float(chi2.ppf(0.95, 3))
"""The 95 % ellipsoid of a 3-D position: its NEES at most this chi-square quantile."""


def _estimates(
    estimator: Any, nets: np.ndarray, prevs: np.ndarray
) -> tuple[NDArray[np.float64], tuple[NDArray[np.float64], NDArray[np.float64]] | None]:
    """The estimator's outputs along one recorded episode, as a rollout calls it, and its
    Gaussian (means, covariances) per step where it exposes one."""
    nets64 = np.asarray(nets, dtype=np.float64)
    estimates = [estimator.reset(nets64[0])]
    gaussian = has_covariance(estimator)
    means, covariances = [], []
    for t in range(len(nets64)):
        if t:
            action = np.asarray(prevs[t], dtype=np.float64)
            estimates.append(estimator.estimate(nets64[t], action))
        if gaussian:
            means.append(np.asarray(estimator.state, dtype=float))
            covariances.append(np.asarray(estimator.covariance, dtype=float))
    beliefs = (np.asarray(means), np.asarray(covariances)) if gaussian else None
    return np.asarray(estimates), beliefs


def _mse_summary(mse: float, sums: dict[str, np.ndarray], counts: np.ndarray) -> dict[str, float]:
    out = {"mse": mse}
    units = {"position": "m", "velocity": "mps"}
    if "position" in sums:
        out["mse_position"] = float(sums["position"][0] / max(counts[0], 1))
    for name, total in sums.items():
        out[f"rmse_{name}_{units[name]}"] = float(np.sqrt(total[0] / max(counts[0], 1)))
        for k, phase in enumerate(PHASES, start=1):
            if counts[k]:
                out[f"rmse_{name}_{phase}_{units[name]}"] = float(np.sqrt(total[k] / counts[k]))
    for k, phase in enumerate(PHASES, start=1):
        out[f"steps_{phase}"] = int(counts[k])
    return out


def estimates_velocity(env: Any) -> bool:
    """Whether a controller of ``env`` reads an ``object_vel`` its packet does not carry (the
    plant's ``state_layout`` has it, its observation does not): then an estimator estimates it."""
    return packet_lacks_velocity(env)


def velocity_slice(env: Any) -> slice | None:
    """The ``object_vel`` slice of a plant's state layout (``None`` without one)."""
    plant = env.unwrapped
    layout = getattr(plant, "state_layout", None) or getattr(plant, "observation_layout", None)
    return (layout or {}).get("object_vel")


def position_slice(env: Any) -> slice | None:
    """The ``object_pos`` slice of a plant's layout (``None`` without one)."""
    layout = getattr(env.unwrapped, "observation_layout", None) or {}
    return layout.get("object_pos")


def cached_episodes(path: Path, make: Callable[[], EpisodeData]) -> EpisodeData:
    """The episodes saved at ``path``; else ``make()``'s, saved there first (resumable runs)."""
    if path.is_file():
        return EpisodeData.load(path)
    data = make()
    data.save(path)
    return data
