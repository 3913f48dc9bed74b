"""What Table I compares: rows (a ``{controller, estimator, qos}`` triple) and plants.

:func:`model_free_rows` are the paper's Table I rows, :func:`model_based_rows` their
model-based counterparts (MPC, the delay-compensating predictor, the covariance rule) and
:func:`all_rows` the head-to-head grid; :data:`PIPELINES` names them. :data:`PLANT_PRESETS`
are the conveyor plants of the tables (both belt speeds of the paper and the variable belt:
scenarios of :data:`~codesign_mb.plants.scenarios.SCENARIOS` under their short names),
:data:`PIPELINE_PLANTS` each pipeline's default ones. The run is
:func:`codesign_mb.studies.table.run_table`.

The covariance rule of these rows has ``threshold_m = "tuned"``
(:data:`~codesign_mb.studies.tuned.TUNED`): its threshold depends on the plant and is
resolved when a row meets one (:func:`row_for_plant`): the threshold ``codesign tune`` chose
for that plant on the ``dev`` seeds (:mod:`codesign_mb.studies.tuned`), else
:data:`~codesign_mb.studies.tuned.RULE_THRESHOLD_DEFAULT_M`. A row given with a number keeps it.

A learned QoS policy is labelled by what it sees (:func:`stack_of`, the row names): a
*model-free* one ``(y_{t-1}, zeta_{t-1})`` and features computed from their history without a
model (``held_history``, ``elapsed_time``); a *hybrid* one also the features of a model-based
predictor replica at the edge (``predictor_std``: the shipped stage-C/D policies).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from codesign_mb.core.config import from_mapping
from codesign_mb.core.registry import ComponentSpec, PlantSpec
from codesign_mb.plants.conveyor import ConveyorConfig
from codesign_mb.plants.scenarios import get_scenario, scenario_options
from codesign_mb.studies.tuned import TUNED, rule_threshold

__all__ = [
    "CODESIGN_RULE_ROW",
    "HYBRID_CODESIGN_ROW",
    "LEARNED_SCENARIOS",
    "MODEL_FREE_CODESIGN_ROW",
    "PIPELINES",
    "PIPELINE_PLANTS",
    "PLANNER_ROW",
    "PLANT_PRESETS",
    "TablePlant",
    "TableRow",
    "all_rows",
    "codesign_rule_row",
    "model_based_rows",
    "model_free_rows",
    "qos_features_stack",
    "row_for_plant",
    "stack_of",
]


@dataclass(frozen=True)
class TableRow:
    """One row: a name, the three components, and the paper's figures for it (if any)."""

    name: str
    controller: ComponentSpec
    estimator: ComponentSpec
    qos: ComponentSpec
    paper_success_rate: float | None = None
    paper_mean_reliability: float | None = None
    threshold_source: str = ""
    """Where the rule's ``threshold_m`` came from, set by :func:`row_for_plant` (``""``: not
    resolved, or no rule)."""

    def __post_init__(self) -> None:
        for role in ("controller", "estimator", "qos"):
            value = getattr(self, role)
            if isinstance(value, Mapping):
                object.__setattr__(
                    self, role, from_mapping(ComponentSpec, value, where=f"rows.{role}")
                )


@dataclass(frozen=True)
class TablePlant:
    """A plant of the table, with the label of its ``plant`` column.

    Parameters
    ----------
    label:
        Shown in the ``plant`` column and the figures, e.g. ``"0.2 m/s"``.
    name, options:
        The :class:`~codesign_mb.core.registry.PlantSpec`.
    scenario:
        The conveyor scenario this plant is (``""``: none named); with no ``options``, the
        scenario's, else they must give the scenario's config.
    """

    label: str
    name: str = "conveyor"
    options: dict[str, Any] = field(default_factory=dict)
    scenario: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.label, str) or not self.label:
            raise ValueError(f"plant label must be a non-empty string, got {self.label!r}")
        if self.scenario:
            preset = get_scenario(self.scenario)  # an unknown name names the choices
            if self.name != "conveyor":
                raise ValueError(f"scenario {self.scenario!r} is a conveyor, not {self.name!r}")
            if not self.options:
                object.__setattr__(self, "options", dict(preset.options))
            elif preset.config() != from_mapping(ConveyorConfig, self.options):
                raise ValueError(
                    f"plant {self.label!r}: options are not those of scenario {self.scenario!r}"
                )
        self.spec  # validates name and options  # noqa: B018

    @property
    def spec(self) -> PlantSpec:
        return PlantSpec(self.name, dict(self.options))

    @classmethod
    def of(cls, spec: PlantSpec) -> TablePlant:
        """A plant labelled from its spec: ``"0.2 m/s"``, ``"variable (0.6 m/s)"``, ``"toy"``."""
        options = dict(spec.options)
        label = spec.name
        if spec.name == "conveyor":
            config = from_mapping(ConveyorConfig, options, where="plant.options")
            label = f"{config.belt_speed_mps:g} m/s"
            if config.belt_profile != "constant":
                label = f"{config.belt_profile} ({label})"
        return cls(label, spec.name, options)


