"""Table I (``tab_p``), the head-to-head table and Fig. 5 (``fig_lat``) of paper.tex, any pipeline.

A table is a list of :class:`~codesign_mb.studies.table_rows.TableRow` — a name and a
``{controller, estimator, qos}`` triple of :class:`~codesign_mb.core.registry.ComponentSpec` —
evaluated on one or more plants (:class:`~codesign_mb.studies.table_rows.TablePlant`, e.g. the
conveyor at 0.2 and 0.6 m/s and with a variable belt) on the same seeded episodes (every row
and plant gets the episode seeds of ``seed``). All episodes of all rows and plants share one
pool of worker processes (:func:`~codesign_mb.evaluation.evaluate.run_jobs`); cells that run
the same components on the same plant run once.

Every table of a pipeline's default rows also gets its reference rows
(:mod:`~codesign_mb.studies.table_refs`; ``TableConfig.references``): ``blind`` (``q = 0``),
``oracle`` (``q = 1``, ``tau = 0``) and ``static`` (``q = 1``, ``tau = 1``) for each stack of
the table, and ``random`` for each co-design row (any QoS policy but ``static``): the same
stack sending each packet with probability ``p``, that row's measured mean requested
reliability on the same plant. The ``random`` rows run in a second pool, after the others.
Co-design rows named in ``TableConfig.bound`` also get a ``bound`` row, the clairvoyant
schedule of each of their episodes (:mod:`~codesign_mb.studies.table_bound`).

Columns of the summary (one row per table row and plant):

``row``, ``plant``, ``scenario``
    The row's name, the plant's label and its scenario (the label if it is not one).
``kind``, ``reference``, ``reference_of``
    ``"row"`` for the table's own rows, else the reference kind (``blind``, ``oracle``,
    ``static``, ``random``) with ``reference`` true; ``reference_of``: the row whose
    budget a ``random`` row spends.
``success_rate``, ``success_ci_low``, ``success_ci_high``
    Success with its 95 % Wilson interval.
``mean_requested_reliability``, ``delivered_fraction``
    The paper's "average PDR" and the fraction of packets delivered.
``train_env_steps``, ``train_wall_time_s``, ``train_sources``
    Training cost of the row (:func:`~codesign_mb.studies.table_cost.training_cost`): the
    ``training.json`` next to every learned checkpoint the row uses, followed through what each
    was trained from (a stage-D estimator continues stage B's under stage C's policy; a stage-D
    QoS policy is warm-started from stage C; a stage-B estimator is trained on the stage-A
    controller's episodes), each file counted once. Model-based components (MPC, predictor,
    the covariance rule) count 0: the rule's threshold is tuned by ``codesign tune`` on the
    ``dev`` seeds and that cost is in the tuned file, not counted here.
``qos_options``, ``rule_threshold_m``, ``rule_threshold_source``
    The QoS policy's options as run on this plant; the covariance rule's threshold, resolved
    per plant (:func:`~codesign_mb.studies.table_rows.row_for_plant`: tuned on ``dev`` for
    the plant's scenario, else the default) and where it came from. ``table.json`` records
    every row as run on each plant (``extra.rows``).
``controller_cpu_ms``, ``estimator_cpu_ms``, ``qos_cpu_ms``, ``cpu_ms_per_step``
    CPU time (``time.process_time``, ms) per control step of ``act``, ``estimate`` and
    ``request`` (the QoS policy runs at the edge), and their sum.
``mpc_failures``
    Failed MPC solves, summed over the episodes (NaN for a row without an MPC).
``est_error_mm_<phase>``, ``nees_<phase>`` (with ``_low``, ``_high``), ``nees_state_<phase>``, ...
    The object's estimation error per phase of the episode and the estimator's NEES with its
    band under a consistent filter, pooled over the steps
    (:mod:`codesign_mb.evaluation.phase_metrics`; NEES NaN without a covariance); in the JSON
    and the summary table, not in the Markdown.
``status``
    ``"ok"``, or why the row was not evaluated (``"missing checkpoint: ..."``): a row whose
    checkpoint is absent is kept in the table with no figures (``on_missing="skip"``, the
    default) or stops the run before any episode (``on_missing="error"``). A missing
    checkpoint is never replaced by another one.
``pareto``
    Whether the row is on the Pareto front of its plant's own rows (no other row has at least
    its success with at most its average reliability, one of them strictly;
    :func:`~codesign_mb.studies.table_select.pareto_front`); a reference row never is.

:data:`~codesign_mb.studies.table_rows.PIPELINES` maps a pipeline name to its default rows and
:data:`~codesign_mb.studies.table_rows.PIPELINE_PLANTS` to its default plants (``model-free``:
the paper's Table I, at 0.2 m/s only; ``model-based``: the ``realistic`` scenario; ``all``: the
head-to-head rows on ``realistic``, at both belt speeds and on the variable belt). Rows and
plants can be given in a config file (``[[rows]]``, ``plants``).

Fig. 5 is the requested reliability along one successful episode, on the first plant, of the
co-design row of the ``model-free`` or ``model-based`` pipeline (as in the paper), or of the
best row of other tables (:func:`~codesign_mb.studies.table_select.best_row`: the least
average reliability among rows with >= 98 % success, else the most successful row). The
files of ``codesign table`` (the summary, its Markdown, the Pareto plot and Fig. 5) are
written by
:func:`codesign_mb.studies.table_figures.write_table_outputs`.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import pandas as pd

from codesign_mb.core.config import EPISODES_CAP, SEED_CAP, WORKERS_CAP, check_range, from_mapping
from codesign_mb.core.records import RecordStore
from codesign_mb.core.registry import ComponentSpec, PlantSpec, plant_factory
from codesign_mb.evaluation.evaluate import rows_to_table, run_jobs
from codesign_mb.plants.scenarios import SCENARIOS, get_scenario, scenario_options
from codesign_mb.studies.table_bound import bound_cells
from codesign_mb.studies.table_cost import (
    TrainingCost,
    incompatible_checkpoints,
    missing_checkpoints,
    timed_factory,
    training_cost,
)
from codesign_mb.studies.table_records import missing_record, record
from codesign_mb.studies.table_refs import (
    ROW_KIND,
    Reference,
    bound_name,
    cell_key,
    fixed_references,
    random_name,
    random_reference,
    random_sources,
)
from codesign_mb.studies.table_rows import (
    PIPELINE_PLANTS,
    PIPELINES,
    PLANT_PRESETS,
    TablePlant,
    TableRow,
    row_for_plant,
)
from codesign_mb.studies.table_select import pareto_front

__all__ = ["TableConfig", "run_table"]


# -- config -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class TableConfig:
    """What ``codesign table`` evaluates.

    Parameters
    ----------
    plants:
        The plants: names of :data:`PLANT_PRESETS` (``"0.2"``, ``"0.6"``, ``"variable"``) or
        of conveyor scenarios (:data:`~codesign_mb.plants.scenarios.SCENARIOS`, labelled by
        their name), or :class:`TablePlant` tables; empty means the pipeline's
        (:data:`PIPELINE_PLANTS`).
    plant:
        One plant instead of ``plants`` (labelled from its options; kept for older configs).
    scenario:
        One conveyor scenario instead of ``plants`` (``codesign table --scenario NAME``);
        ``""``: the pipeline's plants.
    rows:
        The rows; empty means the default rows of ``pipeline``.
    pipeline:
        A key of :data:`PIPELINES`.
    trials:
        Episodes per row and plant (the same seeds for every row and plant).
    seed:
        Root seed of the episodes.
    seeds:
        Several root seeds instead of ``seed``: ``trials`` episodes from each, pooled per row
        (its interval is over all of them) with each seed's success rate in
        ``success_by_seed`` (e.g. ``(0, 1, 2)``: three evaluation seeds; ``()``: ``seed``).
    workers:
        Worker processes, shared by all rows and plants.
    timeline_row:
        Row whose successful episode is plotted (Fig. 5); ``""``: see
        :func:`~codesign_mb.studies.table_select.timeline_row_name`.
    best_min_success:
        Success rate a row needs to be the best one
        (:func:`~codesign_mb.studies.table_select.best_row`).
    on_missing:
        ``"skip"``: a row with a missing checkpoint is listed with its ``status`` and no
        figures; ``"error"``: the run stops before any episode, naming every missing one.
    references:
        Whether to add the reference rows (:mod:`~codesign_mb.studies.table_refs`: ``blind``,
        ``oracle``, ``static`` per stack, ``random`` per co-design row); ``None``: for a
        pipeline's default rows, not for ``rows`` given explicitly.
    bound:
        Co-design rows (names) that get a ``bound`` reference: the clairvoyant schedule of
        each of their episodes (:mod:`~codesign_mb.studies.table_bound`); a few replays an
        episode, so opt-in.
    """

    plants: tuple[TablePlant | str, ...] = ()
    plant: PlantSpec | None = None
    scenario: str = ""
    rows: tuple[TableRow, ...] = ()
    pipeline: str = "model-free"
    trials: int = 100
    seed: int = 0
    seeds: tuple[int, ...] = ()
    workers: int = 1
    timeline_row: str = ""
    best_min_success: float = 0.98
    on_missing: str = "skip"
    references: bool | None = None
    bound: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.pipeline not in PIPELINES:
            raise ValueError(
                f"pipeline must be one of {', '.join(PIPELINES)}, got {self.pipeline!r}"
            )
        if self.trials < 1:
            raise ValueError(f"trials must be >= 1, got {self.trials}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        check_range("trials", self.trials, cap=EPISODES_CAP)
        check_range("workers", self.workers, cap=WORKERS_CAP)
        check_range("seed", self.seed, ge=0, cap=SEED_CAP)
        object.__setattr__(self, "seeds", tuple(int(s) for s in self.seeds))
        for s in self.seeds:
            check_range("seeds", s, ge=0, cap=SEED_CAP)
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds must be distinct, got {self.seeds}")
        if not 0.0 <= self.best_min_success <= 1.0:
            raise ValueError(f"best_min_success must be in [0, 1], got {self.best_min_success}")
        if self.on_missing not in ("skip", "error"):
            raise ValueError(f"on_missing must be 'skip' or 'error', got {self.on_missing!r}")
        if sum(map(bool, (self.plant is not None, self.plants, self.scenario))) > 1:
            raise ValueError("give one of plants, plant or scenario")
        if self.scenario:
            get_scenario(self.scenario)  # an unknown name names the choices
        if isinstance(self.plant, Mapping):
            object.__setattr__(self, "plant", from_mapping(PlantSpec, self.plant, where="plant"))
        object.__setattr__(self, "plants", tuple(_plant(p, i) for i, p in enumerate(self.plants)))
        rows = tuple(
            r if isinstance(r, TableRow) else from_mapping(TableRow, r, where=f"rows[{i}]")
            for i, r in enumerate(self.rows)
        )
        object.__setattr__(self, "rows", rows)
        own = [r.name for r in self.table_rows()]
        names = list(own)
        if self.with_references():
            names += [ref.row.name for ref in fixed_references(self.table_rows())]
            names += [random_name(r) for r in random_sources(self.table_rows())]
        object.__setattr__(self, "bound", _bound_names(self.bound, self.table_rows()))
        names += [bound_name(r) for r in self.table_rows() if r.name in self.bound]
        if len(set(names)) != len(names):
            raise ValueError(f"row names must be unique, got {names}")
        if self.timeline_row and self.timeline_row not in own:
            raise ValueError(f"timeline_row {self.timeline_row!r} is not a row: {own}")
        labels = [p.label for p in self.table_plants()]
        if len(set(labels)) != len(labels):
            raise ValueError(f"plant labels must be unique, got {labels}")

    def root_seeds(self) -> tuple[int, ...]:
        """The root seeds the episodes come from: ``seeds``, else ``(seed,)``."""
        return self.seeds or (self.seed,)

    def table_rows(self) -> tuple[TableRow, ...]:
        return self.rows or PIPELINES[self.pipeline](self.scenario)

    def with_references(self) -> bool:
        """Whether the table gets its reference rows (see ``references``)."""
        return not self.rows if self.references is None else bool(self.references)

    def table_plants(self) -> tuple[TablePlant, ...]:
        if self.plant is not None:
            return (TablePlant.of(self.plant),)
        if self.scenario:
            return (_scenario_plant(self.scenario),)
        if self.plants:
            return self.plants  # type: ignore[return-value]  # normalised in __post_init__
        return tuple(_plant(k, i) for i, k in enumerate(PIPELINE_PLANTS[self.pipeline]))


def _bound_names(value: Any, rows: tuple[TableRow, ...]) -> tuple[str, ...]:
    """``bound`` checked: distinct names of co-design rows (not static QoS)."""
    if isinstance(value, str) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"bound must be a list of row names, got {value!r}")
    names = tuple(value)
    codesign = [r.name for r in random_sources(rows)]
    unknown = [n for n in names if n not in codesign]
    if unknown:
        raise ValueError(f"bound must name co-design rows among {codesign}, got {unknown!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"bound must name distinct rows, got {names!r}")
    return names


def _plant(value: Any, index: int) -> TablePlant:
    if isinstance(value, TablePlant):
        return value
    if isinstance(value, str):
        if value in SCENARIOS and value not in PLANT_PRESETS:
            return _scenario_plant(value)
        if value not in PLANT_PRESETS:
            raise ValueError(
                f"plants[{index}] must be one of {', '.join([*PLANT_PRESETS, *SCENARIOS])} or a "
                f"table with a label, got {value!r}"
            )
        return PLANT_PRESETS[value]
    if isinstance(value, Mapping):
        return from_mapping(TablePlant, value, where=f"plants[{index}]")
    raise ValueError(f"plants[{index}] must be a name or a table, got {value!r}")


def _scenario_plant(name: str) -> TablePlant:
    """The conveyor of scenario ``name``, labelled by the name."""
    return TablePlant(name, "conveyor", scenario_options(name), scenario=name)


# -- the run ------------------------------------------------------------------------------------
def run_table(
    config: TableConfig,
    *,
    progress: Callable[..., Any] | None = None,
    store: RecordStore | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Evaluate every row on every plant; return the summary and all episodes.

    Rows with a missing checkpoint are skipped with a ``RuntimeWarning`` and a ``status``
    (``on_missing="skip"``) or raise ``ValueError`` naming them all (``"error"``). The
    summary has one row per (plant, row) in the config's order, each plant's reference rows
    after its own (:meth:`TableConfig.with_references`; see the module docstring); the
    episodes table one row per episode, with ``plant`` and ``row``. The table's rows and the
    fixed references share one pool; the ``random`` references, which need their co-design
    row's measured reliability, a second one. ``progress`` wraps the stream of finished
    episodes: ``progress(stream, total=..., description=...)``. ``store`` keeps every
    finished episode and gives back those of an earlier run
    (:func:`~codesign_mb.evaluation.evaluate.run_jobs`).
    """
    rows, plants = config.table_rows(), config.table_plants()
    listed = [Reference(row, ROW_KIND) for row in rows]
    if config.with_references():
        listed += fixed_references(rows)
    missing = _missing_rows(tuple(r.row for r in listed), config.on_missing)
    why = {
        (p.label, name): f"missing checkpoint: {', '.join(paths)}"
        for p in plants
        for name, paths in missing.items()
    }
    why.update(_incompatible_cells(listed, plants, missing))
    per_plant = {  # the rows as they run on each plant (the rule's tuned threshold)
        p.label: [dataclasses.replace(r, row=row_for_plant(r.row, p)) for r in listed]
        for p in plants
    }
    cells = [
        (p, r.row) for p in plants for r in per_plant[p.label] if (p.label, r.row.name) not in why
    ]
    tables = _run_cells(cells, config, progress, "table episodes", store)
    if config.with_references():
        randoms = _random_references(rows, plants, tables, per_plant, why)
        tables.update(_run_cells(randoms, config, progress, "random reference episodes", store))
    tables.update(
        bound_cells(
            config.bound,
            plants,
            per_plant,
            why,
            trials=config.trials,
            root_seeds=config.root_seeds(),
            workers=config.workers,
            progress=progress,
        )
    )
    costs: dict[str, TrainingCost] = {}
    summaries, episodes = [], []
    for plant in plants:
        for ref in per_plant[plant.label]:
            table = tables.get((plant.label, ref.row.name))
            if table is None:
                summaries.append(missing_record(plant, ref, why[(plant.label, ref.row.name)]))
                continue
            cost = costs.setdefault(ref.row.name, training_cost(ref.row))
            summaries.append(record(plant, ref, table, cost))
            episodes.append(table.assign(plant=plant.label, row=ref.row.name))
    summary_frame = _mark_pareto(pd.DataFrame(summaries))
    episode_frame = (
        pd.concat(episodes, ignore_index=True)
        if episodes
        else pd.DataFrame(columns=["plant", "row"])
    )
    return summary_frame, episode_frame


