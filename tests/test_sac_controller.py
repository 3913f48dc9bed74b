"""The SAC controller's fast path equals stable-baselines3's predict()."""

from __future__ import annotations

import numpy as np

from codesign_mb.control.sac import SacController
from codesign_mb.robot.assets import asset_path


def test_act_equals_sb3_predict() -> None:
    controller = SacController.load(asset_path("checkpoints/stage_a/model.zip"))
    rng = np.random.default_rng(0)
    for _ in range(20):
        obs = rng.normal(size=controller._obs_shape)
        expected, _ = controller.model.predict(obs.astype(np.float32), deterministic=True)
        np.testing.assert_array_equal(controller.act(obs), expected.astype(np.float64))
