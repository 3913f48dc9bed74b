"""The SAC controller: its fast path equals stable-baselines3's predict(); save and load."""

from __future__ import annotations

import numpy as np
import pytest

from codesign_mb.control.sac import SacController
from codesign_mb.core.registry import PlantSpec, make_plant, resolve_checkpoint
from codesign_mb.robot.assets import asset_path
from codesign_mb.stages.training import SacSpec, make_sac

TOY = PlantSpec("toy", {"horizon": 40})
TINY_SAC = SacSpec(net_arch=(32, 32), buffer_size=5_000, batch_size=32, learning_starts=50)


def test_act_equals_sb3_predict() -> None:
    controller = SacController.load(asset_path("checkpoints/stage_a/model.zip"))
    rng = np.random.default_rng(0)
    for _ in range(20):
        obs = rng.normal(size=controller._obs_shape)
        expected, _ = controller.model.predict(obs.astype(np.float32), deterministic=True)
        np.testing.assert_array_equal(controller.act(obs), expected.astype(np.float64))


def test_sac_controller_save_load_identical_actions(tmp_path) -> None:
    env = make_plant(TOY)
    model = make_sac(env, TINY_SAC, seed=3)
    model.learn(80)
    model.save(tmp_path / "m.zip")
    live, loaded = SacController(model), SacController.load(tmp_path / "m.zip")
    obs, _ = env.reset(seed=5)
    for _ in range(5):
        a, b = live.act(obs), loaded.act(obs)
        np.testing.assert_array_equal(a, b)
        obs, *_ = env.step(a)


def test_sac_controller_missing_checkpoint_is_a_clear_error(tmp_path) -> None:
    with pytest.raises(ValueError, match="train one with `codesign train a`"):
        SacController.load(tmp_path / "nope.zip")
    with pytest.raises(ValueError, match="not found"):
        resolve_checkpoint("checkpoints/does_not_exist.zip")
