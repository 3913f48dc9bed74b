"""Calibrate the perception error model on the edge camera path (``codesign calibrate-perception``).

Frames come from two sources, each seeded from a root seed (``SeedSequence.spawn``):

- **sweep**: the gripper put at random over the belt (arm by inverse kinematics), the object
  with a random yaw at random either near the gripper (where the arm may hide it) or anywhere
  on the belt (across its whole width, along it beyond the camera's view);
- **episodes**: scripted picks (:class:`~codesign_mb.control.scripted.ScriptedPickController`
  on the true state) at a few belt speeds, a frame each control step: the gripper
  approaches, hides the object, lifts it.

Every frame goes through the real camera path (render, sensor noise, segmentation, centroid,
back-projection; :class:`~codesign_mb.robot.camera.EdgeCamera`) and gives one row (true
position, gripper position, detection). :func:`fit_calibration` turns the rows into a
:class:`~codesign_mb.plants.camera_perception.PerceptionCalibration`; :func:`error_statistics`
summarises rows (bias and std per axis, miss rate) the same way for the camera path and for
the model, which is how the test compares them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import mujoco
import numpy as np
import pandas as pd
from numpy.typing import NDArray

from codesign_mb.control.scripted import ScriptedPickController
from codesign_mb.core.config import (
    EPISODES_CAP,
    SEED_CAP,
    STEPS_CAP,
    check_range,
    check_writable,
)
from codesign_mb.plants.camera_perception import (
    LIFTED_M,
    CameraPerception,
    PerceptionCalibration,
)
from codesign_mb.plants.conveyor import ConveyorConfig, ConveyorPickPlace
from codesign_mb.robot.camera import EdgeCamera
from codesign_mb.robot.scene import (
    BELT_HALF_LENGTH,
    BELT_HALF_WIDTH,
    BELT_SURFACE_Z,
    BELT_X,
    OBJECTS,
)
from codesign_mb.robot.simulator import home_configuration

__all__ = [
    "CALIBRATION_SPEEDS",
    "camera_path_rows",
    "error_statistics",
    "fit_calibration",
    "model_rows",
]

CALIBRATION_SPEEDS = (0.1, 0.2, 0.4, 0.6)
"""Belt speeds (m/s) of the calibration episodes."""
_CELL_M, _EXTENT_M = 0.02, 0.2


def camera_path_rows(
    seed: int,
    *,
    object_kind: str = "cube",
    sweep_frames: int = 600,
    episodes_per_speed: int = 3,
    speeds: Sequence[float] = CALIBRATION_SPEEDS,
    progress: Callable[[int, int], None] | None = None,
) -> pd.DataFrame:
    """One row per frame through the camera path (columns: see the module docstring).

    Columns ``source``, ``speed``, ``x, y, z`` (truth), ``gx, gy, gz`` (TCP), ``on_belt``,
    ``detected``, ``mx, my, mz`` (measured, NaN if missed), ``n_pixels``.
    """
    sweep_seq, *speed_seqs = np.random.SeedSequence(seed).spawn(1 + len(speeds))
    total = sweep_frames + episodes_per_speed * len(speeds) * (ConveyorConfig().horizon + 1)
    rows: list[dict[str, Any]] = []
    for speed, seq in zip([0.0, *speeds], [sweep_seq, *speed_seqs], strict=True):
        env = ConveyorPickPlace(ConveyorConfig(object=object_kind, belt_speed_mps=float(speed)))
        camera = EdgeCamera(env.sim.scene)
        try:
            if seq is sweep_seq:
                rows += _sweep(env, camera, np.random.default_rng(seq), sweep_frames)
            else:
                for child in seq.spawn(episodes_per_speed):
                    rows += _episode(env, camera, child, float(speed))
        finally:
            camera.close()
            env.close()
        if progress is not None:
            progress(len(rows), total)
    return pd.DataFrame(rows)


def _row(
    source: str, speed: float, env: ConveyorPickPlace, camera: EdgeCamera, rng: np.random.Generator
) -> dict[str, Any]:
    truth = env.sim.object_position().copy()
    tcp = env.sim.tcp_position()
    detection = camera.locate(env.sim.data, rng)
    measured = detection.position if detection.position is not None else np.full(3, np.nan)
    return {
        "source": source,
        "speed": speed,
        **dict(zip(("x", "y", "z"), truth.tolist(), strict=True)),
        **dict(zip(("gx", "gy", "gz"), tcp.tolist(), strict=True)),
        "on_belt": bool(truth[2] < env.rest_height + LIFTED_M),
        "detected": detection.position is not None,
        **dict(zip(("mx", "my", "mz"), measured.tolist(), strict=True)),
        "n_pixels": detection.n_pixels,
    }


def _sweep(
    env: ConveyorPickPlace, camera: EdgeCamera, rng: np.random.Generator, frames: int
) -> list[dict[str, Any]]:
    env.reset(seed=int(rng.integers(2**31)))
    sim, scene = env.sim, env.sim.scene
    lateral = BELT_HALF_WIDTH - env.object_shape.half_height  # the whole belt's width
    rows = []
    for k in range(frames):
        tcp, q = _random_arm(rng)
        if k % 2:  # near the gripper, where the arm may hide it
            low_x = max(BELT_X - lateral, tcp[0] - _EXTENT_M)
            high_x = min(BELT_X + lateral, tcp[0] + _EXTENT_M)
            xy = np.array([rng.uniform(low_x, high_x), tcp[1] + rng.uniform(-_EXTENT_M, _EXTENT_M)])
        else:  # anywhere along the belt, beyond the camera's view
            xy = np.array(
                [
                    BELT_X + rng.uniform(-lateral, lateral),
                    rng.uniform(-0.8 * BELT_HALF_LENGTH, 0.8 * BELT_HALF_LENGTH),
                ]
            )
        sim.reset(
            object_position=(xy[0], xy[1], env.rest_height),
            belt_speed=0.0,
            q=q,
        )
        yaw = rng.uniform(0.0, math.pi / 2)
        sim.data.qpos[scene.object_qpos][3:] = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
        mujoco.mj_forward(sim.model, sim.data)
        rows.append(_row("sweep", 0.0, env, camera, rng))
    return rows


def _random_arm(rng: np.random.Generator) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A random TCP position over the belt, gripper down, and its arm configuration."""
    while True:
        tcp = np.array(
            [
                BELT_X + rng.uniform(-0.12, 0.12),
                rng.uniform(-0.35, 0.35),
                BELT_SURFACE_Z + rng.uniform(0.04, 0.30),
            ]
        )
        try:
            return tcp, np.array(home_configuration(tuple(tcp.tolist())))
        except ValueError:  # inverse kinematics did not converge: draw again
            continue


