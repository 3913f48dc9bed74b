"""The learned ideal controller of stage A (``eq_control_ideal``): a trained SB3 SAC policy."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from codesign_mb.core.checkpoints import reading_checkpoint

__all__ = ["SacController"]


class SacController:
    """A :class:`~codesign_mb.control.Controller` that runs a stable-baselines3 SAC actor.

    The actor was trained on the plant's perfect-state observation (stage A); composed with
    an estimator it gives the QoS-aware controller of ``eq_c_pol2``. Actions are the actor's
    mean (``deterministic=True``) unless asked otherwise, so a rollout is reproducible.

    Parameters
    ----------
    model:
        A loaded :class:`stable_baselines3.SAC` (or any SB3 model with ``predict``).
    deterministic:
        Use the mean action (default) instead of sampling the squashed Gaussian.
    """

    def __init__(self, model: Any, *, deterministic: bool = True) -> None:
        self.model = model
        self.deterministic = deterministic
        space = model.observation_space
        self._obs_shape = tuple(space.shape)

    @classmethod
    def load(cls, path: str | Path, *, deterministic: bool = True) -> SacController:
        """Load an SB3 ``.zip`` saved by ``codesign train a`` (actor only, on the CPU)."""
        from stable_baselines3 import SAC

        path = Path(path)
        if not path.is_file():
            raise ValueError(
                f"SAC checkpoint {str(path)!r} does not exist; train one with `codesign train a`"
            )
        with reading_checkpoint(path, remedy="train it again with `codesign train a`"):
            model = SAC.load(path, device="cpu")
        return cls(model, deterministic=deterministic)

    def reset(self, *, seed: int | None = None) -> None:
        return None

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        obs = np.asarray(observation, dtype=np.float32).reshape(self._obs_shape)
        policy = getattr(self.model, "policy", None)
        if policy is None or not hasattr(policy, "actor"):
            action, _ = self.model.predict(obs, deterministic=self.deterministic)
            return np.asarray(action, dtype=np.float64)
        # SB3's SAC predict() minus its per-call bookkeeping (training-mode switch, obs
        # preprocessing checks): the same actor, squashing and rescaling.
        import torch

        if policy.training:
            policy.set_training_mode(False)
        with torch.no_grad():
            squashed = policy.actor(torch.as_tensor(obs)[None], deterministic=self.deterministic)
        action = policy.unscale_action(squashed.numpy()[0])
        return np.asarray(action, dtype=np.float64)
