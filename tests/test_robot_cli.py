"""``codesign render`` and ``codesign bench env``, end to end (small settings)."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from typer.testing import CliRunner

from codesign_mb.cli import app

runner = CliRunner()


@pytest.mark.render
def test_render_writes_a_gif(tmp_path: Path) -> None:
    from codesign_mb.robot.render import gl_backend

    if gl_backend() is None:
        pytest.skip("no headless GL backend (install libosmesa6, or libegl1 + libegl-mesa0)")
    config = tmp_path / "render.toml"
    config.write_text("[render]\nsteps = 4\n[render.env]\nrender_width = 96\nrender_height = 72\n")
    out = tmp_path / "episode.gif"
    result = runner.invoke(
        app, ["render", "-c", str(config), "-o", str(out), "--belt-speed", "0.6", "--json"]
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["frames"] == 5 and summary["belt_speed_mps"] == 0.6
    frames = iio.imread(out)
    assert frames.shape == (5, 72, 96, 3)


def test_render_rejects_bad_options(tmp_path: Path) -> None:
    for args, message in (
        (["--belt-speed", "-1"], "belt_speed_mps must be >= 0"),
        (["--object", "banana"], "object must be one of"),
        (["-o", str(tmp_path / "x.avi")], "out must end in .gif or .mp4"),
    ):
        result = runner.invoke(app, ["render", *args])
        assert result.exit_code == 2
        assert message in result.output


def test_bench_env_reports_steps_per_second() -> None:
    from codesign_mb.bench.env import bench_env

    figures = bench_env(repeats=2, seed=0)
    assert figures["steps_per_s"] > 0 and figures["cpu_steps_per_s"] > 0
    assert figures["substeps_per_step"] == 20
    # The headline is the median of the per-repeat ratios env rate / bare-physics rate (not a
    # timing threshold: the env now runs at ~0.85 of the physics, within one repeat's noise).
    ratios = [
        e / p
        for e, p in zip(
            figures["steps_per_s_repeats"], figures["physics_only_steps_per_s_repeats"], strict=True
        )
    ]
    assert figures["physics_fraction"] == pytest.approx(float(np.median(ratios)))
    assert figures["physics_fraction_repeats"] == [round(r, 3) for r in ratios]
    json.dumps(figures)  # JSON-ready
