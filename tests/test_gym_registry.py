"""The plants are registered with Gymnasium and pass its checker when made through their spec."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import codesign_mb.plants  # noqa: F401  (registers the envs)
from codesign_mb.plants.linear import LinearPlantEnv


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [
        ("codesign_mb/ConveyorPickPlace-v0", {}),
        ("codesign_mb/ToyConveyor-v0", {}),
        ("codesign_mb/LinearPlant-v0", {"plant": "pendulum", "horizon": 20}),
        ("codesign_mb/LinearPlant-v0", {"plant": "scalar"}),
        ("codesign_mb/BeltTracking-v0", {}),
    ],
)
def test_made_env_has_its_spec_and_passes_check_env(env_id: str, kwargs: dict) -> None:
    env = gym.make(env_id, **kwargs)
    assert env.spec is not None and env.spec.id == env_id
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings are failures too, except:
        # unbounded Box spaces are intended (a linear plant and the toy's object have no
        # natural bounds), and gymnasium asks for a normalised action space of those.
        warnings.filterwarnings("ignore", message=".*infinity.*")
        warnings.filterwarnings("ignore", message=".*normalized space.*")
        check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=3)
    again, _ = gym.make(env_id, **kwargs).reset(seed=3)
    np.testing.assert_array_equal(obs, again)  # seeded through reset(seed=) alone
    env.close()


def test_linear_plant_by_name_is_the_named_plant() -> None:
    env = gym.make("codesign_mb/LinearPlant-v0", plant="double_integrator").unwrapped
    assert isinstance(env, LinearPlantEnv) and env.plant.name == "double_integrator"
    with pytest.raises(ValueError, match="plant must be one of"):
        gym.make("codesign_mb/LinearPlant-v0", plant="nope")
