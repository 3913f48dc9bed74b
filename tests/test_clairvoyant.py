"""The clairvoyant schedule (evaluation/clairvoyant.py): delta debugging and replay, checked
against brute force and against the episodes it replays."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from codesign_mb.adaptation.base import ScheduledQos
from codesign_mb.core.registry import ComponentSpec, PlantSpec, build, make_plant
from codesign_mb.evaluation.clairvoyant import clairvoyant_episode, minimal_subset
from codesign_mb.evaluation.metrics import episode_row
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.rollout import rollout


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    n=st.integers(0, 9),
    needs=st.lists(
        st.frozensets(st.integers(0, 8), min_size=1, max_size=3), min_size=1, max_size=3
    ),
)
def test_minimal_subset_is_one_minimal_and_succeeds(n: int, needs: list[frozenset[int]]) -> None:
    """A monotone test (a hitting set: "holds an item of each need"): the result succeeds, no
    single item of it can go, it is at least the smallest set brute force finds and at most
    one item per need (each item kept is the only one of some need)."""
    items = tuple(range(n))

    def succeeds(subset: tuple[int, ...]) -> bool:
        return all(need & set(subset) or not need & set(items) for need in needs)

    found, calls = minimal_subset(items, succeeds)
    assert succeeds(found) and set(found) <= set(items) and list(found) == sorted(found)
    for x in found:
        assert not succeeds(tuple(y for y in found if y != x))
    smallest = min(
        len(c) for k in range(n + 1) for c in itertools.combinations(items, k) if succeeds(c)
    )
    assert smallest <= len(found) <= len(needs)
    assert calls <= max(1, n * n)


def test_scheduled_qos_asks_at_its_steps_and_refuses_bad_steps() -> None:
    policy = ScheduledQos((0, 2), latency_steps=2)
    policy.reset()
    asked = [policy.request(np.zeros(1), 0) for _ in range(4)]
    assert [r.reliability for r in asked] == [1.0, 0.0, 1.0, 0.0]
    assert {r.latency_steps for r in asked} == {2}
    policy.reset()
    assert policy.request(np.zeros(1), 0).reliability == 1.0
    with pytest.raises(ValueError, match="steps"):
        ScheduledQos((-1,))
    with pytest.raises(TypeError, match="steps"):
        ScheduledQos((1.5,))  # type: ignore[arg-type]


TOY = PlantSpec("toy")
PICK = ComponentSpec("toy_pick")
NONE = ComponentSpec("none")
AGE_RULE = ComponentSpec("age_rule", options={"low": 0.0, "high": 1.0, "max_age_steps": 2})


def _replay(steps: tuple[int, ...], seed: int) -> dict:
    env = make_plant(TOY)
    wrapped = LinkObservationWrapper(env, BernoulliLink(), ScheduledQos(steps, 1))
    return episode_row(
        rollout(wrapped, build("estimator", NONE, env), build("controller", PICK, env), seed=seed)
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_clairvoyant_schedule_replays_to_a_success_no_packet_of_it_can_go(seed: int) -> None:
    """On the toy plant: the policy's own requests replay its episode; the schedule found is
    a subset of them, succeeds when replayed independently, and fails without any one of it."""
    result = clairvoyant_episode(TOY, PICK, NONE, AGE_RULE, seed)
    assert result.policy_success and result.start == "policy" and result.success
    policy_row = _replay(result.policy_steps, seed)
    assert policy_row["success"]
    assert policy_row["mean_requested_reliability"] == pytest.approx(result.policy_requested)
    assert result.steps is not None and set(result.steps) <= set(result.policy_steps)
    assert len(result.steps) < len(result.policy_steps)
    row = _replay(result.steps, seed)
    assert row["success"] and row["mean_requested_reliability"] == pytest.approx(result.requested)
    for t in result.steps:
        assert not _replay(tuple(s for s in result.steps if s != t), seed)["success"]
