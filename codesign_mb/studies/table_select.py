"""Which rows and episodes a table shows: the Pareto front, the best row, Fig. 5's episode.

:func:`pareto_front` marks the rows no other row dominates (more success for no more network),
:func:`best_row` the cheapest row above a success bar, :func:`timeline_row_name` the row whose
QoS timeline Fig. 5 plots and :func:`qos_timeline` that row's first successful episode,
replayed step by step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from codesign_mb.core.registry import PlantSpec, build, make_plant
from codesign_mb.network.link import BernoulliLink
from codesign_mb.network.wrapper import LinkObservationWrapper
from codesign_mb.rollout import rollout
from codesign_mb.studies.table_rows import MODEL_FREE_CODESIGN_ROW, TablePlant, TableRow

if TYPE_CHECKING:
    from codesign_mb.studies.table import TableConfig

__all__ = ["PIPELINE_TIMELINE", "best_row", "pareto_front", "qos_timeline", "timeline_row_name"]


def pareto_front(success: ArrayLike, reliability: ArrayLike) -> NDArray[np.bool_]:
    """Which points no other point dominates (more success for no more network, or less).

    ``j`` dominates ``i`` when ``success[j] >= success[i]`` and ``reliability[j] <=
    reliability[i]``, one of them strictly; equal points do not dominate each other. NaN
    points are never on the front and dominate nothing.
    """
    s = np.asarray(success, dtype=float)
    r = np.asarray(reliability, dtype=float)
    if s.shape != r.shape or s.ndim != 1:
        raise ValueError(
            f"success and reliability must be 1-D of one length, got {s.shape}, {r.shape}"
        )
    front = np.zeros(s.shape, dtype=bool)
    valid = np.flatnonzero(np.isfinite(s) & np.isfinite(r))
    best_below = -np.inf  # best success among strictly smaller reliabilities
    for level in np.unique(r[valid]):
        group = valid[r[valid] == level]
        top = s[group].max()
        front[group] = (s[group] == top) & (top > best_below)
        best_below = max(best_below, top)
    return front


def best_row(summary: pd.DataFrame, plant: str, *, min_success: float = 0.98) -> str | None:
    """The row of ``plant`` with the least average reliability among those with at least
    ``min_success``; if none, the most successful (ties: less reliability). ``None`` if no row
    of ``plant`` was evaluated. Reference rows (column ``reference``) are not candidates."""
    mine = summary[(summary["plant"] == plant) & (summary["status"] == "ok")]
    if "reference" in mine:
        mine = mine[~mine["reference"].astype(bool)]
    if mine.empty:
        return None
    good = mine[mine["success_rate"] >= min_success - 1e-12]
    if not good.empty:
        pick = good.sort_values(
            ["mean_requested_reliability", "success_rate"], ascending=[True, False], kind="stable"
        )
    else:
        pick = mine.sort_values(
            ["success_rate", "mean_requested_reliability"], ascending=[False, True], kind="stable"
        )
    return str(pick.iloc[0]["row"])


PIPELINE_TIMELINE: dict[str, str] = {
    "model-free": MODEL_FREE_CODESIGN_ROW,  # the paper's co-design
    "model-based": "MPC + predictor, rule QoS (co-design)",
}
"""Pipeline name -> the row of its Fig. 5 (the co-design, as in the paper) with its default
rows; other tables plot :func:`best_row`."""


def timeline_row_name(config: TableConfig, summary: pd.DataFrame) -> str | None:
    """The row Fig. 5 shows: ``config.timeline_row``, else the pipeline's co-design row
    (:data:`PIPELINE_TIMELINE`, default rows only), else :func:`best_row` on the first plant."""
    if config.timeline_row:
        return config.timeline_row
    if not config.rows and config.pipeline in PIPELINE_TIMELINE:
        return PIPELINE_TIMELINE[config.pipeline]
    first = config.table_plants()[0].label
    return best_row(summary, first, min_success=config.best_min_success)


# -- Fig. 5: the QoS timeline ------------------------------------------------------------------
def qos_timeline(
    plant: TablePlant | PlantSpec, row: TableRow, episodes: pd.DataFrame
) -> tuple[pd.DataFrame, int] | None:
    """The per-step record of the row's first successful episode (and its seed), or ``None``.

    With a :class:`TablePlant`, only the episodes of that plant (column ``plant``) count.
    """

    if episodes.empty:
        return None
    mask = episodes["row"] == row.name
    spec: PlantSpec = plant if isinstance(plant, PlantSpec) else plant.spec
    if isinstance(plant, TablePlant) and "plant" in episodes:
        mask &= episodes["plant"] == plant.label
    mine = episodes[mask & episodes["success"].astype(bool)]
    if mine.empty:
        return None
    seed = int(mine.sort_values("episode").iloc[0]["seed"])
    probe = make_plant(spec)
    env = LinkObservationWrapper(probe, BernoulliLink(), build("qos", row.qos, probe))
    steps = rollout(
        env,
        build("estimator", row.estimator, probe),
        build("controller", row.controller, probe),
        seed=seed,
    )
    env.close()
    return steps, seed
