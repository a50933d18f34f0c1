"""A Gymnasium environment for cable insertion: a plug on a flexible cable held by the gripper, a socket.

The gripper (:mod:`s3k.sim.gripper`, its fingers shut on the cable) holds the cable ``CABLE_LENGTH`` above
the plug, so the plug dangles and swings: where it is must be seen, not read off the gripper's pose. The
cable is a chain of short capsule links on ball joints with stiffness and damping (a discrete elastic rod,
what MuJoCo's cable models build too, written out so that it needs no plugin). The socket is a square hole in
a block on the table; the plug fits it with 2 mm of play on each side.

- **Actions**: 6-D Cartesian velocity of the gripper, ``[vx, vy, vz, wx, wy, wz]`` in [-1, 1], scaled to
  ``MAX_SPEED`` m/s and ``MAX_ANGULAR`` rad/s, held for one control step at ``CONTROL_HZ`` (4 Hz).
- **Observations** (float32, 24): gripper position (3), rotation as its first two columns (6), linear and
  angular velocity (6), then the 3D keypoints ``plug_tip``, ``plug_base``, ``socket`` (9), in metres, world
  frame. The keypoints come from a detector callable: the ground truth by default, or e.g.
  :class:`s3k.robot.detect.RunDetector` on four rendered views; a keypoint the detector misses keeps its
  last value.
- **Keypoints**: ``plug_tip`` (centre of the plug's end face), ``plug_base`` (where the cable enters the
  plug), ``socket`` (centre of the hole's opening). Once the tip is inside the hole it cannot be seen, and a
  labeller would click the hole's opening: the ``plug_tip`` keypoint moves there.
- **Reward**: with ``distance = |plug_tip - socket| + |plug_base - socket|`` (the base reaches the opening at
  full insertion), each step gives ``1 - tanh(10 * distance)``. **Success** is ``distance < 2.5 cm`` (the
  plug at least 1.5 cm in): the episode ends and the remaining steps are paid at the full 1, so finishing
  early never costs reward. The episode also ends when the gripper strays out of the workspace (no further
  reward) and is truncated after ``EPISODE_SECONDS`` (10 s, 40 steps).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import gymnasium as gym
import mujoco
import numpy as np

from s3k.sim.camera import camera_from_model
from s3k.sim.gripper import Gripper, gripper_xml
from s3k.sim.render import MultiViewRenderer
from s3k.sim.scene import CameraSampler, quat_from_mat

CONTROL_HZ = 4.0
EPISODE_SECONDS = 10.0
MAX_SPEED = 0.1  # m/s at action 1
MAX_ANGULAR = 0.6  # rad/s at action 1
SUCCESS_DISTANCE = 0.025
KEYPOINTS = ["plug_tip", "plug_base", "socket"]
# Metres, m/s, rad/s: far beyond the workspace and the speeds; observations are clipped to it.
OBS_BOUND = 10.0
PLUG_HALF = (0.006, 0.006, 0.02)  # half extents: a 1.2 x 1.2 x 4 cm plug
HOLE_HALF = 0.008  # a 1.6 cm square hole
HOLE_DEPTH = 0.045
SOCKET_TOP = 0.05  # height of the socket's opening above the table
CABLE_LINKS = 6
LINK_LENGTH = 0.015
CABLE_LENGTH = CABLE_LINKS * LINK_LENGTH
WORKSPACE = np.array([[-0.3, -0.3, 0.03], [0.3, 0.3, 0.45]])  # bounds of the tool centre point

Detector = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def _model_xml(size: int) -> str:
    grip, actuators, equality = gripper_xml("gripper", group=0, rgba="0.3 0.32 0.36 1")
    # Cable links hang from the tool centre point; the last link carries the plug. The cable collides with
    # the table and the socket (bit 2) but not with the fingers (bit 1) that hold it.
    col = 'contype="2" conaffinity="2"'
    links, close = "", ""
    for i in range(CABLE_LINKS):
        pos = "0 0 -0.075" if i == 0 else f"0 0 {-LINK_LENGTH}"
        links += f"""
