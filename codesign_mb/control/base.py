"""The ideal controller interface ``pi_c`` (``eq_control_ideal``)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

__all__ = ["Controller"]


@runtime_checkable
class Controller(Protocol):
    """Maps the plant's (estimated) observation to an action; designed for perfect state."""

    def reset(self, *, seed: int | None = None) -> None:
        """Start an episode."""
        ...

    def act(self, observation: NDArray[np.float64]) -> NDArray[np.float64]:
        """The action for the plant-layout observation ``observation``."""
        ...