def _random_references(
    rows: tuple[TableRow, ...],
    plants: tuple[TablePlant, ...],
    tables: Mapping[tuple[str, str], pd.DataFrame],
    per_plant: dict[str, list[Reference]],
    why: dict[tuple[str, str], str],
) -> list[tuple[TablePlant, TableRow]]:
    """The cells of the ``random`` references, at each co-design row's measured budget.

    Appends every plant's ``random`` references to ``per_plant``; one whose co-design row was
    not evaluated gets its reason in ``why`` and no cell.
    """
    cells = []
    for plant in plants:
        for row in random_sources(rows):
            source = tables.get((plant.label, row.name))
            if source is None:
                idle = TableRow(random_name(row), row.controller, row.estimator, _RANDOM)
                per_plant[plant.label].append(Reference(idle, "random", of=row.name))
                why[(plant.label, idle.name)] = f"not run: {row.name!r} was not evaluated"
                continue
            # A request only costs when the edge has a packet to send (LinkObservationWrapper):
            # random draws on every step, so it asks budget / perceived fraction per step.
            perceived = (
                float(source["perceived_fraction"].mean())
                if "perceived_fraction" in source
                else 1.0
            )
            ref = random_reference(
                row,
                float(source["mean_requested_reliability"].mean()) / max(perceived, 1e-9),
                float(source["mean_latency_steps"].mean()),
            )
            per_plant[plant.label].append(ref)
            cells.append((plant, ref.row))
    return cells


