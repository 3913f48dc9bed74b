"""Observation layouts: a name -> slice mapping of a flat observation, as plants declare them."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

__all__ = ["entry_indices", "slice_indices"]


def slice_indices(s: slice) -> NDArray[np.intp]:
    """The indices a layout slice selects; a slice without an explicit stop is an error."""
    if s.stop is None:
        raise ValueError(f"layout slices need an explicit stop, got {s}")
    return np.arange(s.start or 0, s.stop, s.step or 1)


def entry_indices(layout: Mapping[str, slice], name: str) -> NDArray[np.intp] | None:
    """The indices of the layout entry ``name``, or ``None`` when the layout has none."""
    where = layout.get(name)
    return None if where is None else slice_indices(where)
