"""The reference rows of a table: what the prior alone gives, a perfect link, the paper's link,
and sending at random with a co-design row's budget.

For every stack of a table (:func:`reference_stacks`: e.g. MPC + predictor for the
model-based pipeline, SAC + MLP for the model-free one) :func:`fixed_references` gives

``blind``
    ``q = 0``: no packet is ever sent; the estimator runs on the prior alone.
``oracle``
    ``q = 1``, ``tau = 0``: every packet, at once.
``static``
    ``q = 1``, ``tau = 1``: the paper's link (its "static QoS").

and, for every row with a dynamic QoS policy (a co-design row: any QoS kind but ``static``),
:func:`random_reference` gives ``random``: the same controller and estimator with
:class:`~codesign_mb.adaptation.base.RandomQos`, which requests ``q = 1`` with probability
``p`` and ``q = 0`` otherwise, ``p`` being that row's measured mean requested reliability on
the same plant (so it needs a second pass, after the co-design rows ran) and ``tau`` its
mean requested latency, rounded. A co-design row above its ``random`` row is worth its
choice of *when* to send; one at the level of ``random`` only spends the budget.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pandas as pd

from codesign_mb.core.registry import ComponentSpec
from codesign_mb.studies.table_rows import TableRow, stack_of

__all__ = [
    "REFERENCE_KINDS",
    "ROW_KIND",
    "Reference",
    "bound_name",
    "bound_reference",
    "cell_key",
    "draw_references",
    "fixed_references",
    "random_name",
    "random_reference",
    "random_sources",
    "reference_legend",
    "reference_stacks",
    "stack_label",
]

ROW_KIND = "row"
"""The ``kind`` of a table's own rows."""

REFERENCE_KINDS: tuple[str, ...] = ("blind", "oracle", "static", "random", "bound")
"""The ``kind`` of the reference rows, in the order a table lists them."""

_FIXED_QOS: dict[str, tuple[str, dict[str, float | int]]] = {
    "blind": ("blind (q = 0)", {"reliability": 0.0, "latency_steps": 1}),
    "oracle": ("oracle (q = 1, tau = 0)", {"reliability": 1.0, "latency_steps": 0}),
    "static": ("static (q = 1, tau = 1)", {"reliability": 1.0, "latency_steps": 1}),
}

_KIND_LABELS = {
    "sac": "SAC",
    "mpc": "MPC",
    "mlp": "MLP",
    "lstm": "LSTM",
    "belt_imm": "belt IMM",
    "predictor": "predictor",
    "scripted": "scripted",
    "toy_pick": "toy pick",
}


@dataclass(frozen=True)
class Reference:
    """A reference row: the row, its kind (:data:`REFERENCE_KINDS`) and, for ``random``,
    the name of the table row whose budget it spends."""

    row: TableRow
    kind: str
    of: str = ""


def stack_label(controller: ComponentSpec, estimator: ComponentSpec) -> str:
    """``"MPC + predictor"``, ``"SAC + MLP"``, ``"MPC, no estimator"``."""
    c = _KIND_LABELS.get(controller.kind, controller.kind)
    if estimator.kind == "none":
        return f"{c}, no estimator"
    return f"{c} + {_KIND_LABELS.get(estimator.kind, estimator.kind)}"


def _spec_key(spec: ComponentSpec) -> str:
    return json.dumps(asdict(spec), sort_keys=True, default=str)


def cell_key(plant_label: str, row: TableRow) -> tuple[str, str, str, str]:
    """What a (plant, row) cell runs: equal keys give the same episodes (same seeds)."""
    return (
        plant_label,
        _spec_key(row.controller),
        _spec_key(row.estimator),
        _spec_key(row.qos),
    )


def reference_stacks(rows: tuple[TableRow, ...]) -> list[tuple[ComponentSpec, ComponentSpec]]:
    """The (controller, estimator) stacks that get ``blind``, ``oracle`` and ``static`` rows.

    The distinct stacks of the rows that are not mixed (:func:`stack_of`; all rows if every
    one is mixed), in row order, without a controller's no-estimator stack when that
    controller also comes with an estimator (the reference is the full stack: SAC + MLP for
    the model-free pipeline, MPC + predictor for the model-based one, both for ``all``).
    Stacks of the same kinds (e.g. the hybrid and the model-free co-designs' own stage-D
    MLPs) share the first one's references, which are named by the kinds alone.
    """
    pure = [r for r in rows if stack_of(r) != "mixed"] or list(rows)
    stacks: dict[tuple[str, str], tuple[ComponentSpec, ComponentSpec]] = {}
    labels: set[str] = set()
    for r in pure:
        key = (_spec_key(r.controller), _spec_key(r.estimator))
        label = stack_label(r.controller, r.estimator)
        if key not in stacks and label not in labels:
            stacks[key] = (r.controller, r.estimator)
            labels.add(label)
    with_estimator = {c for (c, _), (_, e) in stacks.items() if e.kind != "none"}
    return [
        (c, e) for (ck, _), (c, e) in stacks.items() if e.kind != "none" or ck not in with_estimator
    ]


def fixed_references(rows: tuple[TableRow, ...]) -> tuple[Reference, ...]:
    """``blind``, ``oracle`` and ``static`` for each of :func:`reference_stacks`."""
    refs = []
    for controller, estimator in reference_stacks(rows):
        label = stack_label(controller, estimator)
        for kind, (what, options) in _FIXED_QOS.items():
            qos = ComponentSpec("static", options=dict(options))
            refs.append(Reference(TableRow(f"{label}, {what}", controller, estimator, qos), kind))
    return tuple(refs)