_RANDOM = ComponentSpec("random")


def _missing_rows(rows: tuple[TableRow, ...], on_missing: str) -> dict[str, list[str]]:
    """Row name -> its missing checkpoints (rows with some); warns, or raises for ``"error"``."""
    found = {row.name: missing_checkpoints(row) for row in rows}
    missing = {name: paths for name, paths in found.items() if paths}
    if missing and on_missing == "error":
        listed = "; ".join(f"{name!r}: {', '.join(paths)}" for name, paths in missing.items())
        raise ValueError(
            f"missing checkpoints ({listed}); train them with `codesign train`, or run with "
            "--on-missing skip"
        )
    for name, paths in missing.items():
        warnings.warn(
            f"row {name!r} skipped: missing checkpoint {', '.join(paths)}",
            RuntimeWarning,
            stacklevel=3,
        )
    return missing


def _incompatible_cells(
    listed: list[Reference], plants: tuple[TablePlant, ...], missing: Mapping[str, Any]
) -> dict[tuple[str, str], str]:
    """(plant, row) -> why, for rows whose checkpoints cannot read the plant's observation.

    Skipped with a ``RuntimeWarning`` and a status, like a missing checkpoint: the shipped
    learned checkpoints were trained on the ``paper`` scenario, whose packet carries the
    object's velocity; ``codesign train --scenario NAME`` trains them for another.
    """
    why = {}
    for plant in plants:
        for ref in listed:
            if ref.row.name in missing:
                continue
            found = incompatible_checkpoints(ref.row, plant.spec)
            if found:
                why[(plant.label, ref.row.name)] = f"incompatible checkpoint: {', '.join(found)}"
                warnings.warn(
                    f"row {ref.row.name!r} skipped on {plant.label}: {', '.join(found)}; "
                    "train for this plant with `codesign train --scenario NAME`",
                    RuntimeWarning,
                    stacklevel=3,
                )
    return why


