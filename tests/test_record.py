"""The per-step record (``rollout.loop._Record``) equals plain per-step dict rows."""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
import pytest

from codesign_mb.rollout.loop import _HEAD, _Record


def _reference(steps: list[tuple[int, list[Any], float, dict[str, Any]]]) -> pd.DataFrame:
    """Every row a dict of the head and the scalar, non-string ``info`` entries (pandas aligns)."""
    rows = []
    for t, head, reward, info in steps:
        row = dict(zip(_HEAD, (t, *head, reward), strict=True))
        for k, v in info.items():
            if k not in _HEAD and np.ndim(v) == 0 and not isinstance(v, str):
                row[k] = v
        rows.append(row)
    return pd.DataFrame(rows)


def _info(t: int, **extra: Any) -> dict[str, Any]:
    return {
        "success": t > 2,
        "distance": 0.1 * t,
        "pos": np.arange(3.0) + t,
        "name": "cube",
        "count": np.int64(t),
        "qos_cost": 0.5,  # in the head: not recorded twice
        "speed": np.float32(0.25),
        **extra,
    }


@pytest.mark.parametrize(
    "change",
    [
        {},  # the same keys every step (the fast path)
        {3: {"late": 1.0}},  # a scalar key appears: rows realigned, NaN before
        {2: {"pos": 4.0}},  # an array entry turns scalar
        {1: {"distance": np.zeros(2)}},  # a scalar entry turns into an array
        {4: {"extra": np.ones(3)}},  # a non-scalar key appears: same columns
    ],
)
def test_record_equals_the_dict_rows(change: dict[int, dict[str, Any]]) -> None:
    steps = []
    for t in range(6):
        info = _info(t, **change.get(t, {}))
        head = [1.0, 1, 0.5 + t, bool(t % 2), t % 3, 0.01 * t]
        steps.append((t, head, float(t), info))
    record = _Record()
    for step in steps:
        record.append(*step)
    pd.testing.assert_frame_equal(record.frame(), _reference(steps), check_exact=True)


def test_empty_record_is_an_empty_frame() -> None:
    assert _Record().frame().empty
