"""The ``plush`` scene: an articulated plush toy among two distractor toys, and a gripper (docs/robot.md).

The toy is a capsule body with a sphere head, two front legs on hinge joints lying forward on the table, two
hind legs and a tail on a hinge. Its keypoints are ``head`` (centre of the head), ``body`` (centre of the
body), ``front_left_paw`` and ``front_right_paw`` (the ends of the front legs, inside them) and ``tail`` (its
tip, inside it). The left front paw wears a white sock and the right one a dark sock, so the two can be told
apart. Two distractor toys of the same build in other colours and proportions lie around it.

The scene is made of **arrangements**: arrangement ``a`` fixes where the three toys lie (a pure function of
the object seed and ``a``), one camera rig, the table and a base lighting; within an arrangement the toys and
cameras stay still while the gripper moves and the lighting changes a little from frame to frame.
Arrangements ``0 .. 6`` are for training (one labelled frame each, the rest unlabelled but still: the
labelled frame's 3D label holds for all of them), ``7 .. 9`` are the datasets' test arrangements. The grasp
trials of ``s3k robot grasp`` use held-out arrangements from ``7`` on (``7 .. 12`` by default: ``10 .. 12``
appear in no dataset). A dataset may have unlabelled frames of further arrangements, from ``13`` on
(``s3k simulate plush --unlabelled-arrangements N``). The frames carry the arrangement in the dataset's
``segment`` column.

Unlike the other scenes the toys and the gripper are dynamic (free joints, collisions with an invisible
floor at the table top), so :mod:`s3k.robot.grasp` can grasp in the very model the dataset was rendered from.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from s3k.sim.gripper import Gripper, gripper_xml, yaw_rotation
from s3k.sim.scene import CameraSampler, FrameSpec, Scene, floats

NUM_ARRANGEMENTS = 10  # the arrangements of a rendered dataset
TRAIN_ARRANGEMENTS = 7  # arrangements 0..6 train, 7..9 test; 10..12 only for grasp trials
FIRST_UNLABELLED_ARRANGEMENT = 13  # further arrangements of unlabelled frames only (unlabelled_arrangements)


@dataclasses.dataclass(frozen=True)
class ToyShape:
    """Proportions (metres) and colours of one toy."""

    body_radius: float = 0.03
    body_half: float = 0.04  # half the length of the body capsule's axis
    head_radius: float = 0.028
    leg_radius: float = 0.011
    leg_length: float = 0.075
    leg_splay: float = 0.35  # radians outwards from straight ahead
    tail_length: float = 0.07
    colour: tuple[float, float, float] = (0.78, 0.55, 0.3)
    left_sock: tuple[float, float, float] = (0.95, 0.95, 0.92)
    right_sock: tuple[float, float, float] = (0.15, 0.12, 0.1)

    @staticmethod
    def random(rng: np.random.Generator) -> ToyShape:
        r, g, b = (float(c) for c in rng.uniform(0.2, 0.95, 3))
        colour = (r, g, b)
        r, g, b = (float(c) for c in rng.uniform(0.1, 0.9, 3))
        sock = (r, g, b)
        return ToyShape(body_radius=rng.uniform(0.025, 0.035), body_half=rng.uniform(0.03, 0.05),
                        head_radius=rng.uniform(0.022, 0.034), leg_radius=rng.uniform(0.009, 0.013),
                        leg_length=rng.uniform(0.055, 0.085), leg_splay=rng.uniform(0.2, 0.5),
                        tail_length=rng.uniform(0.04, 0.09), colour=colour, left_sock=sock, right_sock=sock)

    def leg_line(self, side: int) -> tuple[np.ndarray, np.ndarray]:
        """Start (at the hip, the hinge) and end (the paw) of a front leg's axis in the toy frame;
        ``side`` +1 left, -1 right."""
        r = self.leg_radius
        hip = np.array([self.body_half * 0.6, side * self.body_radius * 0.7, r])
        d = np.array([math.cos(self.leg_splay), side * math.sin(self.leg_splay), 0.0])
        return hip, hip + self.leg_length * d

    def keypoints(self) -> np.ndarray:
        """(5, 3) keypoints in the toy frame (origin on the table under the body's centre): head, body,
        front_left_paw, front_right_paw, tail."""
        return np.array([self.head_centre(), [0.0, 0.0, self.body_radius], self.leg_line(1)[1],
                         self.leg_line(-1)[1], self.tail_line()[1]])

    def head_centre(self) -> np.ndarray:
        return np.array([self.body_half + 0.6 * self.body_radius, 0.0,
                         self.body_radius + 0.7 * self.head_radius])

    def tail_line(self) -> tuple[np.ndarray, np.ndarray]:
        r = 0.007
        root = np.array([-self.body_half - 0.8 * self.body_radius, 0.0, self.body_radius])
        return root, np.array([root[0] - self.tail_length, 0.0, r])


def toy_xml(name: str, shape: ToyShape, group: int = 0) -> str:
    """A toy body ``name`` (free joint) with hinged front legs and tail; keypoint sites ``name_kp{i}``."""
    s = shape
    col = floats([*s.colour, 1.0])
    dark = floats([0.05, 0.04, 0.04, 1.0])
    g = f'group="{group}" friction="1.2 0.02 0.001" condim="4"'
    zc = s.body_radius
    head = s.head_centre()
    hr = s.head_radius
    eyes = "".join(
        f'<geom type="sphere" size="{0.18 * hr:.4g}" '
        f'pos="{floats(head + hr * np.array([0.8, side * 0.35, 0.4]))}" '
        f'rgba="{dark}" contype="0" conaffinity="0" group="{group}" mass="0"/>' for side in (1, -1))
    nose = (f'<geom type="sphere" size="{0.2 * hr:.4g}" pos="{floats(head + hr * np.array([0.95, 0, 0]))}" '
            f'rgba="{dark}" contype="0" conaffinity="0" group="{group}" mass="0"/>')
    hind = "".join(
        f'<geom type="capsule" size="{s.leg_radius:.4g}" '
        f'fromto="{-s.body_half * 0.7:.4g} {side * s.body_radius * 0.6:.4g} {s.leg_radius:.4g} '
        f'{-s.body_half * 0.7 - 0.02:.4g} {side * (s.body_radius + 0.03):.4g} {s.leg_radius:.4g}" '
        f'rgba="{col}" {g}/>' for side in (1, -1))
    legs = ""
    for side, label, sock in ((1, "left", s.left_sock), (-1, "right", s.right_sock)):
        hip, paw = shape.leg_line(side)
        sock_start = hip + 0.7 * (paw - hip)
        legs += f"""
    <body name="{name}_{label}_leg" pos="{floats(hip)}">
      <inertial pos="{floats((paw - hip) / 2)}" mass="0.012" diaginertia="6e-6 6e-6 1e-6"/>
      <joint name="{name}_{label}_leg" type="hinge"
             axis="{floats([-math.sin(s.leg_splay) * side, math.cos(s.leg_splay), 0])}"
             range="-80 4" stiffness="0.02" damping="0.01"/>
      <geom type="capsule" size="{s.leg_radius:.4g}" fromto="0 0 0 {floats(sock_start - hip)}"
            rgba="{col}" {g}/>
      <geom type="capsule" size="{s.leg_radius * 1.05:.4g}"
            fromto="{floats(sock_start - hip)} {floats(paw - hip)}"
            rgba="{floats([*sock, 1.0])}" {g}/>
      <site name="{name}_kp{2 if side == 1 else 3}" pos="{floats(paw - hip)}" size="0.003"/>
    </body>"""
    root, tip = shape.tail_line()
    return f"""
<body name="{name}" pos="0 0 -1">
  <freejoint name="{name}"/>
  <inertial pos="0 0 {zc:.4g}" mass="0.12" diaginertia="1.2e-4 1.6e-4 1.6e-4"/>
  <geom type="capsule" size="{zc:.4g}" fromto="{-s.body_half:.4g} 0 {zc:.4g} {s.body_half:.4g} 0 {zc:.4g}"
        rgba="{col}" {g}/>
  <geom type="sphere" size="{hr:.4g}" pos="{floats(head)}" rgba="{col}" {g}/>
  {eyes}{nose}
  <geom type="ellipsoid" size="{0.35 * hr:.4g} {0.15 * hr:.4g} {0.4 * hr:.4g}"
        pos="{floats(head + hr * np.array([-0.2, 0.8, 0.75]))}" rgba="{col}" contype="0" conaffinity="0"
        group="{group}" mass="0"/>
  <geom type="ellipsoid" size="{0.35 * hr:.4g} {0.15 * hr:.4g} {0.4 * hr:.4g}"
        pos="{floats(head + hr * np.array([-0.2, -0.8, 0.75]))}" rgba="{col}" contype="0" conaffinity="0"
        group="{group}" mass="0"/>
  {hind}
  <site name="{name}_kp0" pos="{floats(head)}" size="0.003"/>
  <site name="{name}_kp1" pos="0 0 {zc:.4g}" size="0.003"/>
  {legs}
  <body name="{name}_tail" pos="{floats(root)}">
    <inertial pos="{floats((tip - root) / 2)}" mass="0.005" diaginertia="2e-6 2e-6 1e-7"/>
    <joint name="{name}_tail" type="hinge" axis="0 0 1" range="-40 40" stiffness="0.01" damping="0.005"/>
    <geom type="capsule" size="0.007" fromto="0 0 0 {floats(tip - root)}" rgba="{col}" {g}/>
    <site name="{name}_kp4" pos="{floats(tip - root)}" size="0.003"/>
  </body>
</body>"""


@dataclasses.dataclass(frozen=True)
class Arrangement:
    """Where the toys lie in one arrangement: ``(x, y, yaw)`` of the labelled toy and of each distractor."""

    index: int
    toy: tuple[float, float, float]
    distractors: tuple[tuple[float, float, float], ...]


class PlushScene(Scene):
    """A plush toy with articulated front legs and tail among two distractor toys on a table, and a gripper.

    See the module docstring: 10 arrangements (7 train, 3 test); within one, toys and cameras are still and
    the gripper and lighting move.
    """

    name = "plush"
    keypoints = ["head", "body", "front_left_paw", "front_right_paw", "tail"]
    cameras_sampler = CameraSampler(distance=(0.6, 0.75), elevation_deg=(35.0, 70.0), fovy_deg=30.0,
                                    target=(0.0, 0.0, 0.03), target_jitter=0.01, roll_deg=8.0)
    occlusion_test = True
    num_distractors = 2
    _FLOOR_GROUP = 4
    _SITE_GROUP = 5

    def _objects_xml(self, rng):
        self.shape = ToyShape()
        self.distractor_shapes = [ToyShape.random(np.random.default_rng([self.seed, 0x7011, i]))
                                  for i in range(self.num_distractors)]
        bodies = (f'<geom name="floor" type="plane" size="3 3 0.1" rgba="0 0 0 0" '
                  f'group="{self._FLOOR_GROUP}" '
                  'friction="1 0.02 0.001"/>')
        bodies += toy_xml("toy", self.shape)
        for i, sh in enumerate(self.distractor_shapes):
            bodies += toy_xml(f"distractor{i}", sh, group=self.OCCLUDER_GROUP)
        grip, self._actuator_xml, self._equality_xml = gripper_xml("gripper", group=self.OCCLUDER_GROUP)
        return "", bodies + grip

    def _xml(self) -> str:
        xml = super()._xml()
        # Physics for the grasp: small timestep, the gripper's actuators, no self-collision of a toy's parts.
        xml = xml.replace("<compiler inertiafromgeom=\"false\"/>",
                          '<compiler inertiafromgeom="false" angle="degree"/>\n'
                          '  <option timestep="0.002" cone="elliptic" impratio="5"/>')
        return xml.replace("</mujoco>", f"<actuator>{self._actuator_xml}</actuator>\n"
                                       f"<equality>{self._equality_xml}</equality>\n</mujoco>")

    def _setup(self):
        obj = mujoco.mjtObj
        self.gripper = Gripper(self.model, "gripper")
        self._toy_body = self._id(obj.mjOBJ_BODY, "toy")
        self._toy_sites = [self._id(obj.mjOBJ_SITE, f"toy_kp{k}") for k in range(len(self.keypoints))]
        self._toys = ["toy"] + [f"distractor{i}" for i in range(self.num_distractors)]
        self._free_qpos = {n: int(self.model.jnt_qposadr[self._id(obj.mjOBJ_JOINT, n)]) for n in self._toys}
        bodies = {n: self._subtree(self._id(obj.mjOBJ_BODY, n)) for n in self._toys}
        self._toy_geoms = np.flatnonzero(np.isin(self.model.geom_bodyid, bodies["toy"]))
        others = [b for n in self._toys[1:] for b in bodies[n]]
        self._occluders = np.concatenate([np.flatnonzero(np.isin(self.model.geom_bodyid, others)),
                                          self.gripper.geoms])
        self.arrangement: Arrangement | None = None

    def _subtree(self, root: int) -> list[int]:
        out = [root]
        for b in range(root + 1, self.model.nbody):
            if int(self.model.body_parentid[b]) in out:
                out.append(b)
        return out

    def _configure_renderer(self, renderer):
        renderer.option.geomgroup[self._FLOOR_GROUP] = 0

    # ------------------------------------------------------------------ arrangements
    def arrangement_of(self, index: int) -> Arrangement:
        """Arrangement ``index`` (>= 0; the datasets use 0-9): a function of the object seed and the index
        only, so adding arrangements changes none of the others."""
        if index < 0:
            raise ValueError(f"plush arrangement must be >= 0, got {index}")
        rng = np.random.default_rng([self.seed, 0xA77, index])
        r, a = 0.04 * math.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        toy = (r * math.cos(a), r * math.sin(a), float(rng.uniform(0, 2 * np.pi)))
        placed = [np.array(toy[:2])]
        distractors = []
        start = rng.uniform(0, 2 * np.pi)
        for i in range(self.num_distractors):
            ang = start + np.pi * i + rng.uniform(-0.6, 0.6)
            dist = rng.uniform(0.2, 0.26)
            xy = np.array(toy[:2]) + dist * np.array([math.cos(ang), math.sin(ang)])
            placed.append(xy)
            distractors.append((float(xy[0]), float(xy[1]), float(rng.uniform(0, 2 * np.pi))))
        return Arrangement(index, toy, tuple(distractors))

    def arrangement_cameras(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """The still camera rig of arrangement ``index``: positions (C, 3) and MuJoCo orientations."""
        return self.cameras_sampler.sample(np.random.default_rng([self.seed, 0xCA3, index]), self.num_cameras)

    def place_toy(self, name: str, x: float, y: float, yaw: float) -> None:
        """Puts toy ``name`` at rest on the table at ``(x, y)`` facing ``yaw``; its joints straight."""
        adr = self._free_qpos[name]
        half = yaw / 2
        self.data.qpos[adr:adr + 7] = [x, y, 0.0, math.cos(half), 0.0, 0.0, math.sin(half)]
        for j in range(self.model.njnt):
            body = int(self.model.jnt_bodyid[j])
            if self.model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and self._root_name(body) == name:
                self.data.qpos[self.model.jnt_qposadr[j]] = 0.0

    def _root_name(self, body: int) -> str:
        while int(self.model.body_parentid[body]) != 0:
            body = int(self.model.body_parentid[body])
        return mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_BODY, body) or ""

    def set_arrangement(self, index: int) -> Arrangement:
        """Places the toys and the camera rig of arrangement ``index``; velocities zero."""
        arr = self.arrangement_of(index)
        self.place_toy("toy", *arr.toy)
        for i, d in enumerate(arr.distractors):
            self.place_toy(f"distractor{i}", *d)
        self.data.qvel[:] = 0.0
        self.set_cameras(*self.arrangement_cameras(index))
        self.arrangement = arr
        return arr

    def place_gripper_randomly(self, rng: np.random.Generator) -> dict:
        """The gripper somewhere above the workspace, clear of the toys, at a random yaw and opening."""
        tcp = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(0.14, 0.32)])
        yaw = rng.uniform(0, 2 * np.pi)
        self.gripper.set_pose(self.data, tcp, yaw_rotation(yaw), kinematic=True)
        self.gripper.set_fingers(self.data, rng.uniform(0, 1) * 0.025, kinematic=True)
        return {"gripper_tcp": tcp.tolist(), "gripper_yaw": float(yaw)}

    # ------------------------------------------------------------------ Scene interface
    def sample(self, spec: FrameSpec, rng: np.random.Generator) -> dict:
        """Arrangement ``spec.segment`` (toys, cameras, table and a base lighting, all still), then this
        frame's lighting (a small change of the base) and gripper."""
        if spec.segment < 0:
            raise ValueError(f"plush scene: every frame needs an arrangement (FrameSpec.segment >= 0), got "
                             f"{spec.segment}")
        extra = self.arrangement_environment(spec.segment, rng)
        arr = self.set_arrangement(spec.segment)
        extra.update(self.place_gripper_randomly(rng))
        extra["arrangement"] = arr.index
        return extra

    def arrangement_environment(self, index: int, rng: np.random.Generator) -> dict:
        """The table and lighting of arrangement ``index``, the lighting changed a little by ``rng``.

        The light moves by about 10 degrees and its strength by 10% from frame to frame: the frames of an
        arrangement look alike (a 3D label carries over to them unchanged; propagation compares images),
        while the lighting still varies over the dataset as in the other scenes.
        """
        m = self.model
        base = np.random.default_rng([self.seed, 0x7AB, index])
        table = int(base.integers(self.num_tables))
        m.geom_matid[self._table_geom] = self._table_mats[table]
        m.mat_rgba[self._table_mats[table]] = [*base.uniform(0.75, 1.0, 3), 1.0]
        az = base.uniform(0, 2 * np.pi) + rng.uniform(-0.15, 0.15)
        el = np.deg2rad(base.uniform(30, 85) + rng.uniform(-5, 5))
        m.light_dir[self._light] = -np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        colour = base.uniform(0.35, 0.8) * base.uniform(0.9, 1.1, 3)
        m.light_diffuse[self._light] = colour * rng.uniform(0.9, 1.1)
        m.light_ambient[self._light] = base.uniform(0.1, 0.35) * rng.uniform(0.9, 1.1) * np.ones(3)
        m.vis.headlight.diffuse[:] = base.uniform(0.1, 0.35) * rng.uniform(0.9, 1.1) * np.ones(3)
        return {"table": table}

    def sample_objects(self, spec, rng):  # the arrangement is placed by sample()
        return {}

    def keypoints_world(self):
        return self.data.site_xpos[self._toy_sites].copy()

    def own_geoms(self):
        return self._toy_geoms

    def occluder_geoms(self):
        return self._occluders

    def toy_keypoint(self, name: str) -> np.ndarray:
        """World position (3,) of one keypoint of the labelled toy."""
        return self.keypoints_world()[self.keypoints.index(name)]


def arrangement_split(index: int) -> str:
    """"train" for arrangements 0-6 and the unlabelled ones from 13 on, "test" for 7-12."""
    return "train" if index < TRAIN_ARRANGEMENTS or index >= FIRST_UNLABELLED_ARRANGEMENT else "test"