def _episode(
    env: ConveyorPickPlace, camera: EdgeCamera, seq: np.random.SeedSequence, speed: float
) -> list[dict[str, Any]]:
    env_seed, noise_seq = seq.generate_state(1)[0], seq.spawn(1)[0]
    controller = ScriptedPickController(env.config)
    rng = np.random.default_rng(noise_seq)
    obs, _ = env.reset(seed=int(env_seed))
    controller.reset(seed=int(env_seed))
    rows = [_row("episode", speed, env, camera, rng)]
    for _ in range(env.horizon):
        obs, *_ = env.step(controller.act(obs))
        rows.append(_row("episode", speed, env, camera, rng))
    return rows


def _far(rows: pd.DataFrame) -> pd.Series:
    return (np.abs(rows.x - rows.gx) >= _EXTENT_M) | (np.abs(rows.y - rows.gy) >= _EXTENT_M)


def fit_calibration(
    rows: pd.DataFrame, *, plane_z: float, camera_position: Sequence[float], object_kind: str
) -> PerceptionCalibration:
    """Fit the error model's parameters to camera-path rows (see the module docstring).

    The footprint is where unoccluded objects were detected; the bias is a least-squares plane
    in (x, y) over the detected objects on the belt, ``std`` its residual standard deviation;
    the occlusion grid is the miss fraction per cell of the object-gripper offset, shrunk
    towards ``miss_rate`` by two pseudo-frames where data are scarce.
    """
    belt = rows[rows.on_belt]
    lifted = rows[~rows.on_belt]
    far = belt[_far(belt)]
    seen = far[far.detected]
    low = (float(seen.x.min()), float(seen.y.min()))
    high = (float(seen.x.max()), float(seen.y.max()))
    inside = belt[belt.x.between(low[0], high[0]) & belt.y.between(low[1], high[1])]
    far_inside = inside[_far(inside)]
    miss_rate = float(1.0 - far_inside.detected.mean())
    centre = ((low[0] + high[0]) / 2, (low[1] + high[1]) / 2)
    hits = inside[inside.detected]
    design = np.column_stack([np.ones(len(hits)), hits.x - centre[0], hits.y - centre[1]])
    errors = np.column_stack([hits.mx - hits.x, hits.my - hits.y])
    coef, *_ = np.linalg.lstsq(design, errors, rcond=None)
    residual = errors - design @ coef
    n_cells = round(2 * _EXTENT_M / _CELL_M)
    near = inside[~_far(inside)]
    cells = np.floor((np.column_stack([near.x - near.gx, near.y - near.gy]) + _EXTENT_M) / _CELL_M)
    index = cells.astype(int).clip(0, n_cells - 1)
    flat = index[:, 0] * n_cells + index[:, 1]
    count = np.bincount(flat, minlength=n_cells**2)
    missed = np.bincount(flat, weights=~near.detected.to_numpy(), minlength=n_cells**2)
    grid = ((missed + 2 * miss_rate) / (count + 2)).reshape(n_cells, n_cells)
    return PerceptionCalibration(
        object_kind=object_kind,
        plane_z=float(plane_z),
        camera_position=tuple(float(v) for v in camera_position),  # type: ignore[arg-type]
        view_low=low,
        view_high=high,
        view_centre=centre,
        bias=(float(coef[0, 0]), float(coef[0, 1])),
        bias_gradient=tuple(tuple(float(v) for v in coef[1:, k]) for k in range(2)),  # type: ignore[arg-type]
        std=(float(residual[:, 0].std()), float(residual[:, 1].std())),
        miss_rate=miss_rate,
        lifted_miss_rate=float(1.0 - lifted.detected.mean()) if len(lifted) else 1.0,
        occlusion_cell_m=_CELL_M,
        occlusion_extent_m=_EXTENT_M,
        occlusion_miss=tuple(tuple(float(v) for v in row) for row in grid),
    )


