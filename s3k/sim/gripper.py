"""A simulated parallel-jaw gripper: a mocap-driven palm with two slide fingers under position actuators.

The caller sets a mocap target's pose each control step (a Cartesian robot with a stiff arm); the hand (a
free body, gravity compensated) follows it through a weld equality constraint. A mocap body moved by hand
has no velocity in the dynamics, so friction could not drag a grasped object along with it; the welded hand
has a real velocity. The fingers are bodies on slide joints along the palm's y axis, each driven by a
position actuator whose target is how far the finger has closed (0 open, ``FINGER_TRAVEL`` shut).
Contacts between fingers and objects carry the load, so a grasp holds only when friction and the actuators'
force do.

Gripper frame: the fingers hang down along -z from the palm; the tool centre point (TCP) lies between the
fingertips, ``TCP_OFFSET`` below the palm's origin. A palm rotation of identity closes the fingers along
world y.
"""

from __future__ import annotations

import mujoco
import numpy as np

#: How far each finger travels from open to shut (metres); the inner faces are then 2 * 0.005 apart.
FINGER_TRAVEL = 0.025
#: Half the distance between the fingers' centres when open.
FINGER_OPEN_HALF = 0.03
#: Half thickness of a finger along the closing axis.
FINGER_HALF_THICKNESS = 0.005
#: The tool centre point in the palm frame: 1 cm above the fingertips.
TCP_OFFSET = np.array([0.0, 0.0, -0.075])


def gripper_xml(name: str = "gripper", group: int = 2, rgba: str = "0.35 0.37 0.4 1") -> tuple[str, str, str]:
    """(worldbody XML, actuator XML, equality XML) of a gripper called ``name`` whose geoms are in geom group
    ``group``.

    The bodies are ``name_target`` (mocap), ``name`` (the hand, a free body welded to the target),
    ``name_left`` and ``name_right`` (fingers); the actuators ``name_left`` and ``name_right`` take the
    closing distance in metres.
    """
    fh = FINGER_HALF_THICKNESS
    o = FINGER_OPEN_HALF
    inertial = '<inertial pos="0 0 -0.045" mass="0.05" diaginertia="2e-5 2e-5 1e-5"/>'
    hand_inertial = '<inertial pos="0 0 0.02" mass="0.5" diaginertia="5e-4 5e-4 5e-4"/>'
    finger_geom = (f'type="box" size="0.012 {fh} 0.0375" pos="0 0 -0.0475" rgba="{rgba}" group="{group}" '
                   'friction="1.5 0.02 0.001" condim="4" solref="0.005 1"')
    body = f"""
<body name="{name}_target" mocap="true" pos="0 0 0.4"/>
<body name="{name}" pos="0 0 0.4" gravcomp="1">
  <freejoint name="{name}"/>
  {hand_inertial}
  <geom name="{name}_palm" type="box" size="0.02 0.045 0.01" rgba="{rgba}" group="{group}"
        contype="0" conaffinity="0"/>
  <geom name="{name}_wrist" type="cylinder" size="0.015 0.04" pos="0 0 0.05" rgba="{rgba}"
        group="{group}" contype="0" conaffinity="0"/>
  <body name="{name}_left" pos="0 {o} 0" gravcomp="1">
    {inertial}
    <joint name="{name}_left" type="slide" axis="0 -1 0" range="0 {FINGER_TRAVEL}" damping="2"/>
    <geom name="{name}_left" {finger_geom}/>
  </body>
  <body name="{name}_right" pos="0 {-o} 0" gravcomp="1">
    {inertial}
    <joint name="{name}_right" type="slide" axis="0 1 0" range="0 {FINGER_TRAVEL}" damping="2"/>
    <geom name="{name}_right" {finger_geom}/>
  </body>
</body>"""
    actuators = "".join(
        f'<position name="{name}_{s}" joint="{name}_{s}" kp="400" ctrlrange="0 {FINGER_TRAVEL}" '
        f'forcerange="-25 25"/>' for s in ("left", "right"))
    equality = f'<weld body1="{name}" body2="{name}_target" solref="0.01 1"/>'
    return body, actuators, equality