def _run_cells(
    cells: list[tuple[TablePlant, TableRow]],
    config: TableConfig,
    progress: Callable[..., Any] | None,
    description: str,
    store: RecordStore | None,
) -> dict[tuple[str, str], pd.DataFrame]:
    """The episodes table of every (plant, row) cell, by ``(plant label, row name)``.

    All in one pool of workers; cells that run the same components on the same plant (a
    reference equal to a table row, e.g. ``static``) are run once and share the episodes.
    """
    keys = [cell_key(plant.label, row) for plant, row in cells]
    unique = list(dict.fromkeys(keys))
    first = {key: cells[keys.index(key)] for key in unique}
    roots = config.root_seeds()
    cells_run = [(first[key], root) for key in unique for root in roots]
    jobs = [
        (
            timed_factory("controller", row.controller),
            timed_factory("estimator", row.estimator),
            timed_factory("qos", row.qos),
            plant_factory(plant.spec),
            config.trials,
            root,
        )
        for (plant, row), root in cells_run
    ]
    results: list[list[dict[str, Any]]] = [[] for _ in unique]
    if jobs:
        done = run_jobs(jobs, workers=config.workers, store=store)
        if progress is not None:
            done = progress(done, total=len(jobs) * config.trials, description=description)
        for j, episode in done:  # a cell's episodes pooled over the root seeds
            results[j // len(roots)].append({**episode, "root_seed": roots[j % len(roots)]})
    tables = [rows_to_table(r) for r in results]
    return {
        (plant.label, row.name): tables[unique.index(key)]
        for (plant, row), key in zip(cells, keys, strict=True)
    }


def _mark_pareto(summary: pd.DataFrame) -> pd.DataFrame:
    """Add the ``pareto`` column: the front of each plant's own rows
    (:func:`~codesign_mb.studies.table_select.pareto_front`); reference rows never are."""
    summary["pareto"] = False
    for label in summary["plant"].unique():
        mask = ((summary["plant"] == label) & ~summary["reference"].astype(bool)).to_numpy()
        summary.loc[mask, "pareto"] = pareto_front(
            summary.loc[mask, "success_rate"],
            summary.loc[mask, "mean_requested_reliability"],
        )
    return summary
