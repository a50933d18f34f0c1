"""A scripted top-down grasp of the plush toy's front paw, and the trials of ``s3k robot grasp``.

The primitive takes two 3D points, the paw to grasp and a second keypoint (the body): the gripper turns so
that its fingers close across the leg (the jaw's x axis along the body -> paw direction), moves above a
point a little behind the paw's end (towards the body, so the fingers grip the leg rather than slide off
its end), descends, closes and lifts. Success is the *true* paw lifted at least 10 cm above where it lay
*and* held: still within 4 cm of the gripper's tool centre point (a grasp of another leg or of the tail
lifts the whole toy, the paw with it, but is not a grasp by the paw).

Physics runs in the plush scene's own model (:class:`s3k.sim.plush.PlushScene`): the toys are free bodies
and the gripper's fingers are position-controlled slide joints, so a grasp holds only through contact.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import mujoco
import numpy as np

from s3k.sim.gripper import yaw_rotation
from s3k.sim.plush import FIRST_UNLABELLED_ARRANGEMENT, TRAIN_ARRANGEMENTS, PlushScene
from s3k.sim.scene import FrameSpec

#: The paw lifted this high (metres), and held this close to the tool centre point, is a success.
SUCCESS_LIFT = 0.10
HELD_DISTANCE = 0.04


@dataclasses.dataclass
class GraspResult:
    """What one grasp did: ``success``, how high the true paw rose (``lift``, metres), how far it ended
    from the tool centre point (``held_mm``), the point aimed at and where the true paw was."""

    success: bool
    lift: float
    held_mm: float
    target: list[float]
    paw_true: list[float]
    aim_error_mm: float


def _move(scene: PlushScene, start: np.ndarray, end: np.ndarray, rot: np.ndarray, seconds: float) -> None:
    """Moves the tool centre point on a straight line at constant speed (one mocap update per step)."""
    m, d = scene.model, scene.data
    n = max(1, int(round(seconds / m.opt.timestep)))
    for i in range(1, n + 1):
        scene.gripper.set_pose(d, start + (end - start) * (i / n), rot)
        mujoco.mj_step(m, d)


def _hold(scene: PlushScene, seconds: float) -> None:
    for _ in range(max(1, int(round(seconds / scene.model.opt.timestep)))):
        mujoco.mj_step(scene.model, scene.data)


def settle(scene: PlushScene, seconds: float = 0.3) -> None:
    """Lets the toys come to rest under gravity (the arrangement's pose is already nearly at rest)."""
    scene.gripper.set_fingers(scene.data, 0.0, kinematic=True)
    mujoco.mj_forward(scene.model, scene.data)
    _hold(scene, seconds)


def grasp(scene: PlushScene, paw: np.ndarray, body: np.ndarray, paw_name: str = "front_left_paw",
          behind: float = 0.012, lift: float = 0.15) -> GraspResult:
    """Grasps at ``paw (3,)`` approaching along the ``body (3,)`` -> paw direction; runs the physics.

    Args:
        scene: a plush scene with its arrangement set (and settled, see :func:`settle`).
        paw, body: the 3D points to use (detected, or the ground truth), world metres.
        paw_name: which keypoint is the paw (for the success test on the true state).
        behind: how far behind the paw's end, towards the body, the fingers close.
        lift: how far the gripper lifts after closing.
    """
    paw = np.asarray(paw, dtype=np.float64)
    body = np.asarray(body, dtype=np.float64)
    true0 = scene.toy_keypoint(paw_name).copy()
    d = paw[:2] - body[:2]
    norm = float(np.linalg.norm(d))
    d = d / norm if norm > 1e-6 else np.array([1.0, 0.0])
    rot = yaw_rotation(math.atan2(d[1], d[0]))
    target = np.array([paw[0] - behind * d[0], paw[1] - behind * d[1], max(float(paw[2]), 0.012)])
    above = target + np.array([0.0, 0.0, 0.12])
    start = scene.gripper.tcp(scene.data).copy()
    scene.gripper.set_fingers(scene.data, 0.0)
    _move(scene, start, np.array([start[0], start[1], max(start[2], above[2])]), rot, 0.2)
    _move(scene, scene.gripper.tcp(scene.data).copy(), above, rot, 0.5)
    _move(scene, above, target, rot, 0.5)
    scene.gripper.set_fingers(scene.data, 1.0)
    _hold(scene, 0.4)
    _move(scene, target, target + np.array([0.0, 0.0, lift]), rot, 1.0)
    _hold(scene, 0.3)
    paw_now = scene.toy_keypoint(paw_name)
    rise = float(paw_now[2] - true0[2])
    held = float(np.linalg.norm(paw_now - scene.gripper.tcp(scene.data)))
    return GraspResult(success=rise >= SUCCESS_LIFT and held <= HELD_DISTANCE, lift=rise,
                       held_mm=held * 1000, target=target.tolist(),
                       paw_true=true0.tolist(),
                       aim_error_mm=float(np.linalg.norm(paw - true0) * 1000))


KeypointSource = Callable[[PlushScene, FrameSpec], np.ndarray]


def ground_truth_keypoints(scene: PlushScene, spec: FrameSpec) -> np.ndarray:
    """The true keypoints (K, 3): the upper bound of the grasp."""
    return scene.keypoints_world()


#: Held-out arrangements of the grasp trials by default: 7, 8, 9 (the datasets' test arrangements) and 10,
#: 11, 12 (in no dataset); the most there are, since a dataset's further unlabelled arrangements start at 13.
ARRANGEMENTS = FIRST_UNLABELLED_ARRANGEMENT - TRAIN_ARRANGEMENTS


def run_trials(source: KeypointSource, trials: int = 30, size: int = 96, seed: int = 0, object_seed: int = 0,
               paw: str = "front_left_paw", arrangements: int = ARRANGEMENTS,
               progress: Callable[[int, GraspResult], None] | None = None) -> dict:
    """Grasp trials on ``arrangements`` held-out arrangements, from 7 on, in turn (7, 8, ..., 7, ...).

    Each trial sets its arrangement, draws lighting and the gripper's start pose from ``(seed, trial)``
    (as a dataset frame would), lets the toys settle, asks ``source(scene, spec)`` for the keypoints (K, 3)
    in the scene's order (NaN where not found: a failed trial), and grasps the paw.

    Returns:
        ``{"successes", "trials", "success_rate", "arrangements": [...], "per_arrangement": {a: rate},
        "per_trial": [...], "paw", "seed", "object_seed", "size"}``.
    """
    if trials < 1:
        raise ValueError(f"run_trials: trials must be >= 1, got {trials}")
    if not 1 <= arrangements <= ARRANGEMENTS:
        raise ValueError(f"run_trials: arrangements must be in [1, {ARRANGEMENTS}] (later ones may be a "
                         f"dataset's unlabelled arrangements), got {arrangements}")
    results = []
    with PlushScene(size=size, seed=object_seed) as scene:
        k_paw, k_body = scene.keypoints.index(paw), scene.keypoints.index("body")
        test = list(range(TRAIN_ARRANGEMENTS, TRAIN_ARRANGEMENTS + arrangements))
        for i in range(trials):
            spec = FrameSpec(i, "test", segment=test[i % len(test)])
            scene.sample(spec, np.random.default_rng([seed, 0x96A5, i]))
            settle(scene)
            X = np.asarray(source(scene, spec), dtype=np.float64)
            if not np.isfinite(X[[k_paw, k_body]]).all():
                true = scene.toy_keypoint(paw)
                r = GraspResult(False, 0.0, math.nan, [math.nan] * 3, true.tolist(), math.nan)
            else:
                r = grasp(scene, X[k_paw], X[k_body], paw_name=paw)
            results.append({"arrangement": spec.segment, **dataclasses.asdict(r)})
            if progress is not None:
                progress(i, r)
    successes = sum(r["success"] for r in results)
    used = sorted({r["arrangement"] for r in results})
    per_arrangement = {str(a): float(np.mean([r["success"] for r in results if r["arrangement"] == a]))
                       for a in used}
    return {"successes": successes, "trials": trials, "success_rate": successes / trials, "paw": paw,
            "seed": seed, "object_seed": object_seed, "size": size, "arrangements": used,
            "per_arrangement": per_arrangement, "per_trial": results}


def detector_keypoints(detector) -> KeypointSource:
    """A :data:`KeypointSource` that renders the four views and runs ``detector`` (a
    :class:`s3k.robot.detect.RunDetector` asked for the scene's keypoints) on them."""

    def source(scene: PlushScene, spec: FrameSpec) -> np.ndarray:
        frame = scene.capture(spec)
        X, _ = detector(frame.images, frame.K, frame.R, frame.t)
        return X

    return source
