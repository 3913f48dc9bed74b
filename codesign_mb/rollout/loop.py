"""THE closed loop: plant behind its link, QoS policy, estimator, controller; per-step record.

Every episode of the toolkit runs here: evaluation, training-data collection, sweeps, the
QoS-learning env of stage C and the N-robot WiFi cell (:func:`rollout_shared`). One step of
robot ``i`` is DESIGN.md's data flow: the QoS policy and the link live in the
:class:`~codesign_mb.network.LinkObservationWrapper`; the robot computes
``x_hat_t = estimator(y_t, zeta_t)`` and ``u_t = controller(x_hat_t)`` (``eq_c_pol2``).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.control.base import Controller
from codesign_mb.estimation.base import Estimator
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.plants.phases import NOT_SPAWNED
from codesign_mb.rollout.object_errors import ObjectErrors

__all__ = [
    "ClosedLoop",
    "SharedChannelLike",
    "Transition",
    "packet_lacks_velocity",
    "rollout",
    "rollout_shared",
    "true_velocity",
]

_RECORDED = ("qos_reliability", "qos_latency_steps", "qos_cost", "delivered", "age")
_recorded = operator.itemgetter(*_RECORDED)


def true_velocity(info: dict[str, Any]) -> NDArray[np.float64]:
    """The object's true velocity from a plant's ``info``: zero before it spawned (as the
    plant's ``remote_true`` gives it when the velocity is perceived)."""
    if info.get("phase", 0) == NOT_SPAWNED:
        return np.zeros(3)
    return np.asarray(info["object_vel"], dtype=float)


def packet_lacks_velocity(env: Any) -> bool:
    """Whether ``env``'s ``state_layout`` has an ``object_vel`` its observation (the packet)
    does not: a controller reads a velocity that must be estimated (or, ideally, given)."""
    plant = env.unwrapped
    state = getattr(plant, "state_layout", None) or {}
    observed = getattr(plant, "observation_layout", None) or {}
    return "object_vel" in state and "object_vel" not in observed


@dataclass(frozen=True, slots=True)
class Transition:
    """One step as an observer sees it (training-data collection).

    ``observation`` is the networked observation acted on (``y_t`` and ``zeta_t``),
    ``state`` what the controller was given, ``info`` the plant's and the link's after the step.
    """

    t: int
    observation: NDArray[Any]
    state: NDArray[np.float64]
    action: NDArray[np.float64]
    reward: float
    next_observation: NDArray[Any]
    terminated: bool
    truncated: bool
    info: dict[str, Any]


Observer = Callable[[Transition], None]


class ClosedLoop:
    """One robot's closed loop, stepped one control period at a time.

    Parameters
    ----------
    env:
        The plant behind its link (:class:`LinkObservationWrapper`).
    estimator:
        An :class:`Estimator`; ``None`` runs *ideal control*: the controller is given the
        plant's observation with the true remote state (the paper's stage A), and, where the
        plant's ``state_layout`` has an ``object_vel`` its packet lacks (the ``realistic``
        scenario), the object's true velocity there (:func:`true_velocity`).
    controller:
        A :class:`Controller`.
    observer:
        Called with each :class:`Transition` (e.g. to record training data).
    record:
        Keep the per-step record (:meth:`table`); off for training loops that need none.
    """

    def __init__(
        self,
        env: LinkObservationWrapper,
        estimator: Estimator | None,
        controller: Controller,
        *,
        observer: Observer | None = None,
        record: bool = True,
    ) -> None:
        self.env = env
        self.estimator = estimator
        self.controller = controller
        self.observer = observer
        self.recording = record
        self._remote = env.remote_slice
        self._true_velocity = packet_lacks_velocity(env)
        self.t = 0
        self.done = True
        self.observation: NDArray[Any] | None = None
        self.info: dict[str, Any] = {}
        self._state: NDArray[np.float64] | None = None
        self._record: _Record | None = None
        self._object_errors = ObjectErrors.of(env, estimator) if record else None
        self._errors: ObjectErrors | None = None  # this episode's (the plant reports a phase)
        bind = getattr(env.qos_policy, "bind_belief", None)
        if bind is not None and estimator is not None:  # a QoS policy reading the robot's belief
            bind(estimator)

    def reset(self, *, seed: int) -> dict[str, Any]:
        """Start an episode: plant, link, QoS policy, controller and estimator from ``seed``."""
        obs, info = self.env.reset(seed=seed)
        self.controller.reset(seed=seed)
        self.observation, self.info = obs, info
        self._state = self._estimate(obs, info, None)
        self.t, self.done = 0, False
        self._errors = self._object_errors if "phase" in info else None
        names = _HEAD
        if self._errors is not None:
            self._errors.reset()
            names = (*_HEAD[:-1], *self._errors.names, _HEAD[-1])
        self._record = _Record(names) if self.recording else None
        return info

    def _estimate(
        self, obs: NDArray[Any], info: dict[str, Any], action: NDArray[np.float64] | None
    ) -> NDArray[np.float64]:
        if self.estimator is None:  # ideal control: the true remote state (a copy: obs is kept)
            state = np.array(obs[:-1], dtype=float)
            state[self._remote] = info["remote_true"]
            if self._true_velocity:  # the state layout's velocity, which no packet carries
                state = np.concatenate([state, true_velocity(info)])
            return state
        if action is None:
            return np.asarray(self.estimator.reset(obs))
        return np.asarray(self.estimator.estimate(obs, action))

    def step(self) -> tuple[bool, bool, dict[str, Any]]:
        """One control period; returns ``(terminated, truncated, info)`` of the plant."""
        if self.done or self._state is None:
            raise RuntimeError("call reset() before step(), and not after the episode ended")
        info = self.info
        state = self._state
        action = np.asarray(self.controller.act(state), dtype=float)
        head: list[Any] | None = None
        if self._record is not None:
            head = [*_recorded(info)]
            error = state[self._remote] - info["remote_true"]
            head.append(math.sqrt(error.dot(error)))  # the norm of the estimation error
            if self._errors is not None:  # the object's phase; its errors kept for table()
                head.extend(self._errors.step(info, error))
        obs, reward, terminated, truncated, next_info = self.env.step(action)
        if self._record is not None and head is not None:
            self._record.append(self.t, head, float(reward), next_info)
        if self.observer is not None:
            self.observer(
                Transition(
                    self.t,
                    self.observation if self.observation is not None else obs,
                    state,
                    action,
                    float(reward),
                    obs,
                    bool(terminated),
                    bool(truncated),
                    next_info,
                )
            )
        self.t += 1
        self.observation, self.info = obs, next_info
        self.done = bool(terminated or truncated)
        if not self.done:
            self._state = self._estimate(obs, next_info, action)
        return bool(terminated), bool(truncated), next_info

    @property
    def state(self) -> NDArray[np.float64] | None:
        """What the controller is given next: the estimate (or the true state, ideal control)."""
        return self._state

    def table(self) -> pd.DataFrame:
        """The per-step record: one row per control step (see :func:`rollout`)."""
        if self._record is None:
            return pd.DataFrame([])
        frame = self._record.frame()
        if self._errors is not None and len(frame):  # after the phase, in its order
            at = frame.columns.get_loc("phase") + 1
            for i, (name, column) in enumerate(self._errors.columns().items()):
                frame.insert(at + i, name, column)
        return frame


_HEAD = ("t", *_RECORDED, "estimation_error", "reward")
_SCALARS = (bool, int, float, np.bool_, np.float64, np.int64)
"""Types whose values are recorded without asking ``np.ndim`` (0-d by construction)."""


def _scalar_keys(info: dict[str, Any], head: tuple[str, ...] = _HEAD) -> list[str]:
    """The ``info`` keys a row records: scalar, non-string values not among ``head``."""
    return [
        k
        for k, v in info.items()
        if k not in head and (type(v) in _SCALARS or (np.ndim(v) == 0 and not isinstance(v, str)))
    ]


class _Record:
    """The per-step rows of one episode, as tuples (one DataFrame at the end).

    A row is the ``names`` (by default :data:`_HEAD`: ``t``, the QoS columns,
    ``estimation_error``, ``reward``) and every scalar, non-string ``info`` entry not among
    them. Which entries those are is found on the first step and again whenever ``info``'s
    keys or value types differ from that step's; while the recorded keys stay those of the
    first step, rows are tuples in one column order, otherwise they fall back to dicts, which
    pandas aligns (a missing entry is NaN).
    """

    def __init__(self, names: tuple[str, ...] = _HEAD) -> None:
        self.names = names
        self.keys: tuple[str, ...] | None = None
        self.tuples: list[tuple[Any, ...]] = []
        self.rows: list[dict[str, Any]] | None = None
        self._signature: tuple[tuple[str, ...], tuple[type, ...]] | None = None

    def append(self, t: int, head: list[Any], reward: float, info: dict[str, Any]) -> None:
        signature = (tuple(info), tuple(map(type, info.values())))
        if signature == self._signature and self.keys is not None:  # the usual step
            self.tuples.append((t, *head, reward, *map(info.__getitem__, self.keys)))
            return
        keys = tuple(_scalar_keys(info, self.names))
        values = (t, *head, reward, *map(info.__getitem__, keys))
        if self.keys is None and self.rows is None:
            self.keys, self._signature = keys, signature
        if self.rows is None and keys != self.keys:
            self.rows = self._as_rows()
        if self.rows is not None:
            self.rows.append(dict(zip((*self.names, *keys), values, strict=True)))
            return
        self.tuples.append(values)

    def _as_rows(self) -> list[dict[str, Any]]:
        names = (*self.names, *(self.keys or ()))
        self._signature = None
        return [dict(zip(names, row, strict=True)) for row in self.tuples]

    def frame(self) -> pd.DataFrame:
        if self.rows is not None:
            return pd.DataFrame(self.rows)
        if self.keys is None:
            return pd.DataFrame([])
        names = (*self.names, *self.keys)
        columns = map(_column, zip(*self.tuples, strict=True))
        return pd.DataFrame(dict(zip(names, columns, strict=True)))


_KINDS = (frozenset({float, np.float64}), frozenset({int, np.int64}), frozenset({bool, np.bool_}))


def _column(values: tuple[Any, ...]) -> NDArray[Any] | list[Any]:
    """A record column for pandas: a numpy array where its values are all floats, all ints or
    all bools (the dtype pandas would infer, without its per-element inference), else a list.
    """
    kinds = set(map(type, values))
    if any(kinds <= kind for kind in _KINDS):
        return np.array(values)
    return list(values)


def rollout(
    env: LinkObservationWrapper,
    estimator: Estimator | None,
    controller: Controller,
    *,
    seed: int,
    max_steps: int | None = None,
    observer: Observer | None = None,
) -> pd.DataFrame:
    """Run one seeded episode and return its per-step record (one row per control step).

    Columns: ``t``, ``reward``, the QoS request and its cost, ``delivered``, ``age``,
    ``estimation_error`` (norm of the remote estimate minus the truth), for a plant that
    reports the object's phase (the conveyor) ``phase``, ``position_error_m`` and, with an
    estimator exposing its covariance, ``nees_position`` and ``nees_state``
    (:mod:`codesign_mb.rollout.object_errors`), and every scalar entry of the plant's
    ``info`` (e.g. ``success``). Row ``t`` holds the action taken at ``t`` and what followed
    it; the QoS columns (and the object's phase and errors) describe the packet that produced
    the observation acted on (the state it was estimated at). ``estimator=None`` runs ideal
    control (see :class:`ClosedLoop`).
    """
    loop = ClosedLoop(env, estimator, controller, observer=observer)
    loop.reset(seed=seed)
    while not loop.done and (max_steps is None or loop.t < max_steps):
        loop.step()
    return loop.table()


class SharedChannelLike(Protocol):
    """What :func:`rollout_shared` needs of a shared channel (``wifi.cell.SharedChannel``)."""

    @property
    def n(self) -> int: ...

    @property
    def links(self) -> Sequence[Any]: ...

    @property
    def step_order(self) -> Sequence[int]: ...

    def reset(self, *, seed: int | None = None) -> None: ...

    def close(self, station: int) -> None: ...

    def rejoin(self, station: int) -> None: ...


def rollout_shared(
    envs: Sequence[LinkObservationWrapper],
    estimators: Sequence[Estimator | None],
    controllers: Sequence[Controller],
    *,
    channel: SharedChannelLike,
    seed: int,
    max_steps: int | None = None,
    episodes: int = 1,
    warmup_episodes: int = 0,
) -> list[pd.DataFrame]:
    """Run N robots in lockstep on one channel; one per-step table per robot (like ``rollout``).

    ``envs[i]`` must be a :class:`~codesign_mb.network.LinkObservationWrapper` around robot
    ``i``'s plant whose link is ``channel.links[i]``. Robots are stepped in
    ``channel.step_order``.

    One episode each (the default): a robot whose episode ends leaves the channel;
    ``max_steps`` caps the steps. Continuous operation (``warmup_episodes + episodes > 1``):
    a robot whose episode ends starts its next one at its next step
    (:meth:`~codesign_mb.wifi.cell.SharedChannel.rejoin`), so the robots' phases drift apart
    as in a running cell; its first ``warmup_episodes`` (begun in step with the others) are
    not returned, then ``episodes`` are; a robot done with those keeps working (episodes not
    returned) until every robot is, so the channel carries N robots throughout. ``max_steps``
    then caps each episode. The tables get an ``episode`` column (counted from 0 after the
    warm-up).

    Seeds: the channel is reset with ``seed``; robot ``i`` gets the ``i``-th stream spawned
    from it (env, link drops and QoS policy, via the wrapper; controller), its later episodes
    seeds spawned from that stream.
    """
    n = channel.n
    if not (len(envs) == len(estimators) == len(controllers) == n):
        raise ValueError(
            f"need one env, estimator and controller per station ({n}), got "
            f"{len(envs)}, {len(estimators)}, {len(controllers)}"
        )
    if episodes < 1 or warmup_episodes < 0:
        raise ValueError(
            f"need episodes >= 1 and warmup_episodes >= 0, got {episodes}, {warmup_episodes}"
        )
    for i, env in enumerate(envs):
        if getattr(env, "link", None) is not channel.links[i]:
            raise ValueError(f"envs[{i}] must be wrapped with channel.links[{i}]")
    chan_ss, *robot_ss = np.random.SeedSequence(seed).spawn(n + 1)
    channel.reset(seed=int(chan_ss.generate_state(1)[0]))
    loops = [ClosedLoop(e, s, c) for e, s, c in zip(envs, estimators, controllers, strict=True)]
    for i in channel.step_order:
        loops[i].reset(seed=int(robot_ss[i].generate_state(1)[0]))
    if warmup_episodes + episodes == 1:
        t = 0
        while not all(loop.done for loop in loops) and (max_steps is None or t < max_steps):
            for i in channel.step_order:
                if not loops[i].done:
                    loops[i].step()
                    if loops[i].done:
                        channel.close(i)
            t += 1
        tables = [loop.table() for loop in loops]
        for i, table in enumerate(tables):
            table.insert(min(1, len(table.columns)), "robot", i)
        return tables
    return _continuous(loops, channel, robot_ss, max_steps, episodes, warmup_episodes)


def _continuous(
    loops: list[ClosedLoop],
    channel: SharedChannelLike,
    robot_ss: list[np.random.SeedSequence],
    max_steps: int | None,
    episodes: int,
    warmup: int,
) -> list[pd.DataFrame]:
    """:func:`rollout_shared`'s continuous operation: episodes back to back per robot."""
    n = len(loops)
    finished = [0] * n  # episodes ended, per robot
    kept: list[list[pd.DataFrame]] = [[] for _ in range(n)]
    while min(finished) < warmup + episodes:
        for i in channel.step_order:
            loop = loops[i]
            if loop.done:  # ended last round: this round's step is the next episode's first
                channel.rejoin(i)
                loop.reset(seed=int(robot_ss[i].spawn(1)[0].generate_state(1)[0]))
                continue
            loop.step()
            if max_steps is not None and loop.t >= max_steps:
                loop.done = True
            if not loop.done:
                continue
            if warmup <= finished[i] < warmup + episodes:
                table = loop.table()
                table.insert(min(1, len(table.columns)), "robot", i)
                table.insert(2, "episode", finished[i] - warmup)
                kept[i].append(table)
            finished[i] += 1
    return [pd.concat(tables, ignore_index=True) for tables in kept]