PLANT_PRESETS: dict[str, TablePlant] = {
    name: TablePlant(label, options=scenario_options(scenario), scenario=scenario)
    for name, label, scenario in (
        ("0.2", "0.2 m/s", "constant-0.2"),
        ("0.6", "0.6 m/s", "constant-0.6"),
        ("variable", "variable (0.6 m/s)", "variable"),
    )
}
"""The conveyor plants of the tables, by the short name ``--plant`` and ``plants`` take: the
scenarios ``constant-0.2`` and ``constant-0.6`` (both belt speeds of the paper) and
``variable`` (seeded speed steps and stops around 0.6 m/s), labelled as before."""


# -- rows -------------------------------------------------------------------------------------
_SAC = ComponentSpec("sac", "checkpoints/stage_a/model.zip")
_MLP = ComponentSpec("mlp", "checkpoints/stage_d_model_free/mlp.pt")
_MPC = ComponentSpec("mpc")
_PREDICTOR = ComponentSpec("predictor")
_STATIC = ComponentSpec("static", options={"reliability": 1.0, "latency_steps": 1})

CODESIGN_RULE_ROW = "MPC + predictor, rule QoS (co-design)"
"""The model-based co-design row, whose threshold ``codesign tune`` tunes."""


RULE_INNOVATION_GATE = 0.99
"""Chi-square probability above which a packet surprises the co-design rule (asks again)."""


PLANNER_ROW = "MPC + belt IMM, QoS planner (co-design)"
"""The model-based co-design of the belt-aware stack: uncertainty-aware MPC, IMM, planner."""

PLANNER_GRASP_STD_M = 0.012
"""The planner's lateral grasp tolerance (RMS, m) and the MPC's grasp gate (dev seeds)."""

PLANNER_FAR_STD_M = 0.035
"""Uncertainty (lateral RMS, m) above which the planner asks wherever the gripper is."""

PLANNER_CLOSING_STD_M = 0.012
"""The planner's tolerance while the fingers close (lateral RMS, m) ..."""

PLANNER_CLOSING_USEFUL_WIDTH_M = 0.06
"""... as long as a packet can still make the controller reopen them (finger width, m)."""

GATED_MPC_CONFIG: dict[str, float] = {
    "grasp_std_gate_m": PLANNER_GRASP_STD_M,
    "grasp_abort_tolerance_m": 0.02,
    "funnel_slope_y": 0.0,
    "abort_tolerance_y_m": 0.3,
    "weight_velocity": 0.2,
}
"""The belt-aware stack's MPC (:class:`~codesign_mb.control.mpc_config.MpcConfig` fields,
chosen on the dev seeds of ``realistic`` and ``variable``): closes on a certain estimate,
reopens when the object leaves the closing fingers (a belt stop or restart), follows the
object along the belt at the grasp height between the open fingers, and a lighter velocity
weight (the descent takes 0.88 s instead of 1.04 s to the grasp on ``variable``)."""

_MPC_GATED = ComponentSpec("mpc", options={"config": GATED_MPC_CONFIG})
_BELT_IMM = ComponentSpec("belt_imm", options={"velocity_output": "likeliest"})