<body name="link{i}" pos="{pos}">
  <inertial pos="0 0 {-LINK_LENGTH / 2}" mass="0.004" diaginertia="1e-7 1e-7 2e-8"/>
  <joint name="link{i}" type="ball" stiffness="0.004" damping="0.006"/>
  <geom type="capsule" size="0.0035" fromto="0 0 0 0 0 {-LINK_LENGTH}" rgba="0.1 0.1 0.1 1" {col}/>"""
        close += "</body>"
    px, py, pz = PLUG_HALF
    plug = f"""
<body name="plug" pos="0 0 {-LINK_LENGTH}">
  <inertial pos="0 0 {-pz}" mass="0.02" diaginertia="3e-6 3e-6 5e-7"/>
  <joint name="plug" type="ball" stiffness="0.01" damping="0.006"/>
  <geom type="box" size="{px} {py} {pz}" pos="0 0 {-pz}" rgba="0.9 0.85 0.2 1" {col}
        friction="0.3 0.005 0.0001"/>
  <geom type="box" size="{px * 0.5} {py * 1.05} {pz * 0.3}" pos="0 0 {-1.75 * pz}" rgba="0.75 0.2 0.1 1"
        contype="0" conaffinity="0"/>
  <site name="plug_base" pos="0 0 0" size="0.002"/>
  <site name="plug_tip" pos="0 0 {-2 * pz}" size="0.002"/>
</body>"""
    grip = grip.replace("</body>\n</body>", "</body>" + links + plug + close + "\n</body>", 1)
    h = HOLE_HALF
    w = 0.02  # wall thickness
    walls = "".join(
        f'<geom type="box" size="{sx} {sy} {SOCKET_TOP / 2}" pos="{x} {y} {SOCKET_TOP / 2}" '
        f'rgba="0.2 0.45 0.8 1" contype="3" conaffinity="3" friction="0.3 0.005 0.0001"/>'
        for sx, sy, x, y in ((w / 2, h + w, h + w / 2, 0), (w / 2, h + w, -h - w / 2, 0),
                             (h, w / 2, 0, h + w / 2), (h, w / 2, 0, -h - w / 2)))
    cams = "".join(f'<camera name="cam{i}" pos="0 0 1" fovy="40"/>' for i in range(4))
    return f"""
<mujoco model="s3k-insertion">
  <compiler inertiafromgeom="false" angle="degree"/>
  <option timestep="0.002" cone="elliptic" impratio="3"/>
  <visual>
    <global offwidth="{size}" offheight="{size}"/>
    <quality shadowsize="0" offsamples="0"/>
    <headlight ambient="0.3 0.3 0.3" diffuse="0.4 0.4 0.4" specular="0.05 0.05 0.05"/>
    <map znear="0.01" zfar="10"/>
  </visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1="0.55 0.5 0.45" rgb2="0.45 0.4 0.36"
             width="64" height="64"/>
    <material name="grid" texture="grid" texrepeat="8 8"/>
  </asset>
  <worldbody>
    <light directional="true" castshadow="false" dir="0.3 0.2 -1" diffuse="0.6 0.6 0.6"/>
    <geom name="table" type="plane" size="2 2 0.1" material="grid" contype="3" conaffinity="3"/>
    {cams}
    <body name="socket" mocap="true" pos="0 0 0">
      {walls}
      <site name="socket" pos="0 0 {SOCKET_TOP}" size="0.002"/>
    </body>
    {grip}
  </worldbody>
  <actuator>{actuators}</actuator>
  <equality>{equality}</equality>
