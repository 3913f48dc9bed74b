"""The clairvoyant schedule of an episode: few packets, at known times, and still a success.

Issue 34's question, "how few packets can a pick need?", asked of one realised episode. The
episode is replayed from its seed (belt profile, detections, perception errors, link draws):
a QoS schedule fixed in advance (:class:`~codesign_mb.adaptation.base.ScheduledQos`) replays
exactly, so whether a set of request steps still succeeds is one replay. Starting from the
co-design policy's own requests (or, where it failed, from every step, if static QoS
succeeds), delta debugging (Zeller and Hildebrandt, "Simplifying and isolating
failure-inducing input", IEEE TSE 2002; :func:`minimal_subset`) removes requests while the
replay succeeds, down to a *1-minimal* schedule: no single request of it can go.

What the number is, and is not: an achievable schedule for a clairvoyant scheduler (it knows
the episode), so the fewest packets the stack needs on that episode is *at most* this; it is
not a proof that fewer cannot do (a schedule with requests at other times than those of the
start is not searched). Beside a co-design row it says how many of its packets the episode
did not need.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from numpy.typing import NDArray

from codesign_mb.adaptation.base import ScheduledQos
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.evaluation.evaluate import episode_record
from codesign_mb.evaluation.pool import imap
from codesign_mb.network import BernoulliLink, LinkObservationWrapper, QosRequest

__all__ = ["ClairvoyantEpisode", "clairvoyant_episode", "clairvoyant_episodes", "minimal_subset"]

T = TypeVar("T", bound=Hashable)


def minimal_subset(
    items: Sequence[T], succeeds: Callable[[tuple[T, ...]], bool]
) -> tuple[tuple[T, ...], int]:
    """A 1-minimal subset of ``items`` that ``succeeds`` (which ``items`` must), and the calls.

    Delta debugging's ``ddmin`` on the complements: split the set into ``n`` chunks, keep the
    first complement that still succeeds (and ``n - 1`` chunks), else split finer; it ends at
    ``n = len``, where removing any single item fails. Order is kept.
    """
    current = tuple(items)
    calls = 0
    n = 2
    while len(current) >= 2:
        size = math.ceil(len(current) / n)
        chunks = [current[i : i + size] for i in range(0, len(current), size)]
        for chunk in chunks:
            complement = tuple(x for x in current if x not in chunk)
            calls += 1
            if succeeds(complement):
                current, n = complement, max(n - 1, 2)
                break
        else:
            if n >= len(current):
                break
            n = min(2 * n, len(current))
    if len(current) == 1:
        calls += 1
        if succeeds(()):
            current = ()
    return current, calls


class _Recording:
    """A QoS policy that remembers the steps at which the policy it wraps asked (``q > 0``)."""

    def __init__(self, policy: Any) -> None:
        self.policy = policy
        self.asked: list[int] = []
        self._t = 0
        self.reads_robot_state = getattr(policy, "reads_robot_state", False)

    def reset(self, *, seed: int | None = None) -> None:
        self.policy.reset(seed=seed)
        self.asked, self._t = [], 0

    def request(self, observation: NDArray[Any], age: int) -> QosRequest:
        request: QosRequest = self.policy.request(observation, age)
        if request.reliability > 0:
            self.asked.append(self._t)
        self._t += 1
        return request


@dataclass(frozen=True)
class ClairvoyantEpisode:
    """One episode: the policy's requests and outcome, and the clairvoyant schedule's."""

    seed: int
    policy_steps: tuple[int, ...]
    policy_success: bool
    policy_requested: float
    """The policy's mean requested reliability (as the tables count it)."""
    start: str
    """What the search started from: ``"policy"``, ``"static"`` or ``"none"`` (both failed)."""
    steps: tuple[int, ...] | None
    success: bool
    requested: float
    """The clairvoyant schedule's mean requested reliability (NaN when there is none)."""
    replays: int
    episode: dict[str, Any] = field(default_factory=dict, compare=False)
    """The clairvoyant schedule's episode row
    (:func:`~codesign_mb.evaluation.evaluate.episode_record`; the policy's own where no
    schedule succeeds): what a table's ``bound`` row is made of."""


def clairvoyant_episode(
    plant: PlantSpec,
    controller: ComponentSpec,
    estimator: ComponentSpec,
    qos: ComponentSpec,
    seed: int,
    *,
    latency_steps: int = 1,
) -> ClairvoyantEpisode:
    """Run the episode ``seed`` under ``qos``, then search its clairvoyant schedule."""
    env = make_plant(plant)
    built_estimator = build("estimator", estimator, env)
    built_controller = build("controller", controller, env)
    replays: dict[frozenset[int], dict[str, Any]] = {}

    def episode(policy: Any) -> dict[str, Any]:
        wrapped = LinkObservationWrapper(env, BernoulliLink(), policy)
        return episode_record(wrapped, built_estimator, built_controller, seed)

    def replay(steps: tuple[int, ...]) -> dict[str, Any]:
        key = frozenset(steps)
        if key not in replays:
            replays[key] = episode(ScheduledQos(steps, latency_steps))
        return replays[key]

    recording = _Recording(build("qos", qos, env))
    row = episode(recording)
    policy_steps = tuple(recording.asked)
    start, steps = "none", None
    if row["success"]:
        start, steps = "policy", policy_steps
    else:
        every = tuple(range(int(row["steps"])))  # static QoS: a request at every step
        if every and replay(every)["success"]:
            start, steps = "static", every
    found = row
    if steps is not None:
        steps, _ = minimal_subset(steps, lambda s: bool(replay(s)["success"]))
        found = replay(steps)
    return ClairvoyantEpisode(
        seed=int(seed),
        policy_steps=policy_steps,
        policy_success=bool(row["success"]),
        policy_requested=float(row["mean_requested_reliability"]),
        start=start,
        steps=steps,
        success=steps is not None and bool(found["success"]),
        requested=float(found["mean_requested_reliability"]) if steps is not None else math.nan,
        replays=len(replays),
        episode=found,
    )


def clairvoyant_episodes(
    plant: PlantSpec,
    controller: ComponentSpec,
    estimator: ComponentSpec,
    qos: ComponentSpec,
    seeds: Sequence[int],
    *,
    workers: int | None = 1,
    latency_steps: int = 1,
) -> Iterator[ClairvoyantEpisode]:
    """:func:`clairvoyant_episode` of every seed, on the one process pool (completion order)."""
    tasks = [(plant, controller, estimator, qos, int(s), latency_steps) for s in seeds]
    for _, result in imap(_episode_task, tasks, workers=workers):
        yield result


def _episode_task(
    plant: PlantSpec,
    controller: ComponentSpec,
    estimator: ComponentSpec,
    qos: ComponentSpec,
    seed: int,
    latency_steps: int,
) -> ClairvoyantEpisode:
    return clairvoyant_episode(plant, controller, estimator, qos, seed, latency_steps=latency_steps)
