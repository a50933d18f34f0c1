"""Tests of the MuJoCo simulation: camera conversion, scenes, occlusion, determinism and `s3k simulate`."""

from __future__ import annotations

import numpy as np
import pytest

from s3k.base.errors import UserError
from s3k.sim import textures
from s3k.sim.camera import look_at_xmat, mujoco_to_opencv, project_points
from s3k.sim.generate import (
    SimulateConfig,
    contact_sheet,
    frame_plan,
    frame_rng,
    render_frames,
    scene_mm_per_px,
)
from s3k.sim.render import MultiViewRenderer
from s3k.sim.scene import NUM_TRAIN_INSTANCES, FrameSpec, in_image, occluded, sight_lines_blocked
from s3k.sim.scenes import CategoryScene, DistractorScene, DistractorSpec, make_scene

mujoco = pytest.importorskip("mujoco")


# ------------------------------------------------------------------------------------------ camera conversion
def test_mujoco_to_opencv_closed_form():
    # A MuJoCo camera at the origin with identity orientation looks down -z with y up.
    W, H, fovy = 64, 48, 60.0
    K, R, t = mujoco_to_opencv(np.zeros(3), np.eye(3), fovy, W, H)
    f = (H / 2) / np.tan(np.deg2rad(fovy) / 2)
    np.testing.assert_allclose(K, [[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    np.testing.assert_allclose(R, np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(t, 0.0)
    # On the axis: the image centre. At the top of the vertical field of view: the image's top edge (v=-0.5).
    X = np.array([[0, 0, -1.0], [0, np.tan(np.deg2rad(fovy) / 2), -1.0], [0.3, 0.0, -2.0]])
    uv, depth = project_points(K[None], R[None], t[None], X)
    np.testing.assert_allclose(depth[0], [1.0, 1.0, 2.0])
    np.testing.assert_allclose(uv[0, 0], [(W - 1) / 2, (H - 1) / 2])
    np.testing.assert_allclose(uv[0, 1], [(W - 1) / 2, -0.5])
    assert uv[0, 2, 0] > (W - 1) / 2  # world +x is to the right


def test_mujoco_to_opencv_rejects_bad_input():
    with pytest.raises(ValueError, match="fovy"):
        mujoco_to_opencv(np.zeros(3), np.eye(3), 0.0, 10, 10)
    with pytest.raises(ValueError, match="image size"):
        mujoco_to_opencv(np.zeros(3), np.eye(3), 45.0, 0, 10)


def _spheres_model(points: np.ndarray, radius: float, W: int, H: int, fovy: float):
    geoms = "".join(f'<geom name="s{i}" type="sphere" size="{radius}" pos="{p[0]} {p[1]} {p[2]}" '
                    f'rgba="1 {i / len(points)} 0 1"/>' for i, p in enumerate(points))
    xml = f"""<mujoco><statistic extent="1" center="0 0 0"/>
      <visual><global offwidth="{W}" offheight="{H}"/><quality shadowsize="0" offsamples="0"/>
        <map znear="0.01" zfar="20"/></visual>
      <worldbody><light directional="true" dir="0 0 -1"/>{geoms}
        <camera name="cam" pos="0 0 1" fovy="{fovy}"/></worldbody></mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_conversion_matches_segmentation_render(seed):
    """Project known 3D points with the converted camera; each must land on its own object in a segmentation
    render, at the centroid of the object's pixels, and the depth render must agree with the projection."""
    rng = np.random.default_rng(seed)
    W, H = 96, 72  # not square, so that cx, cy and the aspect are checked
    radius = 0.035
    points = rng.uniform([-0.15, -0.15, -0.05], [0.15, 0.15, 0.15], size=(6, 3))
    fovy = rng.uniform(30, 45)
    model = _spheres_model(points, radius, W, H, fovy)
    data = mujoco.MjData(model)
    with MultiViewRenderer(model, W, H) as renderer:
        for _ in range(4):
            az, el = rng.uniform(0, 2 * np.pi), rng.uniform(-0.3, 1.3)
            direction = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            eye = rng.uniform(0.7, 0.9) * direction
            model.cam_pos[0] = eye
            xmat = look_at_xmat(eye, rng.normal(0, 0.02, 3), roll=rng.uniform(-np.pi, np.pi))
            mujoco.mju_mat2Quat(model.cam_quat[0], xmat.ravel())
            mujoco.mj_forward(model, data)
            K, R, t = mujoco_to_opencv(data.cam_xpos[0], data.cam_xmat[0], model.cam_fovy[0], W, H)
            out = renderer.render(data, [0], segmentation=True, depth=True)
            seg, depth_img = out["segmentation"][0], out["depth"][0]
            uv, depth = project_points(K[None], R[None], t[None], points)
            checked = 0
            for i in range(len(points)):
                u, v = uv[0, i]
                px, py = int(round(u)), int(round(v))
                mask = seg == i
                if not (2 <= px < W - 2 and 2 <= py < H - 2) or mask.sum() < 20:
                    continue
                # Skip spheres partly hidden by another sphere: their pixel centroid is biased.
                if mask.sum() < 0.9 * np.pi * (K[0, 0] * radius / depth[0, i]) ** 2:
                    continue
                assert seg[py, px] == i, f"point {i} at ({u:.1f}, {v:.1f}) shows geom {seg[py, px]}"
                ys, xs = np.nonzero(mask)
                np.testing.assert_allclose([xs.mean(), ys.mean()], [u, v], atol=0.3)
                # Rendered depth is camera-frame z of the sphere's front surface.
                assert depth_img[py, px] == pytest.approx(depth[0, i] - radius, abs=0.004)
                checked += 1
            assert checked >= 1


@pytest.mark.parametrize("name", ["box", "category"])
def test_scene_keypoints_land_on_their_object(name):
    """Interior points of the labelled object (keypoints pulled towards the object's centre) project onto
    the object in the segmentation render, in every camera of several random frames."""
    with make_scene(name, size=64, seed=3) as scene:
        for i in range(3):
            spec = FrameSpec(i, "labelled", instance=i if name == "category" else -1)
            scene.sample(spec, frame_rng(3, i))
            scene.forward()
            K, R, t = scene.calibration()
            X = scene.keypoints_world()
            if name == "box":
                centre = X[[0, 2]].mean(0)  # opposite lid corners: centre of the lid
                inner = centre + 0.7 * (X - centre)
                inner = inner - 0.3 * scene.box_half[2] * np.cross(X[1] - X[0], X[2] - X[1]) / np.linalg.norm(
                    np.cross(X[1] - X[0], X[2] - X[1]))
            else:
                inner = X[1:2]  # body_centre lies inside the mug
            uv, depth = project_points(K, R, t, inner)
            seg = scene.renderer.render(scene.data, scene.camera_ids, segmentation=True)["segmentation"]
            own = scene.own_geoms()
            for c in range(len(K)):
                for k in range(len(inner)):
                    u, v = np.rint(uv[c, k]).astype(int)
                    assert 0 <= u < 64 and 0 <= v < 64
                    assert seg[c, v, u] in own, f"frame {i} camera {c} point {k} shows geom {seg[c, v, u]}"


# ------------------------------------------------------------------------------------------ occlusion
def test_keypoint_hidden_by_distractor_is_not_visible():
    with DistractorScene(size=64, seed=0) as scene:
        spec = FrameSpec(0, "labelled", segment=0)
        scene.sample(spec, frame_rng(0, 0))
        far = np.array([5.0, 5.0, -1.0])
        block = DistractorSpec("box", (0.06, 0.06, 0.06), material=0)
        for s in range(scene.num_slots):  # clear the view
            scene.set_distractor(s, block, far + s, np.eye(3))
        free = scene.capture(spec)
        assert free.visible[0, 0], "keypoint 0 should be visible in camera 0 with no distractor near"
        # Put a distractor half way between camera 0 and keypoint 0.
        eye = scene.data.cam_xpos[scene.camera_ids[0]].copy()
        middle = 0.5 * (eye + free.points3d[0])
        scene.set_distractor(0, block, middle, np.eye(3))
        hidden = scene.capture(spec)
        assert not hidden.visible[0, 0]
        # Still inside the image: this is occlusion, not clipping; the label stays (flagged not visible).
        assert 0 <= hidden.uv[0, 0, 0] < 64 and 0 <= hidden.uv[0, 0, 1] < 64
        # The other cameras do not look through the block (it is small and near camera 0's line of sight).
        for c in range(1, 4):
            assert hidden.visible[c, 0] == free.visible[c, 0]
        # The segmentation render agrees that the block covers that pixel.
        seg = scene.renderer.render(scene.data, scene.camera_ids[:1], segmentation=True)["segmentation"][0]
        u, v = np.rint(hidden.uv[0, 0]).astype(int)
        assert seg[v, u] == scene.occluder_geoms()[0]


def test_occlusion_shortcut_matches_full_depth_test():
    """Skipping the occluder depth render for cameras whose sight lines miss every occluder's bounding sphere
    gives the same flags as rendering it for all cameras."""
    with DistractorScene(size=48, seed=2) as scene:
        blocked_any = False
        for i in range(8):
            spec = FrameSpec(i, "unlabelled", segment=i % 3)
            scene.sample(spec, frame_rng(2, i))
            frame = scene.capture(spec)
            full = scene.renderer.render(scene.data, scene.camera_ids, group_depth=(scene.OCCLUDER_GROUP,))
            expected = in_image(frame.uv, frame.depth, 48, 48) & ~occluded(
                frame.uv, frame.depth, full["group_depth"], scene.occlusion_tolerance)
            np.testing.assert_array_equal(frame.visible, expected)
            g = scene.occluder_geoms()
            blocked_any |= sight_lines_blocked(scene.data.cam_xpos[scene.camera_ids], frame.points3d,
                                               scene.data.geom_xpos[g], scene.model.geom_rbound[g]).any()
        assert blocked_any  # the shortcut was not trivially "render nothing"


def test_sight_lines_blocked_against_sampling():
    rng = np.random.default_rng(0)
    eyes, points = rng.normal(0, 1, (3, 3)), rng.normal(0, 1, (4, 3))
    centres, radii = rng.normal(0, 1, (5, 3)), rng.uniform(0.05, 0.4, 5)
    s = np.linspace(0, 1, 20001)
    seg = eyes[:, None, None, :] + s[:, None] * (points[None, :, None, :] - eyes[:, None, None, :])  # C,K,S,3
    dist = np.linalg.norm(seg[:, :, :, None, :] - centres, axis=-1).min(axis=2)  # C, K, M
    np.testing.assert_array_equal(sight_lines_blocked(eyes, points, centres, radii),
                                  (dist < radii).any(axis=(1, 2)))


def test_distractor_test_sets_are_unseen_in_training():
    with DistractorScene(size=32, seed=5) as scene:
        train = [d for s in range(6) for d in scene.distractor_set(s, test=False)]
        test = [d for s in range(6, 8) for d in scene.distractor_set(s, test=True)]
        assert {d.material for d in train}.isdisjoint({d.material for d in test})
        assert scene.distractor_set(1, False) != scene.distractor_set(2, False)


# ------------------------------------------------------------------------------------------ determinism
def _frames(scene, specs, seed):
    return [scene.frame(s, frame_rng(seed, s.frame_id)) for s in specs]


def _assert_same(a, b):
    for fa, fb in zip(a, b):
        np.testing.assert_array_equal(fa.images, fb.images)
        for name in ("K", "R", "t", "points3d", "uv", "visible"):
            np.testing.assert_array_equal(getattr(fa, name), getattr(fb, name))


@pytest.mark.parametrize("name", ["box", "distractors", "category"])
def test_same_seed_same_frames_regardless_of_history(name):
    cfg = SimulateConfig(name, size=32, labelled=2, unlabelled=2, test=2, seed=11)
    specs = frame_plan(cfg)
    with make_scene(name, size=32, seed=11) as a:
        forward = _frames(a, specs, 11)
    with make_scene(name, size=32, seed=11) as b:
        backward = _frames(b, specs[::-1], 11)[::-1]  # other order: no state may leak between frames
    _assert_same(forward, backward)
    with make_scene(name, size=32, seed=12) as c:
        other = _frames(c, specs[:1], 12)
    assert not np.array_equal(other[0].images, forward[0].images)


def test_worker_processes_give_the_same_frames():
    cfg = SimulateConfig("box", size=32, labelled=3, unlabelled=3, test=0, seed=4)
    specs = frame_plan(cfg)
    one = list(render_frames(cfg, specs, workers=1))
    two = list(render_frames(cfg, specs, workers=2, chunk=2))
    assert [f.frame_id for f in two] == [s.frame_id for s in specs]
    _assert_same(one, two)


def test_a_fixed_rig_keeps_its_cameras_and_the_frames_poses():
    moving = SimulateConfig("box", size=32, labelled=2, unlabelled=3, test=1, seed=5)
    fixed = SimulateConfig("box", size=32, labelled=2, unlabelled=3, test=1, seed=5, fixed_rig=True)
    specs = frame_plan(moving)
    a, b = list(render_frames(moving, specs, workers=1)), list(render_frames(fixed, specs, workers=1))
    for name in ("K", "R", "t"):
        assert all(np.array_equal(getattr(f, name), getattr(b[0], name)) for f in b)  # one rig throughout
    for name in ("R", "t"):
        assert not all(np.array_equal(getattr(f, name), getattr(a[0], name)) for f in a)
    for fa, fb in zip(a, b):  # the same object poses whatever the cameras
        np.testing.assert_array_equal(fa.points3d, fb.points3d)
    other = list(render_frames(SimulateConfig("box", size=32, labelled=1, unlabelled=0, test=0, seed=6,
                                              fixed_rig=True), specs[:1], workers=1))
    assert not np.array_equal(other[0].t, b[0].t)  # another recording's seed, another rig
    assert fixed.describe()["fixed_rig"] is True and "fixed_rig" not in moving.describe()


# ------------------------------------------------------------------------------------------ pixel size
def test_scene_pixel_size_follows_the_image_size_and_the_rendered_rigs():
    import torch

    from s3k.base.metrics import pixel_sizes_mm
    from s3k.geometry import Cameras

    at96 = scene_mm_per_px("box", 96, frames=6)
    assert scene_mm_per_px("box", 192, frames=6) == pytest.approx(at96 / 2, rel=1e-9)
    # one pixel is the camera's distance (0.85-1.15 m) over f = 48 / tan(11 deg) = 247 px
    f = 48 / np.tan(np.deg2rad(11.0))
    assert 850 / f < at96 < 1150 / f
    # the rigs are those of the rendered frames of `s3k simulate box --test 6`
    cfg = SimulateConfig("box", size=32, labelled=0, unlabelled=0, test=6)
    frames = list(render_frames(cfg, frame_plan(cfg)))
    cams = Cameras.from_numpy(np.stack([fr.K for fr in frames]), None, np.stack([fr.R for fr in frames]),
                              np.stack([fr.t for fr in frames]), dtype=torch.float64)
    rendered = float(np.median(pixel_sizes_mm(cams, 1000.0)))
    assert scene_mm_per_px("box", 32, frames=6) == pytest.approx(rendered, rel=1e-12)
    assert rendered == pytest.approx(at96 * 3, rel=1e-9)


# ------------------------------------------------------------------------------------------ frame plan
def test_frame_plan_modes_and_instances():
    counts = {"labelled": 6, "unlabelled": 12, "test": 4, "segments": 3}
    start = frame_plan(SimulateConfig("distractors", mode="start", **counts))
    full = frame_plan(SimulateConfig("distractors", mode="full", **counts))
    for plan in (start, full):
        assert [s.frame_id for s in plan] == list(range(22))
        assert {s.segment for s in plan if s.split == "unlabelled"} == {0, 1, 2}
        assert {s.segment for s in plan if s.split == "test"} <= {3, 4}
    assert {s.segment for s in start if s.split == "labelled"} == {0}
    assert {s.segment for s in full if s.split == "labelled"} == {0, 1, 2}
    cat = frame_plan(SimulateConfig("category", labelled=5, unlabelled=7, test=8, train_instances=3))
    assert {s.instance for s in cat if s.split != "test"} == {0, 1, 2}
    assert {s.instance for s in cat if s.split == "test"} == set(range(NUM_TRAIN_INSTANCES, 16))
    with pytest.raises(ValueError, match="train_instances"):
        SimulateConfig("category", train_instances=13)
    with pytest.raises(ValueError, match="scene"):
        SimulateConfig("shoes")


# ------------------------------------------------------------------------------------------ textures
def test_box_faces_are_distinct_and_printed():
    faces = textures.box_faces(np.random.default_rng(0), (0.199, 0.105, 0.017), res=64).astype(float)
    assert faces.shape == (6, 64, 64, 3)
    for i in range(6):
        # Not a flat colour: a printed face has structure.
        assert faces[i].std(axis=(0, 1)).max() > 10
        for j in range(i):
            assert np.abs(faces[i] - faces[j]).mean() > 10, f"faces {i} and {j} look alike"


def test_category_instances_differ():
    with CategoryScene(size=32, seed=0) as scene:
        kps = np.array([s.keypoints() for s in scene.shapes])
        assert len(scene.shapes) == 16
        # The handle's ring centre lies outside the body wall, the body centre on the axis.
        assert np.all(kps[:, 0, 0] > np.array([s.radius_at(s.handle_z) for s in scene.shapes]))
        assert np.unique(np.round(kps.reshape(16, -1), 4), axis=0).shape[0] == 16


def test_contact_sheet_draws_every_view():
    with make_scene("box", size=32, seed=0) as scene:
        frames = [scene.frame(FrameSpec(i, "labelled"), frame_rng(0, i)) for i in range(2)]
    sheet = contact_sheet(frames, scene.keypoints)
    assert sheet.dtype == np.uint8 and sheet.shape[0] > 2 * 34 and sheet.shape[1] == 4 * 34


# ------------------------------------------------------------------------------------------ s3k simulate
@pytest.mark.parametrize(
    "args",
    [
        ["box"],
        ["distractors", "--mode", "start"],
        ["distractors", "--mode", "full", "--segments", "2"],
        ["category", "--train-instances", "2"],
    ],
)
def test_simulate_writes_a_valid_dataset(tmp_path, args):
    from s3k.cli import main
    from s3k.data import Dataset

    out = tmp_path / "ds"
    rc = main(["simulate", *args, "--out", str(out), "--size", "32", "--labelled", "3", "--unlabelled", "4",
               "--test", "3", "--seed", "1", "--workers", "1", "--no-progress"])
    assert rc == 0
    ds = Dataset.open(out)
    assert [len(ds.frames(s)) for s in ("labelled", "unlabelled", "test")] == [3, 4, 3]
    assert ds.cameras == ["cam0", "cam1", "cam2", "cam3"] and tuple(ds.image_size) == (32, 32)
    ids = ds.frames("labelled")
    images = ds.images(ids)
    assert images.shape == (3, 4, 32, 32, 3) and images.std() > 5
    # Labels are the projections of the stored ground truth with the stored per-frame calibration.
    uv, mask = ds.labels(ids)
    X, xmask = ds.points3d(ids)
    cal = ds.calibration(ids, np.float64).numpy()
    assert xmask.all() and mask.any()
    for b in range(len(ids)):
        proj, _ = project_points(cal["K"][b], cal["R"][b], cal["t"][b], X[b])
        np.testing.assert_allclose(uv[b][mask[b]], proj[mask[b]], atol=1e-3)
    assert not np.array_equal(cal["R"][0], cal["R"][1])  # cameras move every frame
    if args[0] == "category":
        inst = ds.column("instance").astype(int)
        split = ds.split_of(ds.frames())
        assert set(inst[split != "test"]) <= {0, 1} and set(inst[split == "test"]) <= set(range(12, 16))
    if args[0] == "distractors":
        seg = set(ds.column("segment", ds.frames("labelled")).astype(int))
        assert seg == ({0} if "start" in args else {0, 1})
    assert main(["validate", str(out)]) == 0


def test_simulate_cli_bad_option_is_one_line(tmp_path, capsys):
    from s3k.cli import main

    with pytest.raises(SystemExit) as refused:  # as the command line is parsed
        main(["simulate", "box", "--out", str(tmp_path / "d"), "--size", "8", "--no-progress"])
    assert refused.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["s3k simulate: error: argument --size: must be in [16, 8192], got '8'; see 's3k simulate "
                   "--help'"]
    assert not (tmp_path / "d").exists()
    with pytest.raises(UserError, match="at least 16|from 16"):  # and by the library
        SimulateConfig("box", size=8)


def test_sampling_seed_changes_frames_not_the_object(monkeypatch):
    import s3k.sim.generate as gen

    built = []
    real = gen.make_scene

    def recording(name, size=128, seed=0, **kw):
        built.append(seed)
        return real(name, size=size, seed=seed, **kw)

    monkeypatch.setattr(gen, "make_scene", recording)
    frames = {}
    for seed in (1, 2):
        cfg = SimulateConfig("box", size=32, labelled=1, unlabelled=0, test=0, seed=seed)
        frames[seed] = next(iter(render_frames(cfg, frame_plan(cfg), workers=1)))
    other = SimulateConfig("box", size=32, labelled=1, unlabelled=0, test=0, seed=1, object_seed=5)
    next(iter(render_frames(other, frame_plan(other), workers=1)))
    assert built == [0, 0, 5]  # the scene (its look) follows object_seed only
    assert not np.array_equal(frames[1].points3d, frames[2].points3d)  # the frames follow seed
