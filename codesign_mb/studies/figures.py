"""What the figures of the studies share: a figure without pyplot, PNG files, curve styles.

Every figure of the toolkit has one renderer, in the study that owns it (Table I's Pareto
plot in :mod:`codesign_mb.studies.table_pareto_plot`, Fig. 5 in
:mod:`codesign_mb.studies.table_figures`, Fig. 4 in :mod:`codesign_mb.studies.fig_cn`, Fig. 6
in :mod:`codesign_mb.studies.fig_wifi_figures`, sweeps in
:mod:`codesign_mb.studies.sweep_figures`);
``codesign report`` calls those same renderers. They draw on a
:class:`matplotlib.figure.Figure` (no pyplot: no global figure state, nothing left open) and
write a PNG without a timestamp, atomically.

Curves are identified by *label columns* (e.g. ``pipeline``, ``estimator``): a curve's colour
follows its labels other than ``pipeline``, its line style the pipeline (the learned one, the
paper's, solid; the model-based one dashed).
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from codesign_mb.core.results import atomic_write

__all__ = [
    "PIPELINE_LABEL",
    "PIPELINE_STYLE",
    "Styler",
    "curve_label",
    "curves",
    "integer_ticks",
    "new_figure",
    "pipeline_label",
    "save_png",
    "varying",
]

PIPELINE_LABEL: dict[str, str] = {"learned": "learned", "model_based": "model-based"}
"""How the two pipelines are named in figures and tables."""

PIPELINE_STYLE: dict[str, str] = {"learned": "-", "model_based": "--"}
"""Line style per pipeline (others: solid)."""


def new_figure(
    nrows: int = 1, ncols: int = 1, *, width: float = 5.0, height: float = 3.4, **subplots: Any
) -> tuple[Any, Any]:
    """A constrained-layout figure of ``nrows x ncols`` panels of ``width x height`` inches.

    Returns the figure and a 2-D array of axes (``squeeze=False``).
    """
    from matplotlib.figure import Figure  # no pyplot: no global figure state

    fig = Figure(figsize=(width * ncols, height * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, **subplots)
    return fig, axes


def save_png(fig: Any, path: str | Path, *, dpi: int) -> Path:
    """Write ``fig`` as a PNG at ``dpi``, atomically, without a timestamp (same bytes per run)."""
    path = Path(path)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, metadata={"Software": None})
    with atomic_write(path, "wb") as fh:
        fh.write(buffer.getvalue())
    return path


def integer_ticks(ax: Any) -> None:
    """Integer ticks on the x axis (robot counts, delays in steps)."""
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))


def pipeline_label(pipeline: Any) -> str:
    """``"model_based"`` -> ``"model-based"``; other values as they are."""
    return PIPELINE_LABEL.get(str(pipeline), str(pipeline))


def curve_label(key: Mapping[Any, Any], shown: Sequence[str]) -> str:
    """The legend entry of a curve: its values of the label columns ``shown``."""
    parts = [pipeline_label(key[c]) if c == "pipeline" else str(key[c]) for c in shown]
    return ", ".join(parts) if parts else "all"


def curves(frame: pd.DataFrame, labels: Sequence[str]) -> list[tuple[dict[str, Any], pd.DataFrame]]:
    """Group ``frame`` by ``labels`` in the order of first appearance: ``(key, rows)`` pairs."""
    labels = list(labels)
    if not labels:
        return [({}, frame)]
    out = []
    for key, group in frame.groupby(labels, sort=False, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        out.append((dict(zip(labels, key, strict=True)), group))
    return out


def varying(frame: pd.DataFrame, labels: Sequence[str]) -> list[str]:
    """The label columns whose value changes across ``frame`` (at least the first one)."""
    labels = list(labels)
    return [c for c in labels if frame[c].nunique(dropna=False) > 1] or labels[:1]


class Styler:
    """Colour per curve (from its labels other than ``pipeline``), line style per pipeline."""

    def __init__(self, labels: Sequence[str]) -> None:
        self.keys = [c for c in labels if c != "pipeline"]
        self.colors: dict[tuple[Any, ...], str] = {}

    def __call__(self, key: Mapping[Any, Any]) -> tuple[str, str]:
        ident = tuple(key.get(c) for c in self.keys)
        color = self.colors.setdefault(ident, f"C{len(self.colors) % 10}")
        return color, PIPELINE_STYLE.get(str(key.get("pipeline")), "-")
