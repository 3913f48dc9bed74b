"""The multiplier ``lambda`` of stage C's constrained QoS problem (``eq_q_t_pol2``).

``lambda`` is either fixed or updated by dual ascent on the measured constraint
(:class:`DualAscentCallback`): every ``every_episodes`` finished episodes,
``lambda <- clip(lambda + eta (mean J_episode - J_max), lambda_min, lambda_max)``. The
replay buffer keeps rewards computed with older multipliers (SB3's SAC has one critic); the
multiplier moves slowly compared with the buffer's turnover, which is the usual compromise.
:func:`feasible_score` picks the policy to ship among the evaluated iterates.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

from codesign_mb.core.config import EPISODES_CAP
from codesign_mb.stages.training import require_at_least

__all__ = ["DualAscent", "DualAscentCallback", "feasible_score"]


class DualAscentCallback(BaseCallback):
    """Records finished episodes of :class:`QosAdaptationEnv`; optionally does dual ascent.

    Every ``every_episodes`` episodes: ``lambda <- clip(lambda + learning_rate (mean J -
    j_max), lam_min, lam_max)`` when ``enabled``; the multiplier and the window's mean
    constraint, success and reliability are logged (SB3 logger keys ``dual/*``) and kept in
    :attr:`history`.
    """

    def __init__(
        self,
        *,
        j_max: float,
        lam: float,
        enabled: bool = True,
        learning_rate: float = 50.0,
        every_episodes: int = 20,
        lam_min: float = 0.0,
        lam_max: float = 500.0,
    ) -> None:
        super().__init__()
        if every_episodes < 1:
            raise ValueError(f"every_episodes must be >= 1, got {every_episodes}")
        if not 0 <= lam_min <= lam_max:
            raise ValueError(f"need 0 <= lam_min <= lam_max, got {lam_min}, {lam_max}")
        self.j_max = float(j_max)
        self.lam = float(np.clip(lam, lam_min, lam_max))
        self.enabled = enabled
        self.learning_rate = float(learning_rate)
        self.every_episodes = int(every_episodes)
        self.lam_min, self.lam_max = float(lam_min), float(lam_max)
        self.window: list[dict[str, Any]] = []
        self.recent: deque[dict[str, Any]] = deque(maxlen=100)
        self.history: list[dict[str, float]] = []
        self.episodes = 0

    def _on_training_start(self) -> None:
        self.training_env.env_method("set_lambda", self.lam)

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            episode = info.get("qos_episode")
            if episode is None:
                continue
            self.episodes += 1
            self.window.append(episode)
            self.recent.append(episode)
            if len(self.window) >= self.every_episodes:
                self._update()
        return True

    def _update(self) -> None:
        constraint = float(np.mean([e["constraint"] for e in self.window]))
        if self.enabled:
            step = self.learning_rate * (constraint - self.j_max)
            self.lam = float(np.clip(self.lam + step, self.lam_min, self.lam_max))
            self.training_env.env_method("set_lambda", self.lam)
        point = {
            "steps": int(self.num_timesteps),
            "episodes": self.episodes,
            "lambda": self.lam,
            "constraint": constraint,
            "success_rate": float(np.mean([e["success"] for e in self.window])),
            "mean_reliability": float(np.mean([e["mean_reliability"] for e in self.window])),
        }
        self.history.append(point)
        for key in ("lambda", "constraint", "success_rate", "mean_reliability"):
            self.logger.record(f"dual/{key}", point[key])
        self.window = []

    def summary(self) -> dict[str, float]:
        """Mean success, reliability and constraint over the last 100 training episodes."""
        if not self.recent:
            return {"lambda": self.lam}
        return {
            "lambda": self.lam,
            "train_success_rate": float(np.mean([e["success"] for e in self.recent])),
            "train_mean_reliability": float(np.mean([e["mean_reliability"] for e in self.recent])),
            "train_constraint": float(np.mean([e["constraint"] for e in self.recent])),
        }


@dataclass(frozen=True)
class DualAscent:
    """Primal-dual update of ``lambda`` (off: ``lambda`` stays at ``env.lam``)."""

    enabled: bool = True
    learning_rate: float = 50.0
    every_episodes: int = 20
    lam_min: float = 0.0
    lam_max: float = 500.0

    def __post_init__(self) -> None:
        require_at_least(self, 1, "every_episodes", prefix="dual.", cap=EPISODES_CAP)
        require_at_least(self, 0, "learning_rate", prefix="dual.")
        if not 0 <= self.lam_min <= self.lam_max:
            raise ValueError(
                f"need 0 <= dual.lam_min <= dual.lam_max, got {self.lam_min}, {self.lam_max}"
            )


def feasible_score(point: dict[str, Any], target_success: float) -> float | None:
    """Score of an evaluation for :attr:`StageCConfig.keep_best` (higher is better).

    Feasible evaluations (``eval_success_rate >= target_success``) score ``2 - mean
    reliability`` (in [1, 2]), the others their success rate (in [0, 1)): any feasible
    policy beats every infeasible one, and the cheapest feasible one wins.
    """
    if "eval_success_rate" not in point:
        return None
    success = float(point["eval_success_rate"])
    if success >= target_success:
        return 2.0 - float(point["eval_mean_reliability"])
    return success
