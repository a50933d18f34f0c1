"""The paper's simulated scenes: ``box``, ``distractors`` and ``category`` (docs/scenes.md), and ``plush``.

Each is a :class:`s3k.sim.scene.Scene`; :func:`make_scene` builds one by name. The shared records
(:class:`FrameSpec`, :class:`SimFrame`) and the visibility helpers live in :mod:`s3k.sim.scene`; the plush
toy scene of the grasping experiment (docs/robot.md) in :mod:`s3k.sim.plush`.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from s3k.sim import meshes, textures
from s3k.sim.plush import PlushScene
from s3k.sim.scene import (
    BOX_DIMS,
    NUM_INSTANCES,
    CameraSampler,
    Scene,
    axis_rotation,
    floats,
    quat_from_mat,
    resting_box_pose,
)


class BoxScene(Scene):
    """A printed board-game box (19.9 x 10.5 x 1.7 cm) lying on a table in a random stable pose.

    Keypoints: three corners of the lid (the +z face, whose print has a title band along its top edge), named
    as the lid's print reads: ``lid_top_left`` (-x, +y), ``lid_top_right`` (+x, +y), ``lid_bottom_right``
    (+x, -y), in the box's frame.
    """

    name = "box"
    keypoints = ["lid_top_left", "lid_top_right", "lid_bottom_right"]
    placement_radius = 0.05

    def _objects_xml(self, rng):
        half = np.asarray(BOX_DIMS) / 2
        self.box_half = half
        assets = self._texture("box", textures.box_faces(rng, BOX_DIMS, 128), cube=True)
        assets += '<material name="box" texture="box" specular="0.2" shininess="0.3"/>'
        body = (f'<body name="box" mocap="true"><geom name="box" type="box" size="{floats(half)}" '
                f'material="box" contype="0" conaffinity="0"/></body>')
        return assets, body

    def _setup(self):
        self._box_body = self._id(mujoco.mjtObj.mjOBJ_BODY, "box")
        self._box_geom = self._id(mujoco.mjtObj.mjOBJ_GEOM, "box")
        hx, hy, hz = self.box_half
        self._box_keypoints = np.array([[-hx, hy, hz], [hx, hy, hz], [hx, -hy, hz]])

    def place_box(self, pos: np.ndarray, rot: np.ndarray) -> None:
        self.set_mocap(self._box_body, pos, rot)

    def sample_box(self, rng: np.random.Generator) -> dict:
        rot, z, face = resting_box_pose(rng, self.box_half)
        r = self.placement_radius * math.sqrt(rng.uniform())
        a = rng.uniform(0, 2 * np.pi)
        pos = np.array([r * math.cos(a), r * math.sin(a), z])
        self.place_box(pos, rot)
        return {"box_pos": pos.tolist(), "box_quat": quat_from_mat(rot).tolist(), "resting_face": face}

    def sample_objects(self, spec, rng):
        return self.sample_box(rng)

    def keypoints_world(self):
        b = self._box_body
        return self.data.xpos[b] + self._box_keypoints @ self.data.xmat[b].reshape(3, 3).T

    def own_geoms(self):
        return np.array([self._box_geom])


# ====================================================================== distractors
@dataclasses.dataclass(frozen=True)
class DistractorSpec:
    """One distractor object of a segment: shape, full extents (metres) and material index."""

    shape: str  # "box" or "cylinder"
    dims: tuple[float, float, float]
    material: int


class DistractorScene(BoxScene):
    """The box among distractors of similar size and print that change in segments along a timeline.

    Each segment has its own distractor set (shapes, sizes and prints of ``num_slots`` objects); their poses
    change every frame. Training segments draw prints from one pool and test segments from a disjoint pool,
    so test frames show distractor sets never seen in training. Visibility uses a segmentation and depth
    test: a keypoint behind a distractor is flagged not visible.
    """

    name = "distractors"
    occlusion_test = True
    num_slots = 4
    num_train_textures = 16
    num_test_textures = 8

    def _objects_xml(self, rng):
        assets, bodies = super()._objects_xml(rng)
        for i in range(self.num_train_textures + self.num_test_textures):
            dims = (rng.uniform(0.12, 0.26), rng.uniform(0.06, 0.14), rng.uniform(0.015, 0.05))
            assets += self._texture(f"dist{i}", textures.box_faces(rng, dims, 64), cube=True)
            assets += f'<material name="dist{i}" texture="dist{i}" specular="0.2" shininess="0.3"/>'
        for s in range(self.num_slots):
            bodies += (f'<body name="slot{s}" mocap="true" pos="0 0 -1"><geom name="slot{s}" type="box" '
                       f'size="0.05 0.05 0.05" material="dist0" group="{self.OCCLUDER_GROUP}" contype="0" '
                       f'conaffinity="0"/></body>')
        return assets, bodies

    def _setup(self):
        super()._setup()
        self._slot_bodies = [self._id(mujoco.mjtObj.mjOBJ_BODY, f"slot{s}") for s in range(self.num_slots)]
        self._slot_geoms = [self._id(mujoco.mjtObj.mjOBJ_GEOM, f"slot{s}") for s in range(self.num_slots)]
        n = self.num_train_textures + self.num_test_textures
        self._dist_mats = [self._id(mujoco.mjtObj.mjOBJ_MATERIAL, f"dist{i}") for i in range(n)]
        self._segment_cache: dict[tuple[int, bool], list[DistractorSpec]] = {}

    def distractor_set(self, segment: int, test: bool) -> list[DistractorSpec]:
        """The distractor set of a timeline segment (deterministic in the seed and the segment)."""
        key = (segment, test)
        if key not in self._segment_cache:
            rng = np.random.default_rng([self.seed, 0xD157, segment, int(test)])
            n_train, n_test = self.num_train_textures, self.num_test_textures
            pool = np.arange(n_train, n_train + n_test) if test else np.arange(n_train)
            mats = rng.choice(pool, size=self.num_slots, replace=False)
            specs = []
            for m in mats:
                if rng.uniform() < 0.6:
                    dims = (rng.uniform(0.12, 0.26), rng.uniform(0.06, 0.14), rng.uniform(0.015, 0.05))
                    size = (float(dims[0]), float(dims[1]), float(dims[2]))
                    specs.append(DistractorSpec("box", size, int(m)))
                else:
                    d = rng.uniform(0.05, 0.1)
                    specs.append(DistractorSpec("cylinder", (d, d, float(rng.uniform(0.06, 0.2))), int(m)))
            self._segment_cache[key] = specs
        return self._segment_cache[key]

    def set_distractor(self, slot: int, spec: DistractorSpec, pos: np.ndarray, rot: np.ndarray) -> None:
        """Shapes slot ``slot`` as ``spec`` and places it (centre ``pos``, rotation ``rot``)."""
        g = self._slot_geoms[slot]
        m = self.model
        half = np.asarray(spec.dims) / 2
        if spec.shape == "box":
            m.geom_type[g] = mujoco.mjtGeom.mjGEOM_BOX
            m.geom_size[g] = half
        elif spec.shape == "cylinder":
            m.geom_type[g] = mujoco.mjtGeom.mjGEOM_CYLINDER
            m.geom_size[g] = [half[0], half[2], 0.0]
        else:
            raise ValueError(f"distractor shape must be 'box' or 'cylinder', got {spec.shape!r}")
        m.geom_rbound[g] = float(np.linalg.norm(half))
        m.geom_matid[g] = self._dist_mats[spec.material]
        self.set_mocap(self._slot_bodies[slot], pos, rot)

    def sample_objects(self, spec, rng):
        extra = self.sample_box(rng)
        test = spec.split == "test"
        dset = self.distractor_set(max(spec.segment, 0), test)
        box_xy = np.asarray(extra["box_pos"][:2])
        placed = [(box_xy, float(np.linalg.norm(self.box_half[:2])) * 0.8)]
        for slot, d in enumerate(dset):
            half = np.asarray(d.dims) / 2
            if d.shape == "box":
                rot, z, _ = resting_box_pose(rng, half, (0.4, 0.4, 0.05, 0.05, 0.05, 0.05))
                radius = float(np.linalg.norm(half[:2])) * 0.8
            else:
                rot, z = axis_rotation("z", rng.uniform(0, 2 * np.pi)), half[2]
                radius = half[0]
            # Rejection-sample a spot near the box that does not overlap what is already placed.
            for _ in range(50):
                r, a = rng.uniform(0.08, 0.28), rng.uniform(0, 2 * np.pi)
                xy = box_xy + r * np.array([math.cos(a), math.sin(a)])
                if all(np.linalg.norm(xy - p) > radius + q for p, q in placed):
                    break
            placed.append((xy, radius))
            self.set_distractor(slot, d, np.array([xy[0], xy[1], z]), rot)
        extra["distractors"] = [dataclasses.asdict(d) for d in dset]
        return extra

    def occluder_geoms(self):
        return np.array(self._slot_geoms)


# ====================================================================== category
@dataclasses.dataclass(frozen=True)
class MugShape:
    """Parameters of one procedurally generated mug (metres)."""

    height: float
    r_bottom: float
    r_top: float
    bulge: float
    wall: float
    handle_z: float  # height of the handle's centre
    handle_reach: float  # how far the handle's ring sticks out of the wall
    handle_half_height: float
    handle_tube: float  # radius of the handle's tube
    handle_squareness: float  # superellipse exponent of the handle's centre line (2 = ellipse)

    @staticmethod
    def random(rng: np.random.Generator) -> MugShape:
        height = rng.uniform(0.075, 0.12)
        r_bottom = rng.uniform(0.03, 0.042)
        r_top = r_bottom * rng.uniform(0.9, 1.25)
        hh = min(rng.uniform(0.022, 0.04), 0.36 * height)
        return MugShape(
            height=height, r_bottom=r_bottom, r_top=r_top, bulge=rng.uniform(-0.003, 0.006),
            wall=rng.uniform(0.003, 0.005), handle_z=height * rng.uniform(0.45, 0.6),
            handle_reach=rng.uniform(0.02, 0.035), handle_half_height=hh,
            handle_tube=rng.uniform(0.004, 0.007),
            handle_squareness=rng.uniform(2.0, 4.0),
        )

    def radius_at(self, z: float) -> float:
        return float(meshes.cup_radius(self.height, self.r_bottom, self.r_top, self.bulge, z))

    def handle_centre_line(self, n: int = 9) -> np.ndarray:
        """(n, 3) points of the handle's tube centre line, in the mug frame (handle on +x)."""
        wall = self.radius_at(self.handle_z) - 0.6 * self.wall
        p = 2.0 / self.handle_squareness
        ang = np.linspace(-np.pi / 2, np.pi / 2, n)
        x = np.sign(np.cos(ang)) * np.abs(np.cos(ang)) ** p * self.handle_reach
        z = np.sign(np.sin(ang)) * np.abs(np.sin(ang)) ** p * self.handle_half_height
        return np.stack([wall + x, np.zeros(n), self.handle_z + z], 1)

    def keypoints(self) -> np.ndarray:
        """(3, 3) in the mug frame: ``handle`` (centre of the handle's ring), ``body_centre``, ``lip`` (rim
        point opposite the handle)."""
        outer = self.radius_at(self.handle_z)
        # The loop's hole runs from the body's outer wall to the inner edge of the handle's tube.
        inner_edge = outer - 0.6 * self.wall + self.handle_reach - self.handle_tube
        return np.array([
            [0.5 * (outer + inner_edge), 0.0, self.handle_z],
            [0.0, 0.0, self.height / 2],
            [-(self.r_top - 0.5 * self.wall), 0.0, self.height],  # middle of the rim's thickness
        ])


