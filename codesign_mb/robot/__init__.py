"""The robot: a Franka Panda modelled in Pinocchio, simulated in MuJoCo, one description.

- :mod:`~codesign_mb.robot.model`: :class:`PandaModel`, the Pinocchio model (kinematics,
  Jacobians, mass matrix, gravity/Coriolis, inverse kinematics) of ``models/panda``.
- :mod:`~codesign_mb.robot.osc`: :class:`OperationalSpaceController`, the 500 Hz
  operational-space inner loop turning a Cartesian gripper velocity into joint torques.
- :mod:`~codesign_mb.robot.native`: the inner loop's law, reference and substeps compiled
  with numba, calling MuJoCo's ``mj_step1``/``mj_step2`` directly (the plant's hot path).
- :mod:`~codesign_mb.robot.scene`: :func:`build_scene`, the MuJoCo conveyor scene
  (``models/scene_conveyor.xml`` + the same URDF) with the graspable object.
- :mod:`~codesign_mb.robot.simulator`: :class:`ConveyorSimulator`, physics + inner loop, one
  call per 40 ms control step; the Gymnasium task is :mod:`codesign_mb.plants.conveyor`.
- :mod:`~codesign_mb.robot.render`: headless rendering (EGL or OSMesa).
- :mod:`~codesign_mb.bench.env`: :func:`bench_env`, control steps per second.
"""

from codesign_mb.robot.model import GRIPPER_DOWN, PandaModel
from codesign_mb.robot.osc import OperationalSpaceController, OscGains
from codesign_mb.robot.scene import OBJECTS, build_scene
from codesign_mb.robot.simulator import ConveyorSimulator

__all__ = [
    "GRIPPER_DOWN",
    "OBJECTS",
    "ConveyorSimulator",
    "OperationalSpaceController",
    "OscGains",
    "PandaModel",
    "build_scene",
]
