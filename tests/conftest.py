"""Fixtures shared by the test modules."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner


@pytest.fixture
def runner(monkeypatch: pytest.MonkeyPatch) -> CliRunner:
    """The command line, in process, without progress bars (plain output to assert on)."""
    monkeypatch.setenv("CODESIGN_NO_PROGRESS", "1")
    return CliRunner()