class CategoryScene(Scene):
    """One object category, mugs, in 16 procedurally varied instances (shape, handle and print).

    Instances 0-11 are the training pool, 12-15 are held out for testing. Keypoints: ``handle`` (centre of the
    handle's ring, inside the loop), ``body_centre`` (centre of the body, inside the object) and ``lip`` (the
    rim point opposite the handle). A mug stands upright at a random yaw near the workspace centre.
    """

    name = "category"
    keypoints = ["handle", "body_centre", "lip"]
    cameras_sampler = CameraSampler(distance=(0.42, 0.58), elevation_deg=(20.0, 70.0), fovy_deg=22.0,
                                    target=(0.0, 0.0, 0.05), target_jitter=0.01)
    placement_radius = 0.03
    _HIDDEN_GROUP = 5

    def _objects_xml(self, rng):
        self.shapes = [MugShape.random(np.random.default_rng([self.seed, 0xC0F, i]))
                       for i in range(NUM_INSTANCES)]
        assets, bodies = "", ""
        for i, shape in enumerate(self.shapes):
            trng = np.random.default_rng([self.seed, 0x7E1, i])
            tex, _ = textures.cup_texture(trng, 128, 256)
            assets += self._texture(f"mug{i}", tex)
            assets += f'<material name="mug{i}" texture="mug{i}" specular="0.3" shininess="0.5"/>'
            strips = meshes.cup_profile(shape.height, shape.r_bottom, shape.r_top, shape.wall,
                                        bottom=0.006, bulge=shape.bulge)
            v, f, uv = meshes.lathe(strips, segments=32)
            assets += meshes.mesh_xml(f"mug{i}", v, f, uv)
            handle_rgba = (np.r_[textures.random_colour(trng) / 255, 1.0] if trng.uniform() < 0.5
                           else np.r_[tex[-8:].reshape(-1, 3).mean(0) / 255, 1.0])
            line = shape.handle_centre_line()
            caps = "".join(
                f'<geom name="mug{i}_handle{j}" type="capsule" '
                f'fromto="{floats(line[j])} {floats(line[j + 1])}" '
                f'size="{shape.handle_tube:.5g}" rgba="{floats(handle_rgba)}" contype="0" conaffinity="0"/>'
                for j in range(len(line) - 1)
            )
            bodies += (f'<body name="mug{i}" mocap="true" pos="0 0 -1"><geom name="mug{i}" type="mesh" '
                       f'mesh="mug{i}" material="mug{i}" contype="0" conaffinity="0"/>{caps}</body>')
        return assets, bodies

    def _setup(self):
        self._mug_bodies = [self._id(mujoco.mjtObj.mjOBJ_BODY, f"mug{i}") for i in range(NUM_INSTANCES)]
        self._mug_geoms = [np.flatnonzero(self.model.geom_bodyid == b) for b in self._mug_bodies]
        self._keypoints_local = [s.keypoints() for s in self.shapes]
        self.instance = 0

    def _configure_renderer(self, renderer):
        renderer.option.geomgroup[self._HIDDEN_GROUP] = 0

    def set_instance(self, instance: int, pos: np.ndarray, rot: np.ndarray) -> None:
        """Shows instance ``instance`` only, at ``pos`` with rotation ``rot``."""
        if not 0 <= instance < NUM_INSTANCES:
            raise ValueError(f"category instance must be in [0, {NUM_INSTANCES}), got {instance}")
        for i, geoms in enumerate(self._mug_geoms):
            self.model.geom_group[geoms] = 0 if i == instance else self._HIDDEN_GROUP
        self.instance = instance
        self.set_mocap(self._mug_bodies[instance], pos, rot)

    def sample_objects(self, spec, rng):
        if spec.instance < 0:
            raise ValueError("category scene: every frame needs an instance (FrameSpec.instance >= 0)")
        r = self.placement_radius * math.sqrt(rng.uniform())
        a = rng.uniform(0, 2 * np.pi)
        pos = np.array([r * math.cos(a), r * math.sin(a), 0.0])
        rot = axis_rotation("z", rng.uniform(0, 2 * np.pi))
        self.set_instance(spec.instance, pos, rot)
        return {"object_pos": pos.tolist(), "object_quat": quat_from_mat(rot).tolist()}

    def keypoints_world(self):
        b = self._mug_bodies[self.instance]
        return self.data.xpos[b] + self._keypoints_local[self.instance] @ self.data.xmat[b].reshape(3, 3).T

    def own_geoms(self):
        return self._mug_geoms[self.instance]


SCENES: dict[str, type[Scene]] = {"box": BoxScene, "distractors": DistractorScene, "category": CategoryScene,
                                  "plush": PlushScene}


def make_scene(name: str, size: int = 128, seed: int = 0, **kwargs) -> Scene:
    """Builds scene ``name`` ("box", "distractors", "category" or "plush")."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    return SCENES[name](size=size, seed=seed, **kwargs)