def _planner(*, lookahead: bool = True) -> ComponentSpec:
    """The QoS planner (``lookahead=False``: the event-triggered rule) at the dev-chosen
    tolerances."""
    options = {
        "grasp_std_m": PLANNER_GRASP_STD_M,
        "far_std_m": PLANNER_FAR_STD_M,
        "closing_std_m": PLANNER_CLOSING_STD_M,
        "closing_useful_width_m": PLANNER_CLOSING_USEFUL_WIDTH_M,
    }
    return ComponentSpec("planner", options={**options, "lookahead": lookahead})


def _rule() -> ComponentSpec:
    """The covariance rule with the plant's tuned threshold (:func:`row_for_plant`)."""
    options = {"threshold_m": TUNED, "low": 0.0}
    return ComponentSpec("rule", options={**options, "innovation_gate": RULE_INNOVATION_GATE})


def codesign_rule_row() -> TableRow:
    """The model-based co-design row: MPC + predictor + the covariance rule."""
    return next(r for r in model_based_rows() if r.name == CODESIGN_RULE_ROW)


def row_for_plant(row: TableRow, plant: TablePlant | PlantSpec, *, scenario: str = "") -> TableRow:
    """``row`` as it runs on ``plant``: a rule's ``threshold_m = "tuned"`` made a number.

    The number is :func:`~codesign_mb.studies.tuned.rule_threshold` of the plant (its tuned
    threshold, else the default), recorded with its source in ``threshold_source``; other
    rows are returned as they are. ``scenario``: the plant's scenario name when ``plant`` is
    a bare spec (a :class:`TablePlant` carries its own).
    """
    if row.qos.kind != "rule" or row.qos.options.get("threshold_m") != TUNED:
        return row
    spec = plant.spec if isinstance(plant, TablePlant) else plant
    if isinstance(plant, TablePlant):
        scenario = plant.scenario
    choice = rule_threshold(spec, row.qos.options, scenario=scenario)
    qos = dataclasses.replace(
        row.qos, options={**row.qos.options, "threshold_m": choice.threshold_m}
    )
    return dataclasses.replace(row, qos=qos, threshold_source=choice.source)


HYBRID_CODESIGN_ROW = "MLP estimator, hybrid dynamic QoS (co-design)"
"""The shipped stage-D co-design: its QoS policy reads ``predictor_std`` (a Kalman replica)."""

MODEL_FREE_CODESIGN_ROW = "LSTM estimator, model-free dynamic QoS (co-design)"
"""The paper's co-design: its QoS policy reads ``(y, zeta)`` and ``held_history`` only
(``checkpoints/stage_d_model_free_lstm``, trained with ``--qos-features held_history`` on the
stage-B LSTM)."""

_HYBRID_QOS = ComponentSpec("learned", "checkpoints/stage_d/qos")
_HYBRID_MLP = ComponentSpec("mlp", "checkpoints/stage_d/mlp.pt")
_MODEL_FREE_QOS = ComponentSpec("learned", "checkpoints/stage_d_model_free/qos")
_LSTM = ComponentSpec("lstm", "checkpoints/stage_d_model_free_lstm/lstm.pt")
_MODEL_FREE_LSTM_QOS = ComponentSpec("learned", "checkpoints/stage_d_model_free_lstm/qos")


def model_free_rows(scenario: str | None = None) -> tuple[TableRow, ...]:
    """The paper's Table I rows (latency fixed at one step), and the hybrid co-design.

    The learned rows read stage D's model-free LSTM (``stage_d_model_free_lstm/``): on the
    ``dev`` seeds the SAC actor behind the stage-B LSTM succeeded 100/100 at q = 1, behind the
    stage-B MLP 68/100 and the stage-D MLP 83/100 (the MLP stack is the ``all`` table's
    ``SAC + MLP`` rows). The paper's figures go with the model-free co-design row; the
    hybrid co-design (stage D with the ``predictor_std`` features, ``stage_d/``) is its own
    row with its own stage-D MLP.
    """
    return (
        TableRow("LSTM estimator, static QoS", _SAC, _LSTM, _STATIC, 1.00, 1.00),
        TableRow(
            "no estimator, dynamic QoS",
            _SAC,
            ComponentSpec("none"),
            ComponentSpec("learned", "checkpoints/stage_c_none"),
            0.78,
            0.52,
        ),
        TableRow(MODEL_FREE_CODESIGN_ROW, _SAC, _LSTM, _MODEL_FREE_LSTM_QOS, 0.98, 0.13),
        TableRow(HYBRID_CODESIGN_ROW, _SAC, _HYBRID_MLP, _HYBRID_QOS),
    )