</mujoco>"""


def _rotation_error(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector (3,) that rotates ``R`` back to the identity (a vertical gripper)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    v = np.empty(3)
    mujoco.mju_quat2Vel(v, q, 1.0)
    return -v


class InsertionEnv(gym.Env):
    """Cable insertion (see the module docstring).

    Args:
        detector: ``(images (4, H, W, 3) uint8, K, R, t) -> (X (3, 3), valid (3,))`` in the order
            ``plug_tip, plug_base, socket``; None uses the ground truth (and renders nothing).
        image_size: rendered views' width and height (for the detector and :meth:`render_views`).
        camera_seed: draws the fixed rig of 4 cameras.
        expert_labels: each step's ``info["expert_action"]`` is then what :func:`scripted_action` does on
            the true state the step started from (:meth:`state_observation`), whatever was observed: the
            label an imitating agent learns from on the states it visits itself.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(self, detector: Detector | None = None, image_size: int = 64, camera_seed: int = 0,
                 render_mode: str | None = None, expert_labels: bool = False):
        super().__init__()
        self.detector = detector
        self.expert_labels = bool(expert_labels)
        self.image_size = int(image_size)
        self.render_mode = render_mode
        self.model = mujoco.MjModel.from_xml_string(_model_xml(self.image_size))
        self.data = mujoco.MjData(self.model)
        self.gripper = Gripper(self.model, "gripper")
        obj = mujoco.mjtObj
        self._sites = [mujoco.mj_name2id(self.model, obj.mjOBJ_SITE, n) for n in KEYPOINTS]
        socket = mujoco.mj_name2id(self.model, obj.mjOBJ_BODY, "socket")
        self._socket_mocap = int(self.model.body_mocapid[socket])
        self._cams = [mujoco.mj_name2id(self.model, obj.mjOBJ_CAMERA, f"cam{i}") for i in range(4)]
        sampler = CameraSampler(distance=(0.45, 0.55), elevation_deg=(30.0, 60.0), fovy_deg=40.0,
                                target=(0.0, 0.0, 0.08), target_jitter=0.0, roll_deg=0.0)
        eyes, mats = sampler.sample(np.random.default_rng([camera_seed, 0x1A5]), 4)
        for c, e, m in zip(self._cams, eyes, mats):
            self.model.cam_pos[c] = e
            self.model.cam_quat[c] = quat_from_mat(m)
        self._renderer: MultiViewRenderer | None = None
        self.substeps = int(round(1.0 / CONTROL_HZ / self.model.opt.timestep))
        self.max_steps = int(round(EPISODE_SECONDS * CONTROL_HZ))
        self.action_space = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)
        self.observation_space = gym.spaces.Box(-OBS_BOUND, OBS_BOUND, (24,), np.float32)
        self._steps = 0
        self._keypoints = np.zeros((3, 3))
        self._target_pos = np.zeros(3)
        self._target_rot = np.eye(3)

    # ------------------------------------------------------------------ state
    def true_keypoints(self) -> np.ndarray:
        """Ground-truth keypoints (3, 3): plug_tip (moved to the opening once inside the hole), plug_base,
        socket."""
        X = self.data.site_xpos[self._sites].copy()
        tip, socket = X[0], X[2]
        if tip[2] < socket[2] and np.all(np.abs(tip[:2] - socket[:2]) < HOLE_HALF + 0.002):
            X[0] = socket
        return X

    def views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The four rendered views ``uint8 (4, H, W, 3)`` and their OpenCV ``K, R, t``."""
        if self._renderer is None:
            self._renderer = MultiViewRenderer(self.model, self.image_size, self.image_size)
        mujoco.mj_camlight(self.model, self.data)
        rgb = self._renderer.render(self.data, self._cams)["rgb"]
        K, R, t = (np.array(a) for a in zip(*(camera_from_model(self.model, self.data, c, self.image_size,
                                                                 self.image_size) for c in self._cams)))
        return rgb, K, R, t

    def _observe_keypoints(self) -> np.ndarray:
        if self.detector is None:
            return self.true_keypoints()
        X, valid = self.detector(*self.views())
        X = np.asarray(X, dtype=np.float64)
        ok = np.asarray(valid, bool) & np.isfinite(X).all(axis=1)
        self._keypoints[ok] = X[ok]
        return self._keypoints.copy()

    def _obs(self, keypoints: np.ndarray | None = None) -> np.ndarray:
        R = self.gripper.rotation(self.data)
        if keypoints is None:
            keypoints = self._keypoints = self._observe_keypoints()
        parts = [self.gripper.tcp(self.data), R[:, 0], R[:, 1], self.gripper.velocity(self.data),
                 keypoints.ravel()]
        return np.clip(np.concatenate(parts), -OBS_BOUND, OBS_BOUND).astype(np.float32)

    def state_observation(self) -> np.ndarray:
        """The observation with the ground-truth keypoints, whatever the detector sees (for an expert)."""
        return self._obs(self.true_keypoints())

    def distance(self, keypoints: np.ndarray | None = None) -> float:
        """``|plug_tip - socket| + |plug_base - socket|`` of ``keypoints`` (default: the observed ones)."""
        X = self._keypoints if keypoints is None else keypoints
        return float(np.linalg.norm(X[0] - X[2]) + np.linalg.norm(X[1] - X[2]))

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        mujoco.mj_resetData(self.model, self.data)
        socket = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.0])
        self.data.mocap_pos[self._socket_mocap] = socket
        yaw = rng.uniform(-0.5, 0.5)
        self._target_rot = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                                     [0, 0, 1.0]])
        offset = rng.uniform(0.08, 0.16) * np.array([math.cos(a := rng.uniform(0, 2 * np.pi)), math.sin(a)])
        self._target_pos = np.array([socket[0] + offset[0], socket[1] + offset[1], rng.uniform(0.2, 0.26)])
        self.gripper.set_pose(self.data, self._target_pos, self._target_rot, kinematic=True)
        self.gripper.set_fingers(self.data, 1.0, kinematic=True)
        mujoco.mj_forward(self.model, self.data)
        for _ in range(self.substeps):  # let the cable come to rest
            mujoco.mj_step(self.model, self.data)
        self._steps = 0
        self._keypoints = self.true_keypoints()
        obs = self._obs()
        return obs, {"distance": self.distance(), "is_success": False}

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(6), -1.0, 1.0)
        expert = scripted_action(self.state_observation()) if self.expert_labels else None
        v, w = a[:3] * MAX_SPEED, a[3:] * MAX_ANGULAR
        dt = self.model.opt.timestep
        dR = np.empty(9)
        q = np.empty(4)
        mujoco.mju_axisAngle2Quat(q, w / (np.linalg.norm(w) + 1e-12), float(np.linalg.norm(w)) * dt)
        mujoco.mju_quat2Mat(dR, q)
        dR = dR.reshape(3, 3)
        for _ in range(self.substeps):  # the target moves smoothly; the hand follows through the weld
            self._target_pos = self._target_pos + v * dt
            self._target_rot = dR @ self._target_rot
            self.gripper.set_pose(self.data, self._target_pos, self._target_rot)
            mujoco.mj_step(self.model, self.data)
        self._steps += 1
        obs = self._obs()
        distance = self.distance()
        true_distance = self.distance(self.true_keypoints())
        tcp = self.gripper.tcp(self.data)
        strayed = bool(np.any(tcp < WORKSPACE[0]) or np.any(tcp > WORKSPACE[1])
                       or self.gripper.rotation(self.data)[2, 2] < 0.5)
        success = distance < SUCCESS_DISTANCE
        reward = 1.0 - math.tanh(10.0 * distance)
        if success:
            reward += self.max_steps - self._steps  # the steps left, at the full reward
        terminated = success or strayed
        truncated = not terminated and self._steps >= self.max_steps
        info = {"distance": distance, "true_distance": true_distance, "is_success": success,
                "strayed": strayed,
                "true_success": true_distance < SUCCESS_DISTANCE}
        if expert is not None:
            info["expert_action"] = expert
        return obs, float(reward), terminated, truncated, info

    def render(self):
        rgb = self.views()[0]
        return np.concatenate(list(rgb), axis=1)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def scripted_action(obs: np.ndarray, gain: float = 2.5) -> np.ndarray:
    """A demonstrator on the observation alone: bring the plug's tip above the socket, then lower it in,
    keeping the gripper vertical. Used to fill the replay buffer with demonstrations."""
    obs = np.asarray(obs, dtype=np.float64)
    c0, c1 = obs[3:6], obs[6:9]
    R = np.stack([c0, c1, np.cross(c0, c1)], axis=1)
    tip, base, socket = obs[15:18], obs[18:21], obs[21:24]
    lateral = socket[:2] - tip[:2]
    aligned = np.linalg.norm(lateral) < 0.004 and np.linalg.norm(base[:2] - socket[:2]) < 0.006
    z_goal = socket[2] - 0.03 if aligned else socket[2] + 0.015
    # gain < CONTROL_HZ: each step covers a part of the error, without overshoot
    v = np.r_[gain * lateral, gain * (z_goal - tip[2])] / MAX_SPEED
    v[2] = max(v[2], -0.4)  # lower gently: the plug swings when the gripper moves fast
    w = 2.0 * _rotation_error(R) / MAX_ANGULAR
    return np.clip(np.r_[v, w], -1.0, 1.0).astype(np.float32)
