"""Build the MuJoCo conveyor scene with the Panda attached (``mujoco.MjSpec``).

The scene (``models/scene_conveyor.xml``) and the robot (``models/panda/panda.urdf``, the same
file Pinocchio reads) are composed here; the graspable object and the actuators are added
from code because they depend on the configuration:

- seven ``motor`` actuators on the arm joints take the torques of the operational-space
  controller, clamped by MuJoCo to the URDF effort limits (87 / 12 N m);
- two ``intvelocity`` actuators drive the fingers like the Panda hand: the command is a finger
  speed, integrated into a position target within [0, 0.04] m and tracked by a stiff servo
  whose force is limited to the grasp force, so a closed hand squeezes an object with that
  force;
- the object is a free body (cube or cylinder) on the belt.

Only the hand, the fingers, the object, the belt, the table and the floor collide; the arm
links are visual (keeping the contact search cheap; the conveyor task keeps them clear).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import mujoco
import numpy as np

from codesign_mb.robot.assets import PANDA_URDF, SCENE_XML, asset_path
from codesign_mb.robot.model import (
    ARM_ARMATURE,
    ARM_JOINTS,
    FINGER_ARMATURE,
    FINGER_JOINTS,
    N_ARM,
    TCP_FRAME,
)

__all__ = [
    "BELT_HALF_LENGTH",
    "BELT_HALF_WIDTH",
    "BELT_SURFACE_Z",
    "BELT_X",
    "OBJECTS",
    "ROBOT_PREFIX",
    "STRIPE_PERIOD",
    "ObjectShape",
    "Scene",
    "build_scene",
]

ROBOT_PREFIX = "robot/"
BELT_X = 0.5
"""Belt centre line (m); the belt runs along +y."""
BELT_HALF_WIDTH = 0.15
BELT_HALF_LENGTH = 1.0
BELT_SURFACE_Z = 0.06
"""Height of the belt surface above the robot base plane (m)."""
STRIPE_PERIOD = 0.2
"""Spacing of the visual belt stripes (m)."""

_HAND_BODIES = ("panda_link7", "panda_hand", "panda_leftfinger", "panda_rightfinger")
_FINGER_FRICTION = (1.5, 0.01, 0.0001)
_ROBOT_RGBA = (0.93, 0.93, 0.93, 1.0)
_FINGER_RGBA = (0.25, 0.25, 0.27, 1.0)


@dataclass(frozen=True)
class ObjectShape:
    """A graspable object: MuJoCo geom type and size, mass and half height (m, kg)."""

    geom_type: str
    size: tuple[float, ...]
    mass: float
    half_height: float
    rgba: tuple[float, float, float, float]


OBJECTS: dict[str, ObjectShape] = {
    "cube": ObjectShape("box", (0.0225, 0.0225, 0.0225), 0.1, 0.0225, (0.85, 0.25, 0.15, 1.0)),
    "cylinder": ObjectShape("cylinder", (0.025, 0.03), 0.1, 0.03, (0.15, 0.45, 0.85, 1.0)),
}
"""Objects by name: a 4.5 cm cube and a 5 cm x 6 cm upright cylinder, 100 g each."""


@dataclass(frozen=True)
class Scene:
    """A compiled scene and the indices the simulator needs (ids into ``model``)."""

    model: mujoco.MjModel
    object_shape: ObjectShape
    arm_qpos: slice
    arm_qvel: slice
    object_qpos: slice
    object_qvel: slice
    object_body: int
    object_geom: int
    left_finger_geoms: tuple[int, ...]
    right_finger_geoms: tuple[int, ...]
    hand_geoms: tuple[int, ...]
    belt_geom: int
    stripes_mocap: int
    tcp_site: int
    arm_actuators: slice
    finger_actuators: slice


def build_scene(
    object_kind: str = "cube",
    *,
    grasp_force_n: float = 20.0,
    finger_speed_mps: float = 0.1,
) -> Scene:
    """Compile the conveyor scene with the Panda and one object.

    Parameters
    ----------
    object_kind:
        A key of :data:`OBJECTS`.
    grasp_force_n:
        Force limit of each finger servo (N): the squeeze on a grasped object.
    finger_speed_mps:
        Maximum opening/closing speed of each finger (m/s).
    """
    if object_kind not in OBJECTS:
        raise ValueError(f"object must be one of {sorted(OBJECTS)}, got {object_kind!r}")
    shape = OBJECTS[object_kind]
    spec = mujoco.MjSpec.from_file(str(asset_path(SCENE_XML)))
    spec.compiler.fusestatic = True
    robot = _robot_spec(grasp_force_n, finger_speed_mps)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        spec.attach(robot, frame=spec.frame("robot_mount"), prefix=ROBOT_PREFIX)
    for name in ("panda_leftfinger", "panda_rightfinger"):
        spec.add_exclude(bodyname1=ROBOT_PREFIX + name, bodyname2=ROBOT_PREFIX + "panda_hand")
    spec.add_exclude(
        bodyname1=ROBOT_PREFIX + "panda_leftfinger", bodyname2=ROBOT_PREFIX + "panda_rightfinger"
    )
    _add_object(spec, shape)
    model = spec.compile()
    model.flg_surfacevel = True  # the belt speed is changed at run time, also from zero

    def jid(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, ROBOT_PREFIX + name)

    first, last = jid(ARM_JOINTS[0]), jid(FINGER_JOINTS[-1])
    if not (model.jnt_qposadr[first] == 0 and model.jnt_qposadr[last] == N_ARM + 1):
        raise RuntimeError("unexpected joint layout in the conveyor scene")
    obj_joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, "object")
    qadr, vadr = int(model.jnt_qposadr[obj_joint]), int(model.jnt_dofadr[obj_joint])
    obj_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "object")

    def body_geoms(name: str) -> tuple[int, ...]:
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, ROBOT_PREFIX + name)
        return tuple(int(g) for g in range(model.ngeom) if model.geom_bodyid[g] == body)

    hand_bodies = {
        mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, ROBOT_PREFIX + n) for n in _HAND_BODIES
    }
    hand_geoms = tuple(
        int(g)
        for g in range(model.ngeom)
        if model.geom_bodyid[g] in hand_bodies and model.geom_contype[g]
    )
    stripes = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "belt_stripes")
    return Scene(
        model=model,
        object_shape=shape,
        arm_qpos=slice(0, N_ARM + 2),
        arm_qvel=slice(0, N_ARM + 2),
        object_qpos=slice(qadr, qadr + 7),
        object_qvel=slice(vadr, vadr + 6),
        object_body=obj_body,
        object_geom=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "object"),
        left_finger_geoms=body_geoms("panda_leftfinger"),
        right_finger_geoms=body_geoms("panda_rightfinger"),
        hand_geoms=hand_geoms,
        belt_geom=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "belt"),
        stripes_mocap=int(model.body_mocapid[stripes]),
        tcp_site=mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ROBOT_PREFIX + "tcp"),
        arm_actuators=slice(0, N_ARM),
        finger_actuators=slice(N_ARM, N_ARM + 2),
    )


def robot_only_model() -> mujoco.MjModel:
    """The Panda alone (URDF import, same armature, no scene): for agreement tests."""
    return _robot_spec(20.0, 0.1).compile()


def _robot_spec(grasp_force_n: float, finger_speed_mps: float) -> mujoco.MjSpec:
    robot = mujoco.MjSpec.from_file(str(asset_path(PANDA_URDF)))
    for joint in robot.joints:
        joint.armature = ARM_ARMATURE if joint.name in ARM_JOINTS else FINGER_ARMATURE
    robot.body(TCP_FRAME).add_site(name="tcp", size=[0.005, 0.005, 0.005], rgba=[0, 1, 0, 0.0])
    for geom in robot.geoms:
        body = geom.parent.name
        if body in _HAND_BODIES and body != "panda_link7":
            geom.contype, geom.conaffinity = 1, 1
            if body != "panda_hand":
                geom.friction = list(_FINGER_FRICTION)
                geom.rgba = list(_FINGER_RGBA)
            else:
                geom.rgba = list(_ROBOT_RGBA)
        else:
            geom.contype, geom.conaffinity = 0, 0
            geom.rgba = list(_ROBOT_RGBA)
    limits = _urdf_effort_limits(robot)
    for name in ARM_JOINTS:
        act = robot.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_motor()
        act.ctrlrange = [-limits[name], limits[name]]
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    for name in FINGER_JOINTS:
        act = robot.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_intvelocity(kp=1000.0, dampratio=1.0)
        act.ctrlrange = [-finger_speed_mps, finger_speed_mps]
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.actrange = [0.0, 0.04]
        act.actlimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-grasp_force_n, grasp_force_n]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
    return robot


def _urdf_effort_limits(robot: mujoco.MjSpec) -> dict[str, float]:
    # The URDF importer keeps <limit effort=...> as the joint's actuator force range.
    return {joint.name: float(np.max(joint.actfrcrange)) for joint in robot.joints}


def _add_object(spec: mujoco.MjSpec, shape: ObjectShape) -> None:
    body = spec.worldbody.add_body(name="object", pos=[BELT_X, 0.0, 1.0])
    body.add_freejoint(name="object")
    geom_type = {"box": mujoco.mjtGeom.mjGEOM_BOX, "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER}
    body.add_geom(
        name="object",
        type=geom_type[shape.geom_type],
        size=list(shape.size) + [0.0] * (3 - len(shape.size)),
        mass=shape.mass,
        rgba=list(shape.rgba),
        contype=1,
        conaffinity=1,
        condim=4,
        friction=[1.0, 0.01, 0.0001],
    )