class Gripper:
    """Handles of a gripper built by :func:`gripper_xml` in a compiled model.

    Args:
        model: the compiled ``mujoco.MjModel``.
        name: the gripper's name in the model.
    """

    def __init__(self, model: mujoco.MjModel, name: str = "gripper"):
        obj = mujoco.mjtObj
        self.model = model
        self.body = mujoco.mj_name2id(model, obj.mjOBJ_BODY, name)
        if self.body < 0:
            raise KeyError(f"no gripper body {name!r} in the model")
        self.target = mujoco.mj_name2id(model, obj.mjOBJ_BODY, f"{name}_target")
        self.mocap = int(model.body_mocapid[self.target])
        free = mujoco.mj_name2id(model, obj.mjOBJ_JOINT, name)
        self.free_qpos, self.free_qvel = int(model.jnt_qposadr[free]), int(model.jnt_dofadr[free])
        self.joints = [mujoco.mj_name2id(model, obj.mjOBJ_JOINT, f"{name}_{s}") for s in ("left", "right")]
        self.qpos = [int(model.jnt_qposadr[j]) for j in self.joints]
        self.qvel = [int(model.jnt_dofadr[j]) for j in self.joints]
        self.actuators = [mujoco.mj_name2id(model, obj.mjOBJ_ACTUATOR, f"{name}_{s}")
                          for s in ("left", "right")]
        self.geoms = np.flatnonzero(np.isin(model.geom_bodyid, [self.body, self.body + 1, self.body + 2]))

    def set_pose(self, data: mujoco.MjData, tcp: np.ndarray, rot: np.ndarray,
                 kinematic: bool = False) -> None:
        """Moves the target to put the tool centre point at ``tcp (3,)`` with palm rotation ``rot (3, 3)``
        (world); ``kinematic`` also puts the hand there at once, at rest (for renders and resets)."""
        rot = np.asarray(rot, dtype=np.float64).reshape(3, 3)
        pos = np.asarray(tcp, dtype=np.float64) - rot @ TCP_OFFSET
        q = np.empty(4)
        mujoco.mju_mat2Quat(q, rot.ravel())
        data.mocap_pos[self.mocap] = pos
        data.mocap_quat[self.mocap] = q
        if kinematic:
            data.qpos[self.free_qpos:self.free_qpos + 7] = [*pos, *q]
            data.qvel[self.free_qvel:self.free_qvel + 6] = 0.0

    def tcp(self, data: mujoco.MjData) -> np.ndarray:
        """World position (3,) of the hand's tool centre point (after a forward pass or step)."""
        return data.xpos[self.body] + self.rotation(data) @ TCP_OFFSET

    def rotation(self, data: mujoco.MjData) -> np.ndarray:
        """The hand's rotation (3, 3) in world."""
        return data.xmat[self.body].reshape(3, 3).copy()

    def velocity(self, data: mujoco.MjData) -> np.ndarray:
        """The hand's (linear (3,), angular (3,)) velocity in world, stacked (6,)."""
        out = np.empty(6)
        mujoco.mj_objectVelocity(self.model, data, mujoco.mjtObj.mjOBJ_BODY, self.body, out, 0)
        return np.concatenate([out[3:], out[:3]])

    def set_fingers(self, data: mujoco.MjData, closed: float, kinematic: bool = False) -> None:
        """Sets the fingers' target closing (0 open .. ``FINGER_TRAVEL`` shut); ``kinematic`` also puts the
        joints there at once (for renders without physics)."""
        closed = float(np.clip(closed, 0.0, FINGER_TRAVEL))
        for a, q in zip(self.actuators, self.qpos):
            data.ctrl[a] = closed
            if kinematic:
                data.qpos[q] = closed

    def opening(self, data: mujoco.MjData) -> float:
        """Distance between the fingers' inner faces (metres)."""
        closed = sum(float(data.qpos[q]) for q in self.qpos)
        return 2 * (FINGER_OPEN_HALF - FINGER_HALF_THICKNESS) - closed


def yaw_rotation(yaw: float) -> np.ndarray:
    """Rotation (3, 3) about world z by ``yaw`` radians (a top-down gripper's orientation)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
