"""Seeds as a contract: independent episode streams and the named seed sets of the protocol.

Anything tuned or selected (thresholds, checkpoints, hyperparameters) is chosen on the ``dev``
set; every reported number comes from the ``test`` set (DESIGN.md, evaluation protocol).
"""

from __future__ import annotations

import numpy as np

from codesign_mb.core.config import EPISODES_CAP, SEED_CAP, check_range

__all__ = ["SEED_SETS", "episode_seeds", "seed_set"]

SEED_SETS: dict[str, int] = {"test": 0, "dev": 1_000_003}
"""Named root seeds: ``test`` for reported figures, ``dev`` for tuning and selection."""


def seed_set(name: str) -> int:
    """The root seed of the named set (``ValueError`` naming the sets for an unknown name)."""
    if name not in SEED_SETS:
        raise ValueError(f"seed set must be one of {', '.join(SEED_SETS)}, got {name!r}")
    return SEED_SETS[name]


def episode_seeds(seed: int, trials: int) -> list[int]:
    """Independent episode seeds: ``SeedSequence(seed).spawn(trials)``, one integer each."""
    if isinstance(trials, bool) or int(trials) != trials or trials < 1:
        raise ValueError(f"trials must be an integer >= 1, got {trials!r}")
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    check_range("trials", trials, cap=EPISODES_CAP)
    check_range("seed", seed, cap=SEED_CAP)
    children = np.random.SeedSequence(int(seed)).spawn(int(trials))
    return [int(c.generate_state(1, dtype=np.uint32)[0]) for c in children]