def model_based_rows(scenario: str | None = None) -> tuple[TableRow, ...]:
    """The model-based counterparts of Table I: MPC, the predictor, the covariance rule; and
    the belt-aware stack (uncertainty-aware MPC, IMM predictor) with the event-triggered rule
    and the QoS planner."""
    return (
        TableRow("MPC + predictor, static QoS", _MPC, _PREDICTOR, _STATIC),
        TableRow("MPC, no estimator, rule QoS", _MPC, ComponentSpec("none"), _rule()),
        TableRow(CODESIGN_RULE_ROW, _MPC, _PREDICTOR, _rule()),
        TableRow("MPC + belt IMM, event rule", _MPC_GATED, _BELT_IMM, _planner(lookahead=False)),
        TableRow(PLANNER_ROW, _MPC_GATED, _BELT_IMM, _planner()),
    )


def all_rows(scenario: str | None = None) -> tuple[TableRow, ...]:
    """The head-to-head rows: {static, rule, SAC} QoS x {SAC + MLP, MPC + predictor}, ...

    ... the mixed pairs with the QoS policies that do not depend on who they serve (SAC +
    predictor and MPC + MLP, static and rule QoS; a SAC QoS policy is trained for one
    controller and estimator), and the no-estimator rows (the paper's "no estimator, dynamic
    QoS" and its model-based counterpart). The learned stack uses stage D's estimator and
    QoS policy (the paper's final synthesis): model-free (``held_history`` features, the
    estimator of every other learned row) and hybrid (``predictor_std`` features, with its
    own stage-D estimator); the model-based SAC QoS is stage C on MPC + predictor
    (``checkpoints/stage_c_mpc``, features ``predictor_std``).
    """
    rule = _rule()
    return (
        TableRow("SAC + MLP, static QoS", _SAC, _MLP, _STATIC, 1.00, 1.00),
        TableRow("SAC + MLP, rule QoS", _SAC, _MLP, rule),
        TableRow("SAC + MLP, model-free SAC QoS", _SAC, _MLP, _MODEL_FREE_QOS, 0.98, 0.13),
        TableRow("SAC + MLP, hybrid SAC QoS", _SAC, _HYBRID_MLP, _HYBRID_QOS),
        TableRow(
            "SAC, no estimator, SAC QoS",
            _SAC,
            ComponentSpec("none"),
            ComponentSpec("learned", "checkpoints/stage_c_none"),
            0.78,
            0.52,
        ),
        TableRow("MPC + predictor, static QoS", _MPC, _PREDICTOR, _STATIC),
        TableRow("MPC + predictor, rule QoS", _MPC, _PREDICTOR, rule),
        TableRow(
            "MPC + predictor, SAC QoS",
            _MPC,
            _PREDICTOR,
            ComponentSpec("learned", "checkpoints/stage_c_mpc"),
        ),
        TableRow("MPC, no estimator, rule QoS", _MPC, ComponentSpec("none"), rule),
        TableRow("SAC + predictor, static QoS", _SAC, _PREDICTOR, _STATIC),
        TableRow("SAC + predictor, rule QoS", _SAC, _PREDICTOR, rule),
        TableRow("MPC + MLP, static QoS", _MPC, _MLP, _STATIC),
        TableRow("MPC + MLP, rule QoS", _MPC, _MLP, rule),
    )


LEARNED_CODESIGN_ROW = "BC+SAC actor + GRU estimator, model-free SAC QoS (co-design)"
"""The learned stack of the realistic scenario (issue 30): stage A's actor (a behaviour clone
fine-tuned by SAC, whose success is the clone's: models/checkpoints/README.md) behind the
stage-B Gaussian sequence estimator, stage C's SAC QoS policy on that estimator's belief."""

