"""Results folders: tidy tables + config + version, written atomically."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import pytest

from codesign_mb.core.results import ResultsDir, atomic_write, write_results


@dataclass(frozen=True)
class Cfg:
    trials: int = 3
    speeds: tuple[float, ...] = (0.2, 0.6)


def _table() -> pd.DataFrame:
    return pd.DataFrame({"policy": ["a", "b"], "success_rate": [1.0, 0.5], "n": [10, 10]})


def test_write_and_read_back(tmp_path: Path) -> None:
    paths = write_results(
        tmp_path / "out", table=_table(), config=Cfg(), name="tab_p", extra={"seed": 7}
    )
    assert {p.name for p in paths.values()} == {"tab_p.parquet", "tab_p.csv", "tab_p.json"}
    results = ResultsDir(tmp_path / "out")
    assert results.names == ["tab_p"] and "tab_p" in results
    pd.testing.assert_frame_equal(results.table("tab_p"), _table())
    pd.testing.assert_frame_equal(pd.read_csv(paths["csv"]), _table())
    meta = results.meta("tab_p")
    assert meta["config"] == {"trials": 3, "speeds": [0.2, 0.6]}
    assert meta["extra"] == {"seed": 7}
    assert meta["version"] and meta["created"] and meta["n_rows"] == 2
    with pytest.raises(ValueError, match=r"no table 'fig_cn'.*present: tab_p"):
        results.table("fig_cn")


def test_rewrite_replaces_and_leaves_no_temp_files(tmp_path: Path) -> None:
    write_results(tmp_path, table=_table(), config=None, name="t")
    write_results(tmp_path, table=_table().iloc[:1], config={"x": 1}, name="t")
    assert len(ResultsDir(tmp_path).table("t")) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv", "t.json", "t.parquet"]


def test_interrupted_write_leaves_no_partial_file(tmp_path: Path) -> None:
    target = tmp_path / "x.csv"
    with pytest.raises(KeyboardInterrupt), atomic_write(target, "w") as fh:
        fh.write("half a ")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
    # An existing complete file survives an interrupted rewrite untouched.
    target.write_text("complete\n")
    with pytest.raises(RuntimeError), atomic_write(target, "w") as fh:
        fh.write("garbage")
        raise RuntimeError("interrupted")
    assert target.read_text() == "complete\n"
    assert [p.name for p in tmp_path.iterdir()] == ["x.csv"]


def test_interrupted_write_results(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Crash mid-table (in the CSV writer): no half file, table not listed as complete."""
    write_results(tmp_path, table=_table(), config=None, name="old")

    def boom(self: pd.DataFrame, fh: object, **kwargs: object) -> None:
        fh.write("policy,success_rate\na,")  # type: ignore[attr-defined]
        raise KeyboardInterrupt

    monkeypatch.setattr(pd.DataFrame, "to_csv", boom)
    with pytest.raises(KeyboardInterrupt):
        write_results(tmp_path, table=_table(), config=None, name="new")
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["new.parquet", "old.csv", "old.json", "old.parquet"]
    assert ResultsDir(tmp_path).names == ["old"]


def test_tidy_checks(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="results name"):
        write_results(tmp_path, table=_table(), config=None, name="../evil")
    with pytest.raises(TypeError, match="DataFrame"):
        write_results(tmp_path, table={"a": [1]}, config=None, name="t")  # type: ignore[arg-type]
    indexed = _table().set_index("policy")
    write_results(tmp_path, table=indexed, config=None, name="t")
    assert list(ResultsDir(tmp_path).table("t").columns) == ["policy", "success_rate", "n"]
    assert json.loads((tmp_path / "t.json").read_text())["config"] is None