def model_rows(
    rows: pd.DataFrame, model: CameraPerception, rng: np.random.Generator
) -> pd.DataFrame:
    """``rows`` with the detections replaced by the error model's draws at the same states."""
    out = rows.copy()
    measured = np.full((len(rows), 3), np.nan)
    truth = rows[["x", "y", "z"]].to_numpy()
    gripper = rows[["gx", "gy", "gz"]].to_numpy()
    for i in range(len(rows)):
        sample = model.sample(truth[i], rng, gripper[i])
        if sample is not None:
            measured[i] = sample
    out[["mx", "my", "mz"]] = measured
    out["detected"] = ~np.isnan(measured[:, 0])
    return out


def error_statistics(rows: pd.DataFrame) -> dict[str, float]:
    """Bias and std of the error per axis (mm, detected objects on the belt), miss rates.

    ``miss_rate``: over all frames; ``miss_rate_far``: over frames of an object on the belt
    with the gripper far from it.
    """
    hits = rows[rows.detected & rows.on_belt]
    stats: dict[str, float] = {}
    for axis in ("x", "y"):
        error = 1e3 * (hits["m" + axis] - hits[axis])
        stats[f"bias_{axis}_mm"] = float(error.mean())
        stats[f"std_{axis}_mm"] = float(error.std())
    stats["miss_rate"] = float(1.0 - rows.detected.mean())
    far = rows[rows.on_belt & _far(rows)]
    stats["miss_rate_far"] = float(1.0 - far.detected.mean())
    stats["frames"] = float(len(rows))
    return stats


def calibrate(
    out: str,
    *,
    seed: int,
    object_kind: str = "cube",
    sweep_frames: int = 4000,
    episodes_per_speed: int = 5,
    command: str = "",
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run the camera path, fit the calibration, write it to ``out``; return its summary."""
    check_range("sweep_frames", sweep_frames, ge=1, cap=STEPS_CAP)
    # The miss rate and the errors in motion come from the episodes: at least one per speed.
    check_range("episodes", episodes_per_speed, ge=1, cap=EPISODES_CAP)
    check_range("seed", seed, ge=0, cap=SEED_CAP)
    check_writable("out", out)
    if object_kind not in OBJECTS:
        raise ValueError(f"object must be one of {', '.join(OBJECTS)}, got {object_kind!r}")
    rows = camera_path_rows(
        seed,
        object_kind=object_kind,
        sweep_frames=sweep_frames,
        episodes_per_speed=episodes_per_speed,
        progress=progress,
    )
    env = ConveyorPickPlace(ConveyorConfig(object=object_kind))
    camera = EdgeCamera(env.sim.scene)
    calibration = fit_calibration(
        rows,
        plane_z=camera.plane_z,
        camera_position=camera.camera.position.tolist(),
        object_kind=object_kind,
    )
    env.close()
    per_speed = {
        f"{speed:g}": error_statistics(group)
        for speed, group in rows[rows.source == "episode"].groupby("speed")
    }
    summary = {
        "camera_path": error_statistics(rows),
        "sweep": error_statistics(rows[rows.source == "sweep"]),
        "episodes_by_speed": per_speed,
    }
    provenance = {
        "command": command,
        "seed": seed,
        "sweep_frames": sweep_frames,
        "episodes_per_speed": episodes_per_speed,
        "speeds_mps": list(CALIBRATION_SPEEDS),
        "frame": f"{camera.camera.width}x{camera.camera.height} RGB, {camera.camera.frame_bytes} B",
        "measured": summary,
    }
    calibration = dataclasses.replace(calibration, provenance=provenance)
    calibration.to_json(out)
    return {"out": out, **CameraPerception(calibration).describe(), **summary}
