"""A table's ``bound`` rows (studies/table_bound.py): the clairvoyant schedule of a co-design
row, on the row's own episodes, against the row and against the schedules found directly."""

from __future__ import annotations

import pytest

from codesign_mb.core.registry import ComponentSpec
from codesign_mb.evaluation.clairvoyant import clairvoyant_episode
from codesign_mb.studies.table import TableConfig, run_table
from codesign_mb.studies.table_rows import TablePlant, TableRow

TOY = TablePlant("toy", name="toy")
PICK = ComponentSpec("toy_pick")
NONE = ComponentSpec("none")
AGE_RULE = ComponentSpec("age_rule", options={"low": 0.0, "high": 1.0, "max_age_steps": 2})
ROW = TableRow("age rule", PICK, NONE, AGE_RULE)
STATIC = TableRow("static", PICK, NONE, ComponentSpec("static"))


def test_bound_row_is_the_clairvoyant_schedule_of_each_episode_of_its_row() -> None:
    config = TableConfig(plants=(TOY,), rows=(ROW, STATIC), trials=4, seed=3, bound=("age rule",))
    summary, episodes = run_table(config)
    bound = summary[summary["kind"] == "bound"]
    assert list(bound["row"]) == ["clairvoyant schedule of: age rule"]
    assert bool(bound["reference"].iloc[0]) and bound["reference_of"].iloc[0] == "age rule"
    own = episodes[episodes["row"] == "age rule"].set_index("seed")
    found = episodes[episodes["row"] == bound["row"].iloc[0]].set_index("seed")
    assert list(found.index) == list(own.index)  # the row's episodes, the same seeds
    for seed in own.index:
        direct = clairvoyant_episode(TOY.spec, PICK, NONE, AGE_RULE, int(seed))
        assert bool(found.loc[seed, "success"]) == direct.success
        if direct.success:
            assert found.loc[seed, "mean_requested_reliability"] == pytest.approx(direct.requested)
        if own.loc[seed, "success"]:  # pruned from the row's own requests: never more
            assert found.loc[seed, "success"]
            assert (
                found.loc[seed, "mean_requested_reliability"]
                <= own.loc[seed, "mean_requested_reliability"]
            )
    assert (
        bound["mean_requested_reliability"].iloc[0]
        < summary.set_index("row").loc["age rule", "mean_requested_reliability"]
    )


@pytest.mark.parametrize(
    ("bound", "match"),
    [(("static",), "co-design rows"), (("nope",), "co-design rows"), ("age rule", "list")],
)
def test_bound_must_name_co_design_rows(bound: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        TableConfig(plants=(TOY,), rows=(ROW, STATIC), bound=bound)  # type: ignore[arg-type]