def random_sources(rows: tuple[TableRow, ...]) -> tuple[TableRow, ...]:
    """The rows that get a ``random`` reference: those whose QoS policy is not static."""
    return tuple(r for r in rows if r.qos.kind != "static")


def random_name(row: TableRow) -> str:
    """The name of ``row``'s ``random`` reference."""
    return f"random, same PDR as: {row.name}"


def random_reference(row: TableRow, probability: float, latency_steps: float) -> Reference:
    """``row``'s stack with :class:`~codesign_mb.adaptation.base.RandomQos` at ``probability``
    (``row``'s measured mean requested reliability) and ``latency_steps`` (its mean, rounded)."""
    if not (math.isfinite(probability) and math.isfinite(latency_steps)):
        raise ValueError(
            f"row {row.name!r} has no finite mean reliability and latency "
            f"({probability}, {latency_steps})"
        )
    qos = ComponentSpec(
        "random",
        options={
            "probability": min(max(float(probability), 0.0), 1.0),
            "latency_steps": round(latency_steps),
        },
    )
    return Reference(
        TableRow(random_name(row), row.controller, row.estimator, qos), "random", of=row.name
    )


def bound_name(row: TableRow) -> str:
    """The name of ``row``'s ``bound`` reference."""
    return f"clairvoyant schedule of: {row.name}"


def bound_reference(row: TableRow) -> Reference:
    """``row``'s ``bound`` reference: per episode, the 1-minimal clairvoyant schedule found
    from ``row``'s own requests (:mod:`~codesign_mb.evaluation.clairvoyant`), on its stack."""
    return Reference(
        TableRow(bound_name(row), row.controller, row.estimator, row.qos), "bound", of=row.name
    )


# -- how the Pareto figure draws them (table_pareto_plot.plot_pareto) --------------------------
_MARKERS = {"blind": "v", "oracle": "*", "static": "D", "random": "X", "bound": "H"}
_LABELS = {
    "blind": "blind (q = 0)",
    "oracle": "oracle (q = 1, τ = 0)",
    "static": "static (q = 1, τ = 1)",
    "random": "random (a co-design row's PDR)",
    "bound": "clairvoyant schedule (a co-design row's episodes)",
}
_STACK_GREYS = ("dimgray", "darkgray", "black", "silver")


def draw_references(
    ax: Any, refs: pd.DataFrame, greys: dict[tuple[str, ...], str], kinds: set[str]
) -> None:
    """Draw reference rows on ``ax``: a grey marker per kind with its interval, and per stack
    a dotted line from ``blind`` through the ``random`` points to ``static``.

    ``refs`` has the summary's columns ``kind``, ``success_rate``, ``success_ci_low``,
    ``success_ci_high``, ``mean_requested_reliability`` (and ``controller``, ``estimator``
    for the stacks). ``greys`` (stack -> grey, kept across panels) and ``kinds`` (the kinds
    drawn) are filled in for :func:`reference_legend`.
    """
    x = refs["mean_requested_reliability"].astype(float)
    refs = refs[np.isfinite(x) & np.isfinite(refs["success_rate"].astype(float))]
    pair = [c for c in ("controller", "estimator") if c in refs.columns] or ["kind"]
    for _, stack in refs.groupby(pair, sort=False):
        key = tuple(str(stack.iloc[0][c]) for c in pair)
        grey = greys.setdefault(key, _STACK_GREYS[len(greys) % len(_STACK_GREYS)])
        for _, r in stack.iterrows():
            kind = str(r["kind"])
            y, low, high = r["success_rate"], r["success_ci_low"], r["success_ci_high"]
            ax.errorbar(
                r["mean_requested_reliability"],
                y,
                yerr=[[y - low], [high - y]] if np.isfinite([low, high]).all() else None,
                fmt=_MARKERS.get(kind, "P"),
                color=grey,
                mfc="none" if kind == "static" else grey,
                ms={"oracle": 9, "static": 10}.get(kind, 7),
                capsize=2,
                lw=0.8,
                alpha=0.85,
                zorder=3,  # above the rows: a reference often sits on a row (static: q = 1)
            )
            kinds.add(kind)
        line = stack[stack["kind"].isin(("blind", "random", "static"))]
        if len(line) > 1:
            line = line.sort_values("mean_requested_reliability", kind="stable")
            x_line, y_line = line["mean_requested_reliability"], line["success_rate"]
            ax.plot(x_line, y_line, ls=":", color=grey, lw=1.2, zorder=1)


def reference_legend(kinds: set[str], greys: dict[tuple[str, ...], str]) -> dict[str, Any]:
    """Legend label -> handle: each reference kind drawn, each stack's dotted line."""
    from matplotlib.lines import Line2D

    out: dict[str, Any] = {}
    for kind, label in _LABELS.items():
        if kind in kinds:
            fill = "none" if kind == "static" else "dimgray"
            out[f"ref.: {label}"] = Line2D(
                [], [], ls="", marker=_MARKERS[kind], color="dimgray", mfc=fill
            )
    for stack, grey in greys.items():
        name = " ".join(stack)
        if len(stack) == 2:
            name = stack_label(ComponentSpec(stack[0]), ComponentSpec(stack[1]))
        out[f"ref.: random sending, {name}"] = Line2D([], [], ls=":", color=grey)
    return out
