"""A ChArUco board seen by three cameras, drawn with OpenCV (no renderer): the rig's truth, the board and its
images, and a labelled dataset of that rig for ``s3k check-calibration --recalibrate`` (used by the tests and
by ``scripts/loose-ends/calibration.sh``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

NAMES = ["p", "q", "r"]
SIZE = (640, 480)


def look_at(centre, target=(0.0, 0.0, 0.0)):
    """World->camera R, t for a camera at ``centre`` looking at ``target`` (OpenCV axes, y roughly down)."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ centre


def render_charuco_rig(folder: str | Path, poses: int = 8, *, inverted: bool = False, back: str | None = None,
                       stray: dict[str, list[int]] | None = None, seen: dict[str, list[int]] | None = None,
                       turned: str | None = None, lag: dict[str, int] | None = None):
    """A 5 x 7 ChArUco board (30 mm squares) in ``poses`` poses seen by cameras p, q, r, written as
    ``folder/<camera>-<pose>.png``: ``(truth Rig, Board, {camera: [files]})``.

    Args:
        inverted: the board printed inverted (white squares and markers on black).
        back: a camera placed below the board, which sees its back face (a two-sided board printed through:
            the front's pattern seen from behind, mirrored).
        stray: per camera the poses whose image also shows a marker the board does not have (id 40 of the
            board's dictionary) in a corner of the background.
        seen: per camera the poses it sees the board in (an empty grey image in the others).
        turned: a camera knocked halfway through: from pose ``poses // 2`` on it is turned by 1 degree about
            its vertical axis (the truth returned is its first pose).
        lag: cameras whose clock lags: the board moves smoothly (a pose a frame, each close to the last), and
            a camera with lag ``d`` shows in its image ``i`` the board of the others' image ``i - d``.
    """
    from s3k.data.rig import Rig
    from s3k.geometry import Cameras
    from s3k.rigcal.boards import Board

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    W, H = SIZE
    spec = Board(5, 7, 30.0, 22.0, 4, 50)
    px_per_mm = 4
    art = spec.cv2_board().generateImage((5 * 30 * px_per_mm, 7 * 30 * px_per_mm), marginSize=0)
    if inverted:
        art = 255 - art
    # The board image maps board (x, y) mm -> art pixels (x, y) * px_per_mm (pixel centres at +0.5).
    A = np.array([[px_per_mm, 0, -0.5], [0, px_per_mm, -0.5], [0, 0, 1.0]])
    angles = (0.3, 2.2, 4.2)
    cams = [look_at(np.array([250 * np.cos(a), 250 * np.sin(a), -400.0 if NAMES[c] == back else 400.0]))
            for c, a in enumerate(angles)]
    Rs, ts = np.stack([p[0] for p in cams]), np.stack([p[1] for p in cams])
    Ks = np.array([[[600.0 + 60 * c, 0, (W - 1) / 2], [0, 600.0 + 60 * c, (H - 1) / 2], [0, 0, 1]]
                   for c in range(3)])
    marker = cv2.aruco.generateImageMarker(spec.cv2_board().getDictionary(), 40, 48)
    rng = np.random.default_rng(0)
    files: dict[str, list[Path]] = {n: [] for n in NAMES}
    def board_pose(j: int):
        # Board pose in the world: near the origin, tilted, its printed side up towards the cameras (the
        # board's z axis points into the board, so it points down here).
        if lag is None:
            rvec, shift = rng.uniform(-0.35, 0.35, 3), rng.uniform(-30, 30, 3)
        else:  # a smooth motion
            rvec = 0.3 * np.sin(np.array([0.4, 0.3, 0.5]) * j + np.array([0.0, 1.0, 2.0]))
            shift = 30 * np.sin(np.array([0.35, 0.25, 0.2]) * j + np.array([0.5, 1.5, 0.0]))
        R_wb = cv2.Rodrigues(rvec)[0] @ np.diag([1.0, -1.0, -1.0])
        return R_wb, shift - R_wb @ np.array([75.0, 105.0, 0.0])

    for i in range(poses):
        pose = board_pose(i)
        for c, n in enumerate(NAMES):
            R_wb, t_wb = board_pose(i - lag[n]) if lag and lag.get(n) else pose
            R, t = Rs[c], ts[c]
            if n == turned and i >= poses // 2:
                R = cv2.Rodrigues(np.array([0.0, np.radians(1.0), 0.0]))[0] @ R
                t = R @ (-Rs[c].T @ ts[c]) * -1
            # Homography board plane (z = 0) -> image: K [R R_wb[:, :2] | R t_wb + t].
            Hb = Ks[c] @ np.column_stack([R @ R_wb[:, 0], R @ R_wb[:, 1], R @ t_wb + t])
            image = cv2.warpPerspective(art, Hb @ np.linalg.inv(A), (W, H), borderValue=255)
            if seen is not None and i not in seen.get(n, range(poses)):
                image = np.full((H, W), 200, np.uint8)
            if i in (stray or {}).get(n, []):
                image[8:80, 8:80] = 255
                image[20:68, 20:68] = marker
            path = folder / f"{n}-{i}.png"
            cv2.imwrite(str(path), image)
            files[n].append(path)
    cameras = Cameras.from_numpy(Ks, np.zeros((3, 5)), Rs, ts, dtype=torch.float64)
    truth = Rig(list(NAMES), cameras, np.array([[W, H]] * 3), "mm")
    return truth, spec, files


