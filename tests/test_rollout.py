"""The one closed loop: ideal control, observers, and the step-by-step form all give one episode."""

from __future__ import annotations

import itertools

import numpy as np
import pandas as pd

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.control.scripted import ToyPickController
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.network import BernoulliLink, LinkObservationWrapper
from codesign_mb.plants.toy import ToyConveyor
from codesign_mb.rollout import ClosedLoop, Transition, rollout


def _env(q: float, tau: int) -> LinkObservationWrapper:
    return LinkObservationWrapper(ToyConveyor(), BernoulliLink(), StaticQos(q, tau))


def test_ideal_control_is_a_perfect_fresh_link() -> None:
    """estimator=None acts on the true state: the same episode as q = 1, tau = 0 pass-through."""
    env = _env(0.3, 2)  # a lossy, late link: ideal control must not see it
    ideal = rollout(env, None, ToyPickController.from_env(env), seed=5)
    perfect = _env(1.0, 0)
    through = rollout(perfect, PassThroughEstimator(), ToyPickController.from_env(perfect), seed=5)
    cols = ["t", "reward", "success", "estimation_error"]
    pd.testing.assert_frame_equal(ideal[cols], through[cols])
    assert (ideal["estimation_error"] == 0).all() and ideal["success"].any()
    assert ideal["delivered"].mean() < 0.6  # the link itself still lost packets


def test_observer_sees_every_step_and_step_by_step_equals_rollout() -> None:
    env = _env(0.6, 1)
    seen: list[Transition] = []
    table = rollout(env, PassThroughEstimator(), ToyPickController.from_env(env), seed=2,
                    observer=seen.append)  # fmt: skip
    assert [tr.t for tr in seen] == list(table["t"])
    np.testing.assert_allclose([tr.reward for tr in seen], table["reward"])
    for before, after in itertools.pairwise(seen):
        np.testing.assert_array_equal(before.next_observation, after.observation)
    loop = ClosedLoop(env, PassThroughEstimator(), ToyPickController.from_env(env))
    loop.reset(seed=2)
    while not loop.done:
        loop.step()
    pd.testing.assert_frame_equal(loop.table(), table)


def test_max_steps_caps_the_episode() -> None:
    env = _env(1.0, 0)
    table = rollout(env, PassThroughEstimator(), ToyPickController.from_env(env), seed=0,
                    max_steps=7)  # fmt: skip
    assert len(table) == 7 and list(table["t"]) == list(range(7))


def test_ideal_control_does_not_overwrite_the_observation() -> None:
    """The observer's y_t is what the link delivered, even when the controller sees the truth."""
    env = _env(0.0, 1)  # nothing delivered: y_t stays the prior
    seen: list[Transition] = []
    rollout(env, None, ToyPickController.from_env(env), seed=4, observer=seen.append)
    prior = env.unwrapped.remote_prior()
    remote = env.remote_slice
    for tr in seen:
        np.testing.assert_array_equal(tr.observation[remote], prior)
        assert not np.array_equal(tr.state[remote], prior)