LEARNED_SCENARIOS = ("realistic", "variable")
"""The scenarios the learned stack is trained on (``checkpoints/stage_{a,b,c}_*_<scenario>``):
``variable``'s packet carries the belt velocity, so ``realistic``'s checkpoints cannot read it."""


def learned_rows(scenario: str | None = None) -> tuple[TableRow, ...]:
    """The learned stack on ``scenario`` (``realistic`` unless ``variable``) stage by stage:
    each row swaps one stage with the model-based one, so a reader sees which learned stage
    costs what (the references add each stack's blind, oracle and static rows and random at
    each row's budget). The belt IMM cannot run behind the learned actor: its output has one
    entry more than the state layout the actor reads (14 vs 13)."""
    trained = scenario if scenario in LEARNED_SCENARIOS else "realistic"
    actor = ComponentSpec("sac", f"checkpoints/stage_a_{trained}/model.zip")
    sequence = ComponentSpec("sequence", f"checkpoints/stage_b_sequence_{trained}/sequence.pt")
    qos = ComponentSpec("learned", f"checkpoints/stage_c_learned_{trained}")
    return (
        TableRow(LEARNED_CODESIGN_ROW, actor, sequence, qos),
        TableRow("BC+SAC actor + GRU estimator, static QoS", actor, sequence, _STATIC),
        TableRow("MPC + GRU estimator, model-free SAC QoS", _MPC_GATED, sequence, qos),
        TableRow(PLANNER_ROW, _MPC_GATED, _BELT_IMM, _planner()),
    )


PIPELINES: dict[str, Callable[[str | None], tuple[TableRow, ...]]] = {
    "model-free": model_free_rows,
    "model-based": model_based_rows,
    "all": all_rows,
    "learned": learned_rows,
}
"""Pipeline name -> its default rows on a scenario (``None``: the pipeline's own plants)."""

PIPELINE_PLANTS: dict[str, tuple[str, ...]] = {
    "model-free": ("0.2",),
    "model-based": ("realistic",),
    "all": ("realistic", "0.2", "0.6", "variable"),
    "learned": ("realistic",),
}
"""Pipeline name -> its default plants (keys of :data:`PLANT_PRESETS` or scenario names): the
benchmark's ``realistic`` scenario; the paper's Table I (``model-free``) at 0.2 m/s, the plant
its shipped checkpoints were trained on (they cannot read the realistic packet)."""

_LEARNED_CONTROLLERS = ("sac", "bc")
_LEARNED_ESTIMATORS = ("mlp", "lstm", "sequence")
_MODEL_BASED = ("mpc", "predictor", "belt_imm", "scripted", "toy_pick")


def stack_of(row: TableRow) -> str:
    """``"model-free"`` (learned controller, learned or no estimator, a QoS policy that reads
    no model), ``"hybrid"`` (the same with a learned QoS policy fed by a model-based replica,
    :func:`qos_features_stack`), ``"model-based"`` (a model-based controller with a
    model-based or no estimator) or ``"mixed"``."""
    c, e = row.controller.kind, row.estimator.kind
    no_estimator = e == "none"
    if c in _LEARNED_CONTROLLERS and (e in _LEARNED_ESTIMATORS or no_estimator):
        return qos_features_stack(row.qos)
    if c in _MODEL_BASED and (e in _MODEL_BASED or no_estimator):
        return "model-based"
    return "mixed"


def qos_features_stack(qos: ComponentSpec) -> str:
    """``"hybrid"`` for a learned QoS policy whose recorded features are model-based
    (:data:`~codesign_mb.adaptation.learned.HYBRID_FEATURES`), else ``"model-free"`` (any
    other QoS kind, or a policy whose checkpoint is not there to say)."""
    from codesign_mb.adaptation.learned import HYBRID_FEATURES, LearnedQosPolicy
    from codesign_mb.core.registry import resolve_checkpoint

    if qos.kind != "learned" or not qos.checkpoint:
        return "model-free"
    try:
        meta = LearnedQosPolicy.read_meta(resolve_checkpoint(qos.checkpoint))
    except (ValueError, OSError):
        return "model-free"
    kind = (meta.get("features") or {}).get("kind")
    return "hybrid" if kind in HYBRID_FEATURES else "model-free"