def copy_camera(rig, dst: int, src: int):
    """``rig`` with camera ``dst`` given the parameters of camera ``src`` (its distortion kept)."""
    a = rig.cameras.numpy()
    return rig.replace_camera(rig.names[dst], a["K"][src], a["dist"][dst], a["R"][src], a["t"][src])


def board_toml(spec) -> str:
    """anipose's ``board.toml`` of the board ``spec``."""
    return (f"board_x = {spec.squares_x}\nboard_y = {spec.squares_y}\nsquare_length = {spec.square_length}\n"
            f"marker_length = {spec.marker_length}\nmarker_bits = {spec.marker_bits}\n"
            f"dict_size = {spec.dict_size}\n")


def labels(truth, frames: int = 8, keypoints: int = 4, noise: float = 0.3, seed: int = 1):
    """Points near the origin projected by ``truth`` with ``noise`` px: ``uv (B, C, K, 2)``, ``mask``."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-100, 100, (frames * keypoints, 3))
    a = truth.cameras.numpy()
    uv = []
    for K, d, R, t in zip(a["K"], a["dist"], a["R"], a["t"]):
        p, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, d)
        uv.append(p.reshape(frames, keypoints, 2))
    uv = np.stack(uv, axis=1) + noise * rng.standard_normal((frames, len(truth.names), keypoints, 2))
    return uv, np.ones(uv.shape[:-1], bool)


def write_recalibration_case(folder: str | Path, broken: bool = True):
    """In ``folder``: the board's images (``images/``), ``board.toml``, ``calibration.toml`` (with
    ``broken`` the truth with camera q given r's parameters, else the truth) and the dataset ``ds`` of 8
    labelled frames imported from it (labels projected by the truth). Returns ``(truth, spec, files)``."""
    from s3k.data import DatasetWriter
    from s3k.data.formats.anipose import write_anipose_calibration

    folder = Path(folder)
    truth, spec, files = render_charuco_rig(folder / "images")
    rig = copy_camera(truth, 1, 2) if broken else truth
    write_anipose_calibration(folder / "calibration.toml", rig)
    (folder / "board.toml").write_text(board_toml(spec))
    uv, mask = labels(truth)
    W, H = SIZE
    with DatasetWriter(folder / "ds", ["a", "b", "c", "d"], truth.names, (W, H), "mm",
                       calibration=rig.cameras,
                       source={"calibration": str((folder / "calibration.toml").resolve())}) as writer:
        for b in range(len(uv)):
            writer.add_frame(b, "labelled", np.zeros((3, H, W, 3), np.uint8), labels=(uv[b], mask[b]))
    return truth, spec, files
