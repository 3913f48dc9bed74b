"""The robot's physics: MuJoCo scene + Pinocchio operational-space inner loop.

One :meth:`ConveyorSimulator.step` is one control period: the Cartesian gripper velocity and
the grip command are held while ``n_substeps`` physics steps of ``model.opt.timestep`` run,
each preceded by the operational-space torques computed from the current state (DESIGN.md
step 7: 20 x 2 ms in a 40 ms step). Like dm_control's ``Physics``, this class knows nothing of
rewards or observations; :mod:`codesign_mb.plants.conveyor` builds the task on it.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache, partial

import mujoco
import numpy as np
import pinocchio as pin
from numpy.typing import ArrayLike, NDArray

from codesign_mb.robot.model import GRIPPER_DOWN, N_ARM, PandaModel
from codesign_mb.robot.osc import OperationalSpaceController, OscGains, SensedTcp
from codesign_mb.robot.scene import BELT_SURFACE_Z, BELT_X, STRIPE_PERIOD, Scene, build_scene

__all__ = ["HOME_TCP_POSITION", "ConveyorSimulator", "home_configuration"]

HOME_TCP_POSITION = (BELT_X, 0.0, BELT_SURFACE_Z + 0.24)
"""Where the gripper waits at the start of an episode: 24 cm above the belt centre."""

FINGER_OPEN = 0.04


@lru_cache(maxsize=8)
def home_configuration(position: tuple[float, float, float] = HOME_TCP_POSITION) -> tuple:
    """Arm + finger configuration with the TCP at ``position``, pointing down, fingers open."""
    robot = PandaModel()
    q = robot.inverse_kinematics(position, GRIPPER_DOWN, robot.neutral())
    q[N_ARM:] = FINGER_OPEN
    return tuple(float(x) for x in q)


class ConveyorSimulator:
    """MuJoCo conveyor scene with the Panda under operational-space control.

    Parameters
    ----------
    object_kind:
        Key of :data:`codesign_mb.robot.scene.OBJECTS`.
    n_substeps:
        Physics steps (of ``timestep_s``) per control step.
    timestep_s:
        Physics and inner-control step (s).
    gains:
        Operational-space gains.
    model_period:
        Substeps between recomputations of the task-space inertia (see
        :class:`~codesign_mb.robot.osc.OperationalSpaceController`).
    grasp_force_n, finger_speed_mps:
        Gripper force limit per finger and finger speed.
    compiled:
        Run the substeps between two model refreshes compiled
        (:mod:`codesign_mb.robot.native`); ``False``: the same law looped in Python, with
        each physics step's second half through :attr:`_mj_step2` (which the benchmark
        hooks to record the torques). Same torques either way.
    """

    def __init__(
        self,
        object_kind: str = "cube",
        *,
        n_substeps: int = 20,
        timestep_s: float = 0.002,
        gains: OscGains | None = None,
        model_period: int = 10,
        grasp_force_n: float = 20.0,
        finger_speed_mps: float = 0.1,
        compiled: bool = True,
    ) -> None:
        self.scene: Scene = build_scene(
            object_kind, grasp_force_n=grasp_force_n, finger_speed_mps=finger_speed_mps
        )
        self.model: mujoco.MjModel = self.scene.model
        self.model.opt.timestep = timestep_s
        self.data = mujoco.MjData(self.model)
        self.robot = PandaModel()
        self.osc = OperationalSpaceController(
            self.robot, gains, dt=timestep_s, model_period=model_period
        )
        self.n_substeps = int(n_substeps)
        self.finger_speed = float(finger_speed_mps)
        self.q_home = np.array(home_configuration())
        sc = self.scene
        # Live views into MjData, read by the inner loop without copies.
        self._q = self.data.qpos[sc.arm_qpos]
        self._v = self.data.qvel[sc.arm_qvel]
        self._arm_ctrl = self.data.ctrl[sc.arm_actuators]
        self._finger_ctrl = self.data.ctrl[sc.finger_actuators]
        self._object_pos = self.data.qpos[sc.object_qpos][:3]
        self._object_quat = self.data.qpos[sc.object_qpos][3:]
        self._object_vel = self.data.qvel[sc.object_qvel][:3]
        self._belt_surface = self.model.geom_surfacevel[sc.belt_geom]
        self._stripes = self.data.mocap_pos[sc.stripes_mocap]
        # The inner loop splits each physics step around the torque computation: mj_step1
        # (kinematics, bias forces of the current state), then mj_step2 (constraints,
        # integration); identical to mj_step (tests/test_robot.py).
        self._mj_step2 = partial(mujoco.mj_step2, self.model, self.data)
        self._sensed = SensedTcp(
            forward=partial(mujoco.mj_step1, self.model, self.data),
            rotation=self.data.site_xmat[sc.tcp_site],
            position=self.data.site_xpos[sc.tcp_site],
            bias=self.data.qfrc_bias[sc.arm_qvel],
            addresses=(self.model._address, self.data._address),
        )
        self.compiled = bool(compiled)
        self._bad_qacc = self.data.warning[mujoco.mjtWarning.mjWARN_BADQACC]  # a live view
        self._left_geoms = frozenset(sc.left_finger_geoms)
        self._right_geoms = frozenset(sc.right_finger_geoms)
        self._tcp_pos = np.zeros(3)
        self._tcp_vel = np.zeros(3)
        self._belt_speed = 0.0
        self._belt_offset = 0.0
        self._closed = False

    # ----------------------------------------------------------------------------- state
    @property
    def control_period_s(self) -> float:
        return self.n_substeps * float(self.model.opt.timestep)

    @property
    def time(self) -> float:
        return float(self.data.time)

    @property
    def belt_speed(self) -> float:
        return self._belt_speed

    @property
    def gripper_closed(self) -> bool:
        """The last grip command (True: closing/closed)."""
        return self._closed

    def reset(
        self,
        *,
        object_position: ArrayLike,
        belt_speed: float,
        q: ArrayLike | None = None,
    ) -> None:
        """Put the arm at ``q`` (default: home) at rest and the object at ``object_position``."""
        m, d, sc = self.model, self.data, self.scene
        mujoco.mj_resetData(m, d)
        q = self.q_home if q is None else np.asarray(q, dtype=float)
        d.qpos[sc.arm_qpos] = q
        d.act[:] = q[N_ARM:]  # finger position targets
        obj = d.qpos[sc.object_qpos]
        obj[:3] = object_position
        obj[3:] = (1.0, 0.0, 0.0, 0.0)
        self._belt_offset = 0.0
        self._closed = False
        d.ctrl[sc.finger_actuators] = 0.0
        self.set_belt_speed(belt_speed)
        d.qvel[sc.object_qvel][:3] = (0.0, belt_speed, 0.0)
        mujoco.mj_forward(m, d)
        self.osc.reset(q, posture=self.q_home)
        self._measure()

    def place_object(self, position: ArrayLike, velocity: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        """Put the object at ``position``, upright, moving at ``velocity`` (m/s), not turning.

        A teleport, for the conveyor's scenarios: an object that appears on the belt mid-episode,
        or one parked off the scene until then.
        """
        sc = self.scene
        obj = self.data.qpos[sc.object_qpos]
        obj[:3] = position
        obj[3:] = (1.0, 0.0, 0.0, 0.0)
        vel = self.data.qvel[sc.object_qvel]
        vel[:] = 0.0
        vel[:3] = velocity
        mujoco.mj_forward(self.model, self.data)

    def push_object(self, linear: ArrayLike, yaw_rate: float = 0.0) -> None:
        """Add ``linear`` (m/s, world frame, shape ``(3,)``) to the object's velocity and
        ``yaw_rate`` (rad/s) to its angular velocity about its own z axis: a slip or a turn."""
        vel = self.data.qvel[self.scene.object_qvel]
        vel[:3] += np.asarray(linear, dtype=float)
        vel[5] += float(yaw_rate)

    def set_belt_speed(self, speed: float) -> None:
        """Belt surface speed along +y (m/s)."""
        self._belt_speed = float(speed)
        self._belt_surface[1] = self._belt_speed

    def step(self, velocity: ArrayLike, close: bool) -> None:
        """One control period: track the TCP ``velocity`` (m/s) and open/close the gripper."""
        self.osc.set_velocity_command(velocity)
        self._closed = bool(close)
        self._finger_ctrl[:] = -self.finger_speed if close else self.finger_speed
        # Torque limits: the arm actuators' ctrlrange (the URDF effort limits) clamps.
        self.osc.run(
            self._q,
            self._v,
            self._arm_ctrl,
            self._mj_step2,
            self.n_substeps,
            clip=False,
            sensed=self._sensed if self.compiled else replace(self._sensed, addresses=None),
        )
        if self._bad_qacc.number:
            raise RuntimeError(
                "the simulation diverged (MuJoCo reported a bad acceleration); reset the env"
            )
        self._belt_offset = (
            self._belt_offset + self._belt_speed * self.control_period_s
        ) % STRIPE_PERIOD
        self._stripes[1] = self._belt_offset
        self._measure()

    # ----------------------------------------------------------------------------- readouts
    def joint_positions(self) -> NDArray[np.float64]:
        return self._q.copy()

    def joint_velocities(self) -> NDArray[np.float64]:
        return self._v.copy()

    def tcp_position(self) -> NDArray[np.float64]:
        """TCP position (m) at the current state (Pinocchio; equal to MuJoCo's site)."""
        return self._tcp_pos.copy()

    def tcp_velocity(self) -> NDArray[np.float64]:
        """TCP linear velocity (m/s) at the current state."""
        return self._tcp_vel.copy()

    def finger_width(self) -> float:
        """Distance between the finger pads (m): the sum of the two finger joints."""
        return float(self._q[N_ARM] + self._q[N_ARM + 1])

    def object_position(self) -> NDArray[np.float64]:
        return self._object_pos.copy()

    def object_velocity(self) -> NDArray[np.float64]:
        """Linear velocity of the object's centre (m/s, world frame)."""
        return self._object_vel.copy()

    def object_quaternion(self) -> NDArray[np.float64]:
        return self._object_quat.copy()

    def finger_contacts(self) -> tuple[bool, bool]:
        """Whether the left and the right finger touch the object (contacts of the last step)."""
        d = self.data
        obj, left_geoms, right_geoms = self.scene.object_geom, self._left_geoms, self._right_geoms
        left = right = False
        for g1, g2 in d.contact.geom[: d.ncon].tolist():  # a handful of contacts
            other = g2 if g1 == obj else g1 if g2 == obj else -1
            left = left or other in left_geoms
            right = right or other in right_geoms
        return left, right

    def _measure(self) -> None:
        # TCP position and velocity of the current state, once per control step.
        robot = self.robot
        J = pin.computeFrameJacobian(
            robot.model, robot.data, self._q, robot.tcp_id, pin.LOCAL_WORLD_ALIGNED
        )
        self._tcp_pos = pin.updateFramePlacement(robot.model, robot.data, robot.tcp_id).translation
        self._tcp_vel = J[:3] @ self._v
