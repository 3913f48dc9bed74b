"""Edge perception: the camera's geometry, the detector, and the calibrated error model.

Render-marked tests need a headless GL backend (EGL or OSMesa) and skip without one.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from codesign_mb.plants.camera_perception import LIFTED_M, CameraPerception, PerceptionCalibration
from codesign_mb.robot.camera import FRAME_BUDGET_BYTES, PinholeCamera, segment_colour
from codesign_mb.robot.scene import BELT_SURFACE_Z, OBJECTS, build_scene


def _needs_gl() -> None:
    from codesign_mb.robot.render import gl_backend

    if gl_backend() is None:
        pytest.skip("no headless GL backend (install libosmesa6, or libegl1 + libegl-mesa0)")


@pytest.fixture(scope="module")
def camera() -> PinholeCamera:
    return PinholeCamera.from_model(build_scene().model)


# ------------------------------------------------------------------------ camera geometry


def test_edge_camera_pose_and_intrinsics_come_from_the_model(camera: PinholeCamera) -> None:
    # models/scene_conveyor.xml: pos 0.5 0 1.56, image x along +y, image up along -x, fovy 14.
    np.testing.assert_allclose(camera.position, [0.5, 0.0, 1.56])
    np.testing.assert_allclose(camera.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert (camera.width, camera.height, camera.fovy_deg) == (120, 37, 14.0)
    assert camera.frame_bytes <= FRAME_BUDGET_BYTES
    # The frame's half height subtends fovy / 2 at the focal length.
    assert np.isclose(np.degrees(2 * np.arctan(18.5 / camera.focal_px)), 14.0)


def test_back_projection_inverts_projection_on_the_plane(camera: PinholeCamera) -> None:
    rng = np.random.default_rng(0)
    plane_z = BELT_SURFACE_Z + OBJECTS["cube"].half_height
    points = np.column_stack(
        [rng.uniform(0.38, 0.62, 50), rng.uniform(-0.5, 0.5, 50), np.full(50, plane_z)]
    )
    pixels = camera.project(points)
    np.testing.assert_allclose(camera.back_project(pixels, plane_z), points, atol=1e-12)
    # Independent: straight below the camera is the frame's centre; 1 m along the belt at
    # depth d is focal * 1 / d pixels to the right.
    depth = camera.position[2] - plane_z
    np.testing.assert_allclose(
        camera.project([[0.5, 0.1, plane_z]]), [[60 + camera.focal_px * 0.1 / depth, 18.5]]
    )


def test_segment_colour_finds_the_object_hue_under_shading() -> None:
    frame = np.full((20, 30, 3), 32, dtype=np.uint8)  # dark grey belt
    frame[:, 25:] = (184, 158, 128)  # the table's tan
    red = np.array(OBJECTS["cube"].rgba[:3])
    frame[5:10, 5:10] = np.round(255 * red).astype(np.uint8)  # lit face
    frame[10:12, 5:10] = np.round(120 * red).astype(np.uint8)  # shaded side
    frame[6, 6] = (255, 128, 92)  # a highlight: less saturated, same hue
    mask = segment_colour(frame, red)
    expected = np.zeros((20, 30), dtype=bool)
    expected[5:12, 5:10] = True
    np.testing.assert_array_equal(mask, expected)


# --------------------------------------------------------------------------- error model


def _calibration(**changes: object) -> PerceptionCalibration:
    grid = np.zeros((20, 20))
    grid[9:11, 9:11] = 0.9  # under the gripper
    fields = {
        "object_kind": "cube",
        "plane_z": 0.0825,
        "camera_position": (0.5, 0.0, 1.56),
        "view_low": (0.37, -0.54),
        "view_high": (0.63, 0.54),
        "view_centre": (0.5, 0.0),
        "bias": (0.001, -0.002),
        "bias_gradient": ((0.01, 0.0), (0.0, 0.02)),
        "std": (0.002, 0.004),
        "miss_rate": 0.1,
        "lifted_miss_rate": 1.0,
        "occlusion_cell_m": 0.02,
        "occlusion_extent_m": 0.2,
        "occlusion_miss": tuple(map(tuple, grid)),
    }
    fields.update(changes)
    return PerceptionCalibration(**fields)  # type: ignore[arg-type]


def test_error_model_draws_its_calibrated_bias_noise_and_misses() -> None:
    model = CameraPerception(_calibration())
    rng = np.random.default_rng(1)
    truth = np.array([0.55, 0.3, 0.0825])
    draws = [model.sample(truth, rng) for _ in range(20_000)]
    hits = np.array([d for d in draws if d is not None])
    miss = 1 - len(hits) / len(draws)
    assert abs(miss - 0.1) < 4 * np.sqrt(0.1 * 0.9 / len(draws))
    # bias + gradient @ (xy - centre): x 1 + 10 * 0.05 = 1.5 mm, y -2 + 20 * 0.3 = 4 mm.
    np.testing.assert_allclose((hits[:, :2] - truth[:2]).mean(0), [0.0015, 0.004], atol=1e-4)
    np.testing.assert_allclose(hits[:, :2].std(0), [0.002, 0.004], rtol=0.03)
    assert np.all(hits[:, 2] == 0.0825)  # the detector's plane


def test_error_model_view_occlusion_and_parallax() -> None:
    model = CameraPerception(_calibration(std=(0.0, 0.0), bias=(0.0, 0.0)))
    rng = np.random.default_rng(2)
    assert model.sample([0.5, 0.7, 0.0825], rng) is None  # out of view
    assert model.miss_probability([0.5, 0.0, 0.0825], gripper_position=[0.5, 0.01, 0.2]) == 0.9
    assert model.miss_probability([0.5, 0.0, 0.0825], gripper_position=[0.5, 0.3, 0.2]) == 0.1
    lifted = [0.5, 0.2, 0.0825 + 2 * LIFTED_M]
    assert model.sample(lifted, rng, gripper_position=[0.5, 0.2, 0.1]) is None
    # Seen along the camera's ray, a raised object lands farther from the nadir on the plane.
    model = CameraPerception(
        _calibration(
            std=(0.0, 0.0), bias=(0.0, 0.0), bias_gradient=((0, 0), (0, 0)), lifted_miss_rate=0.0
        )
    )
    measured = model.sample([0.5, 0.2, 0.1825], rng)
    assert measured is not None
    np.testing.assert_allclose(measured[1], 0.2 * (1.56 - 0.0825) / (1.56 - 0.1825))


def test_calibration_round_trips_through_json(tmp_path: Path) -> None:
    cal = _calibration(provenance={"command": "codesign calibrate-perception"})
    cal.to_json(tmp_path / "c.json")
    assert PerceptionCalibration.from_json(tmp_path / "c.json") == cal
    with pytest.raises(ValueError, match="miss_rate must be in"):
        _calibration(miss_rate=1.5)


def test_shipped_calibration_loads_and_records_its_command() -> None:
    model = CameraPerception.load("cube")
    prov = model.calibration.provenance
    assert prov["command"].startswith("codesign calibrate-perception")
    assert json.dumps(prov)  # plain data
    figures = model.describe()
    assert 0 < figures["std_x_mm"] < 10 and 0 < figures["std_y_mm"] < 10


# ------------------------------------------------------------------------- camera path


@pytest.mark.render
def test_detector_locates_the_object_in_a_rendered_frame() -> None:
    import mujoco

    from codesign_mb.plants.conveyor import ConveyorPickPlace
    from codesign_mb.robot.camera import EdgeCamera

    _needs_gl()
    env = ConveyorPickPlace()
    env.reset(seed=0)  # arm at home over y = 0, object upstream at y = -0.45
    camera = EdgeCamera(env.sim.scene)
    frame = camera.capture(env.sim.data, np.random.default_rng(0))
    assert frame.shape == (37, 120, 3) and len(frame.tobytes()) <= FRAME_BUDGET_BYTES
    detection = camera.detect(frame)
    truth = env.sim.object_position()
    assert detection.position is not None
    assert np.linalg.norm(detection.position[:2] - truth[:2]) < 0.01  # a pixel is ~1 cm
    # Out of view (beyond the frame's end): missed, not guessed.
    env.sim.data.qpos[env.sim.scene.object_qpos][1] = 0.75
    mujoco.mj_forward(env.sim.model, env.sim.data)
    assert camera.locate(env.sim.data).position is None
    camera.close()
    env.close()


@pytest.mark.render
def test_error_model_matches_the_camera_path_on_test_frames() -> None:
    """The shipped model (calibrated on the dev seeds) against fresh camera-path frames.

    Frames from the ``test`` seed set, disjoint from the calibration's: bias and std per axis
    and the miss rate within 20 % (biases, which are near zero, within 20 % of the std).
    """
    from codesign_mb.core.seeds import seed_set
    from codesign_mb.studies.perception import camera_path_rows, error_statistics, model_rows

    _needs_gl()
    rows = camera_path_rows(seed_set("test"), sweep_frames=500, episodes_per_speed=1)
    model = CameraPerception.load("cube")
    path = error_statistics(rows)
    drawn = error_statistics(model_rows(rows, model, np.random.default_rng(seed_set("test"))))
    print("camera path", path, "\nerror model", drawn)
    for axis in ("x", "y"):
        std = path[f"std_{axis}_mm"]
        assert abs(drawn[f"std_{axis}_mm"] - std) <= 0.2 * std
        assert abs(drawn[f"bias_{axis}_mm"] - path[f"bias_{axis}_mm"]) <= 0.2 * std
    for rate in ("miss_rate", "miss_rate_far"):
        assert abs(drawn[rate] - path[rate]) <= 0.2 * path[rate]


@pytest.mark.render
def test_render_edge_camera_with_detection(tmp_path: Path) -> None:
    import imageio.v3 as iio
    from typer.testing import CliRunner

    from codesign_mb.cli import app
    from codesign_mb.studies.render import DETECTION_ZOOM

    _needs_gl()
    out = tmp_path / "edge.gif"
    args = ["render", "-o", str(out), "--steps", "3", "--json"]
    result = CliRunner().invoke(app, [*args, "--camera", "edge", "--show-detection"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["frames"] == 4 and summary["detected_frames"] == 4
    frames = iio.imread(out)
    assert frames.shape == (4, 37 * DETECTION_ZOOM, 120 * DETECTION_ZOOM, 3)
    result = CliRunner().invoke(app, [*args, "--show-detection"])  # overview camera
    assert result.exit_code == 2 and "show_detection needs the edge camera" in result.output


def test_calibrate_refuses_the_shipped_calibration_folder_without_overwrite(tmp_path) -> None:
    """Like ``train``: the package's models/ is written only with --overwrite."""
    from typer.testing import CliRunner

    from codesign_mb.cli import app
    from codesign_mb.core.registry import models_dir

    shipped = models_dir() / "perception" / "edge_cube.json"
    before = shipped.read_bytes()
    result = CliRunner().invoke(app, ["calibrate-perception", "-o", str(shipped)])
    assert result.exit_code == 2
    assert "inside the installed package's models folder" in result.output
    assert "--overwrite" in result.output
    assert shipped.read_bytes() == before
