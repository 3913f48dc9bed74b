"""The ``bound`` reference rows of a table: the clairvoyant schedule of a co-design row.

For a co-design row named in ``TableConfig.bound``, every episode of the row (the same seeds)
is replayed from its seed and the row's own requests are pruned by delta debugging to a
1-minimal schedule that still succeeds (:mod:`~codesign_mb.evaluation.clairvoyant`; where the
row failed, from a request at every step if that succeeds). The row's success and mean
requested reliability are those of the schedules found: what a scheduler that knew the
episode would need on the row's stack, an *upper* bound on the fewest packets (requests at
times the row did not ask are not searched). Where no schedule succeeds the row's own episode
stands, a failure.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import pandas as pd

from codesign_mb.core.seeds import episode_seeds
from codesign_mb.evaluation.clairvoyant import clairvoyant_episodes
from codesign_mb.evaluation.evaluate import rows_to_table
from codesign_mb.studies.table_cost import CPU_COLUMNS
from codesign_mb.studies.table_refs import ROW_KIND, Reference, bound_reference
from codesign_mb.studies.table_rows import TablePlant

__all__ = ["bound_cells"]


def bound_cells(
    names: tuple[str, ...],
    plants: tuple[TablePlant, ...],
    per_plant: dict[str, list[Reference]],
    why: dict[tuple[str, str], str],
    *,
    trials: int,
    root_seeds: tuple[int, ...],
    workers: int,
    progress: Callable[..., Any] | None = None,
) -> dict[tuple[str, str], pd.DataFrame]:
    """The episodes table of each ``bound`` reference, by ``(plant label, row name)``.

    Appends each plant's ``bound`` references to ``per_plant`` (the rows as run on that
    plant); one whose row was not evaluated gets its reason in ``why`` and no table. The
    tables have the columns of the table's episodes (CPU times NaN: a bound is many
    replays, not a controller's cost) and ``root_seed``.
    """
    seeds = [  # (root seed, index, episode seed), as the table's episodes (run_jobs)
        (root, i, s) for root in root_seeds for i, s in enumerate(episode_seeds(root, trials))
    ]
    tables = {}
    for plant in plants:
        own = {r.row.name: r.row for r in per_plant[plant.label] if r.kind == ROW_KIND}
        for name in names:
            ref = bound_reference(own[name])
            per_plant[plant.label].append(ref)
            if (plant.label, name) in why:
                why[(plant.label, ref.row.name)] = f"not run: {name!r} was not evaluated"
                continue
            row = ref.row
            stream = clairvoyant_episodes(
                plant.spec,
                row.controller,
                row.estimator,
                row.qos,
                [s for _, _, s in seeds],
                workers=workers,
            )
            if progress is not None:
                stream = progress(stream, total=len(seeds), description=f"bound of {name}")
            found = {r.seed: r.episode for r in stream}
            episodes = [{**found[s], "episode": i, "root_seed": root} for root, i, s in seeds]
            table = rows_to_table(episodes)
            for column in CPU_COLUMNS:
                table[column] = math.nan
            tables[(plant.label, ref.row.name)] = table
    return tables
