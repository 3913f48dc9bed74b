"""Public constructors and functions name the argument they reject (issue 35's examples).

Each call below was accepted, or failed deep inside with an AttributeError, before; now it
raises a ``TypeError``/``ValueError`` whose message names the bad argument, and the CLI path
examples end in one line with exit code 2.
"""

from __future__ import annotations

import math

import pytest
from typer.testing import CliRunner

from codesign_mb.adaptation.rules import tune_threshold
from codesign_mb.cli import app
from codesign_mb.network.link import BernoulliLink, ObservationBuffer, Packet
from codesign_mb.network.qos import QosRequest, reliability_cost
from codesign_mb.wifi.offline import offline_optimum


@pytest.mark.parametrize(
    ("call", "error", "names"),
    [
        (lambda: reliability_cost(None), TypeError, "qos"),
        (lambda: BernoulliLink(seed=True), TypeError, "seed"),
        (lambda: BernoulliLink(seed=-1), ValueError, "seed"),
        (lambda: Packet("a", "b"), TypeError, "timestamp"),
        (lambda: Packet(1, "b"), TypeError, "value"),
        (lambda: ObservationBuffer(prior=[[math.nan]]), ValueError, "prior"),
        (
            lambda: tune_threshold(
                lambda x: (1.0, 0.0), target_success=0.9, low=0.1, high=1.0, iterations=0
            ),
            ValueError,
            "iterations",
        ),
        (lambda: offline_optimum(None, solver=None), ValueError, "solver"),
        (lambda: offline_optimum(None), TypeError, "trace"),
    ],
)
def test_bad_arguments_are_named(call, error, names) -> None:
    with pytest.raises(error, match=names):
        call()


def test_valid_arguments_still_pass() -> None:
    assert reliability_cost(QosRequest(0.5, 1)) == 0.5
    link = BernoulliLink(seed=3)
    link.reset(seed=4, prior=[0.0])
    assert Packet(2, [1.0, 2.0]).value.tolist() == [1.0, 2.0]


def test_unwritable_outputs_are_one_line_errors(tmp_path) -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["render", "--steps", "2", "-o", "/proc/x.gif"])
    assert result.exit_code == 2
    assert result.stderr.startswith("error: out: cannot write '/proc/x.gif'")
    assert result.stderr.count("\n") == 1
    result = runner.invoke(
        app, ["calibrate-perception", "--episodes", "0", "-o", str(tmp_path / "c.json")]
    )
    assert result.exit_code == 2 and "episodes must be >= 1" in result.stderr
    assert not (tmp_path / "c.json").exists()
