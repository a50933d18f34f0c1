"""What every simulated scene shares: frame specs and records, camera sampling, the base :class:`Scene`.

The scenes themselves (``box``, ``distractors``, ``category``) are in :mod:`s3k.sim.scenes`. A scene owns
one compiled MuJoCo model (textures baked from the object seed), its ``MjData`` and a renderer.
Frames are made in two steps so that tests can stage exact situations:

1. ``scene.sample(spec, rng)`` draws a random state for frame ``spec`` (object pose, distractors, instance,
   lighting, table, four cameras) and applies it, returning the metadata to store with the frame;
2. ``scene.capture(spec)`` renders the four views of the current state and returns a :class:`SimFrame` with
   images, OpenCV calibration, ground-truth 3D keypoints, their projections and visibility flags.

World frame: z up, the table top is the plane z = 0, the workspace centre is the origin; metres.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from s3k.sim import textures
from s3k.sim.camera import camera_from_model, look_at_xmat, project_points
from s3k.sim.render import MultiViewRenderer

#: Full extents (x, y, z) of the board-game box in metres: 19.9 x 10.5 cm lid, 1.7 cm thick.
BOX_DIMS = (0.199, 0.105, 0.017)

#: Number of procedurally varied instances in the ``category`` scene; the last 4 are held out for testing.
NUM_INSTANCES = 16
NUM_TRAIN_INSTANCES = 12

SPLITS = ("labelled", "unlabelled", "test")


@dataclasses.dataclass(frozen=True)
class FrameSpec:
    """What a frame is before it is rendered.

    Attributes:
        frame_id: index of the frame in the dataset (also seeds its randomness).
        split: "labelled", "unlabelled" or "test".
        segment: distractor segment on the timeline (``distractors`` scene), else -1.
        instance: object instance (``category`` scene), else -1.
    """

    frame_id: int
    split: str
    segment: int = -1
    instance: int = -1


@dataclasses.dataclass
class SimFrame:
    """One rendered multi-view frame (C cameras, K keypoints).

    Attributes:
        frame_id, split: as in :class:`FrameSpec`.
        images: uint8 (C, H, W, 3) RGB, row 0 at the top.
        K: float64 (C, 3, 3) intrinsics; R: (C, 3, 3) and t: (C, 3) world -> camera (OpenCV).
        points3d: float64 (K, 3) ground-truth keypoints in world coordinates (metres).
        uv: float64 (C, K, 2) their projections in pixels.
        depth: float64 (C, K) their camera-frame z.
        visible: bool (C, K): in front of the camera, inside the image and not hidden by another object.
        extra: per-frame metadata (segment, instance, object pose...), JSON-serialisable.
    """

    frame_id: int
    split: str
    images: np.ndarray
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    points3d: np.ndarray
    uv: np.ndarray
    depth: np.ndarray
    visible: np.ndarray
    extra: dict


@dataclasses.dataclass(frozen=True)
class CameraSampler:
    """How a scene draws its cameras: on a sphere around a target point, looking at it.

    Attributes:
        distance: (min, max) distance from the target in metres.
        elevation_deg: (min, max) elevation above the table plane in degrees.
        fovy_deg: vertical field of view in degrees.
        target: nominal point looked at (the workspace centre).
        target_jitter: standard deviation in metres of the per-camera aim point around ``target``.
        roll_deg: maximum absolute roll about the viewing axis, in degrees.
        azimuth_jitter_deg: cameras are spread evenly in azimuth from a random start, each then moved by up to
            this many degrees (so no two cameras coincide).
        fixed: None: every frame draws its own cameras (from the frame's generator). A number: the cameras
            are drawn once, from this seed, and every frame shows them (a rig that stays put, as a lab's
            does through a recording); the frame's generator is then left untouched by them.
    """

    distance: tuple[float, float] = (0.85, 1.15)
    elevation_deg: tuple[float, float] = (25.0, 70.0)
    fovy_deg: float = 22.0
    target: tuple[float, float, float] = (0.0, 0.0, 0.01)
    target_jitter: float = 0.015
    roll_deg: float = 10.0
    azimuth_jitter_deg: float = 35.0
    fixed: int | None = None

    def sample(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Returns camera positions (n, 3) and MuJoCo orientations (n, 3, 3)."""
        if self.fixed is not None:
            rng = np.random.default_rng([int(self.fixed), 0xF1CED])
        start = rng.uniform(0, 2 * np.pi)
        eyes, mats = [], []
        for i in range(n):
            az = start + 2 * np.pi * i / n + np.deg2rad(rng.uniform(-1, 1) * self.azimuth_jitter_deg)
            el = np.deg2rad(rng.uniform(*self.elevation_deg))
            dist = rng.uniform(*self.distance)
            target = np.asarray(self.target) + rng.normal(0.0, self.target_jitter, 3)
            eye = target + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            roll = np.deg2rad(rng.uniform(-1, 1) * self.roll_deg)
            eyes.append(eye)
            mats.append(look_at_xmat(eye, target, roll=roll))
        return np.array(eyes), np.array(mats)


def floats(a) -> str:
    return " ".join(f"{float(x):.6g}" for x in np.ravel(a))


def quat_from_mat(mat: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(mat, dtype=np.float64).ravel())
    return q


def axis_rotation(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


# Orientations that put each face of a box down on the table: (rotation, index of the vertical axis).
_RESTING = {
    "+z up": (np.eye(3), 2),
    "-z up": (axis_rotation("x", np.pi), 2),
    "+x down": (axis_rotation("y", np.pi / 2), 0),
    "-x down": (axis_rotation("y", -np.pi / 2), 0),
    "+y down": (axis_rotation("x", -np.pi / 2), 1),
    "-y down": (axis_rotation("x", np.pi / 2), 1),
}


def resting_box_pose(
    rng: np.random.Generator, half: np.ndarray, p_faces=(0.35, 0.35, 0.075, 0.075, 0.075, 0.075)
) -> tuple[np.ndarray, float, str]:
    """A random stable pose of a box with half extents ``half (3,)`` on the table: one face down, random yaw.

    Returns:
        ``(rotation (3, 3), height of the centre above the table, name of the resting face)``.
    """
    names = list(_RESTING)
    name = names[int(rng.choice(len(names), p=np.asarray(p_faces) / np.sum(p_faces)))]
    base, axis = _RESTING[name]
    rot = axis_rotation("z", rng.uniform(0, 2 * np.pi)) @ base
    return rot, float(half[axis]), name


class Scene:
    """Base class: table, lights, cameras, texture upload, rendering and labelling.

    Args:
        size: image width and height in pixels.
        seed: object seed: the scene's textures, object shapes and distractor sets derive from it (the
            frames' poses and cameras come from the generator passed to :meth:`frame`).
        num_cameras: number of cameras (the paper uses 4).
        cameras: how the cameras are drawn, instead of the scene's own ``cameras_sampler`` (a rig outside
            the training rig's ranges: :mod:`s3k.sim.rigs`).
    """

    name = "scene"
    keypoints: list[str] = []
    cameras_sampler = CameraSampler()
    #: Whether visibility needs the segmentation + depth test (scenes where other objects can hide keypoints).
    occlusion_test = False
    #: Depth margin in metres before an occluder in front of a keypoint counts.
    occlusion_tolerance = 0.005
    #: Geom group of the objects that can hide keypoints (rendered alone for the occlusion depth test).
    OCCLUDER_GROUP = 2
    num_tables = 6

    def __init__(self, size: int = 128, seed: int = 0, num_cameras: int = 4,
                 cameras: CameraSampler | None = None):
        if size < 8:
            raise ValueError(f"{self.name} scene: image size must be >= 8 px, got {size}")
        if cameras is not None:
            self.cameras_sampler = cameras
        self.size = int(size)
        self.seed = int(seed)
        self.num_cameras = int(num_cameras)
        self.camera_names = [f"cam{i}" for i in range(self.num_cameras)]
        self._textures: dict[str, np.ndarray] = {}
        self._rng = np.random.default_rng([self.seed, 0x5CE4E])
        xml = self._xml()
        self.model = mujoco.MjModel.from_xml_string(xml)
        self._write_textures()
        self.data = mujoco.MjData(self.model)
        self._renderer: MultiViewRenderer | None = None
        self._table_geom = self._id(mujoco.mjtObj.mjOBJ_GEOM, "table")
        mat = mujoco.mjtObj.mjOBJ_MATERIAL
        self._table_mats = [self._id(mat, f"table{i}") for i in range(self.num_tables)]
        self.camera_ids = [self._id(mujoco.mjtObj.mjOBJ_CAMERA, n) for n in self.camera_names]
        self._light = self._id(mujoco.mjtObj.mjOBJ_LIGHT, "key")
        self._setup()
        mujoco.mj_forward(self.model, self.data)

    # ------------------------------------------------------------------ model building
    def _id(self, kind, name: str) -> int:
        i = mujoco.mj_name2id(self.model, kind, name)
        if i < 0:
            raise KeyError(f"{self.name} scene: no {kind} named {name!r} in the model")
        return i

    def _texture(self, name: str, image: np.ndarray, cube: bool = False) -> str:
        """Registers texture data (``(h, w, 3)``, or ``(6, s, s, 3)`` for a cube) and returns its XML."""
        self._textures[name] = np.ascontiguousarray(image, dtype=np.uint8)
        if cube:
            s = image.shape[1]
            return (f'<texture name="{name}" type="cube" builtin="flat" width="{s}" height="{s}" '
                    'rgb1="1 1 1"/>')
        h, w = image.shape[:2]
        return f'<texture name="{name}" type="2d" builtin="flat" width="{w}" height="{h}" rgb1="1 1 1"/>'

    def _write_textures(self) -> None:
        m = self.model
        for name, img in self._textures.items():
            tid = self._id(mujoco.mjtObj.mjOBJ_TEXTURE, name)
            n = int(m.tex_width[tid] * m.tex_height[tid] * m.tex_nchannel[tid])
            if img.size != n:
                raise ValueError(f"texture {name!r}: {img.size} values for a {m.tex_width[tid]}x"
                                 f"{m.tex_height[tid]}x{m.tex_nchannel[tid]} texture")
            adr = int(m.tex_adr[tid])
            m.tex_data[adr : adr + n] = img.reshape(-1)

    def _xml(self) -> str:
        rng = self._rng
        assets = []
        for i in range(self.num_tables):
            assets.append(self._texture(f"table{i}", textures.table_texture(rng, 256)))
            assets.append(f'<material name="table{i}" texture="table{i}" texuniform="true" texrepeat="2 2" '
                          f'specular="0.1" shininess="0.1"/>')
        cams = "\n".join(f'<camera name="{n}" pos="0 0 1" fovy="{self.cameras_sampler.fovy_deg}"/>'
                         for n in self.camera_names)
        assets_xml, bodies_xml = self._objects_xml(rng)
        s = self.size
        return f"""
<mujoco model="s3k-{self.name}">
  <compiler inertiafromgeom="false"/>
  <statistic extent="1" center="0 0 0"/>
  <visual>
    <global offwidth="{s}" offheight="{s}"/>
    <quality shadowsize="0" offsamples="0"/>
    <headlight ambient="0.1 0.1 0.1" diffuse="0.3 0.3 0.3" specular="0.05 0.05 0.05"/>
    <map znear="0.01" zfar="20"/>
  </visual>
  <asset>
    {"".join(assets)}
    {assets_xml}
  </asset>
  <worldbody>
    <light name="key" directional="true" castshadow="false" pos="0 0 2" dir="0 0 -1"
           diffuse="0.6 0.6 0.6" ambient="0.2 0.2 0.2" specular="0.1 0.1 0.1"/>
    <geom name="table" type="plane" size="3 3 0.1" material="table0" contype="0" conaffinity="0"/>
    {cams}
    {bodies_xml}
  </worldbody>
</mujoco>
"""

    def _objects_xml(self, rng: np.random.Generator) -> tuple[str, str]:
        """(assets XML, worldbody XML) of the scene's objects."""
        raise NotImplementedError

    def _setup(self) -> None:
        """Looks up ids of the scene's objects after compilation."""

    # ------------------------------------------------------------------ state
    @property
    def renderer(self) -> MultiViewRenderer:
        if self._renderer is None:
            self._renderer = MultiViewRenderer(self.model, self.size, self.size)
            self._configure_renderer(self._renderer)
        return self._renderer

    def _configure_renderer(self, renderer: MultiViewRenderer) -> None:
        """Scene-specific render options (e.g. hidden geom groups)."""

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def set_cameras(self, eyes: np.ndarray, xmats: np.ndarray) -> None:
        """Places the cameras: positions (C, 3) and MuJoCo orientations (C, 3, 3) in world coordinates."""
        for i, cam in enumerate(self.camera_ids):
            self.model.cam_pos[cam] = eyes[i]
            self.model.cam_quat[cam] = quat_from_mat(xmats[i])

    def set_mocap(self, body: int, pos: np.ndarray, rot: np.ndarray) -> None:
        mid = int(self.model.body_mocapid[body])
        self.data.mocap_pos[mid] = pos
        self.data.mocap_quat[mid] = quat_from_mat(rot)

    def sample_environment(self, rng: np.random.Generator) -> dict:
        """Random table texture and tint, key light direction and colour, ambient and headlight levels."""
        m = self.model
        table = int(rng.integers(self.num_tables))
        m.geom_matid[self._table_geom] = self._table_mats[table]
        m.mat_rgba[self._table_mats[table]] = [*rng.uniform(0.75, 1.0, 3), 1.0]
        az, el = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(30, 85))
        m.light_dir[self._light] = -np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        m.light_diffuse[self._light] = rng.uniform(0.35, 0.8) * rng.uniform(0.9, 1.1, 3)
        m.light_ambient[self._light] = rng.uniform(0.1, 0.35) * np.ones(3)
        m.vis.headlight.diffuse[:] = rng.uniform(0.1, 0.35) * np.ones(3)
        return {"table": table}

    def sample(self, spec: FrameSpec, rng: np.random.Generator) -> dict:
        """Draws and applies the random state of frame ``spec``; returns its metadata."""
        extra = self.sample_environment(rng)
        extra.update(self.sample_objects(spec, rng))
        eyes, mats = self.cameras_sampler.sample(rng, self.num_cameras)
        self.set_cameras(eyes, mats)
        return extra

    def sample_objects(self, spec: FrameSpec, rng: np.random.Generator) -> dict:
        raise NotImplementedError

    def keypoints_world(self) -> np.ndarray:
        """Ground-truth keypoints (K, 3) in world coordinates for the current state."""
        raise NotImplementedError

    def own_geoms(self) -> np.ndarray:
        """Geom ids of the labelled object (what a keypoint may be hidden behind without being occluded)."""
        raise NotImplementedError

    def occluder_geoms(self) -> np.ndarray:
        """Geom ids of objects that can hide keypoints (distractors)."""
        return np.zeros(0, np.int64)

    def calibration(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """OpenCV ``K (C, 3, 3), R (C, 3, 3), t (C, 3)`` of the current cameras (after :meth:`forward`)."""
        Ks, Rs, ts = zip(*(camera_from_model(self.model, self.data, c, self.size, self.size)
                           for c in self.camera_ids))
        return np.array(Ks), np.array(Rs), np.array(ts)

    def forward(self) -> None:
        """Updates world poses of bodies and cameras from the state set so far."""
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)

    def capture(self, spec: FrameSpec, extra: dict | None = None) -> SimFrame:
        """Renders the current state into a :class:`SimFrame` with labels."""
        self.forward()
        K, R, t = self.calibration()
        X = self.keypoints_world()
        uv, depth = project_points(K, R, t, X)
        groups, cams = None, None
        if self.occlusion_test:
            groups = (self.OCCLUDER_GROUP,)
            # Only cameras where an occluder's bounding sphere meets a line of sight need the depth render.
            geoms = self.occluder_geoms()
            eyes = self.data.cam_xpos[self.camera_ids]
            cams = sight_lines_blocked(eyes, X, self.data.geom_xpos[geoms], self.model.geom_rbound[geoms])
        out = self.renderer.render(self.data, self.camera_ids, group_depth=groups, group_depth_cameras=cams)
        visible = in_image(uv, depth, self.size, self.size)
        if self.occlusion_test:
            visible &= ~occluded(uv, depth, out["group_depth"], self.occlusion_tolerance)
        return SimFrame(spec.frame_id, spec.split, out["rgb"], K, R, t, X, uv, depth, visible,
                        dict(extra or {}))

    def frame(self, spec: FrameSpec, rng: np.random.Generator) -> SimFrame:
        """:meth:`sample` then :meth:`capture`."""
        extra = self.sample(spec, rng)
        extra.update({"segment": spec.segment, "instance": spec.instance})
        return self.capture(spec, extra)


def in_image(uv: np.ndarray, depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """bool (C, K): in front of the camera and inside ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``."""
    u, v = uv[..., 0], uv[..., 1]
    return (depth > 1e-6) & (u >= -0.5) & (u <= width - 0.5) & (v >= -0.5) & (v <= height - 0.5)


def sight_lines_blocked(
    eyes: np.ndarray, points: np.ndarray, centres: np.ndarray, radii: np.ndarray
) -> np.ndarray:
    """bool (C,): whether any sphere (``centres (M, 3)``, ``radii (M,)``) meets a segment from a camera centre
    ``eyes (C, 3)`` to a point ``points (K, 3)``; a cheap test that rules occlusion out for most cameras."""
    if len(centres) == 0:
        return np.zeros(len(eyes), bool)
    d = points[None, :, :] - eyes[:, None, :]  # (C, K, 3) sight lines
    rel = centres[None, :, :] - eyes[:, None, :]  # (C, M, 3)
    s = np.einsum("ckj,cmj->ckm", d, rel) / np.maximum((d * d).sum(-1), 1e-12)[..., None]
    closest = eyes[:, None, None, :] + np.clip(s, 0.0, 1.0)[..., None] * d[:, :, None, :]  # (C, K, M, 3)
    dist = np.linalg.norm(closest - centres[None, None], axis=-1)
    return (dist < radii[None, None, :]).any(axis=(1, 2))


def occluded(uv: np.ndarray, depth: np.ndarray, occluder_depth: np.ndarray, tolerance: float) -> np.ndarray:
    """bool (C, K): at the pixel nearest to each projection an occluder lies in front of the keypoint.

    Args:
        uv: (C, K, 2) projections; depth: (C, K) their camera-frame z.
        occluder_depth: float (C, H, W) camera-frame z of a render that draws only the occluders (large where
            none is drawn).
        tolerance: metres an occluder must be in front of the keypoint to hide it.
    """
    C, H, W = occluder_depth.shape
    px = np.clip(np.rint(uv[..., 0]).astype(np.int64), 0, W - 1)
    py = np.clip(np.rint(uv[..., 1]).astype(np.int64), 0, H - 1)
    z = occluder_depth[np.arange(C)[:, None], py, px]
    return z < depth - tolerance


# ====================================================================== box
