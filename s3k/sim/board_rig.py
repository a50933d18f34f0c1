"""A simulated rig filming a calibration board: a ChArUco (or checkerboard) texture on a flat mesh, moved
through poses in front of a few MuJoCo cameras with known intrinsics and poses. The frames, one image folder
per camera, are what ``s3k calibrate`` reads; the cameras (:func:`mujoco_to_opencv`) are the truth to check it
against.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from s3k.rigcal.boards import Board
from s3k.sim.camera import look_at_xmat, mujoco_to_opencv
from s3k.sim.meshes import mesh_xml
from s3k.sim.render import MultiViewRenderer

PX_PER_SQUARE = 64
MARGIN = 0.5  # white border around the board, in squares


@dataclass
class BoardRig:
    """The true cameras (``x_cam = R x_world + t``, world in metres) and the folders written."""

    names: list[str]
    K: np.ndarray  # (C, 3, 3)
    R: np.ndarray  # (C, 3, 3)
    t: np.ndarray  # (C, 3)
    folders: dict[str, Path]
    size: tuple[int, int]


def _board_image(board: Board) -> np.ndarray:
    """The printed board as a grey image with a white margin, :data:`PX_PER_SQUARE` pixels a square (the
    texture the simulated rig films)."""
    m = int(MARGIN * PX_PER_SQUARE)
    w, h = board.squares_x * PX_PER_SQUARE, board.squares_y * PX_PER_SQUARE
    if board.charuco:
        gray = board.cv2_board().generateImage((w + 2 * m, h + 2 * m), marginSize=m)
    else:
        yy, xx = np.mgrid[0:h, 0:w] // PX_PER_SQUARE
        gray = np.pad(np.where((xx + yy) % 2 == 0, 0, 255).astype(np.uint8), m, constant_values=255)
    return np.repeat(gray[..., None], 3, axis=2)


def _xml(board: Board, metres_per_unit: float, eyes: np.ndarray, fovy: float, image: np.ndarray) -> str:
    # centred on the board (MuJoCo moves a mesh's frame to its centroid); the board frame of OpenCV: x right,
    # y down the printed image, z into the board (the camera sees -z)
    W = (board.squares_x + 2 * MARGIN) * board.square_length * metres_per_unit / 2
    H = (board.squares_y + 2 * MARGIN) * board.square_length * metres_per_unit / 2
    verts = np.array([[-W, -H, 0], [W, -H, 0], [W, H, 0], [-W, H, 0]], float)
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    cams = []
    for i, eye in enumerate(eyes):
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, look_at_xmat(eye, np.zeros(3)).ravel())
        cams.append(
            f'<camera name="cam{i}" pos="{" ".join(map(str, eye))}" quat="{" ".join(map(str, quat))}" '
            f'fovy="{fovy}"/>'
        )
    h, w = image.shape[:2]
    return f"""<mujoco>
  <compiler balanceinertia="true"/>
  <visual><quality shadowsize="0" offsamples="4"/><global offwidth="2048" offheight="2048"/>
    <headlight ambient="0.6 0.6 0.6" diffuse="0.4 0.4 0.4"/></visual>
  <asset>
    <texture name="board" type="2d" builtin="flat" width="{w}" height="{h}" rgb1="1 1 1"/>
    <material name="board" texture="board" emission="1" specular="0" shininess="0"/>
    {mesh_xml("board", verts, faces, uv)}
  </asset>
  <worldbody>
    {"".join(cams)}
    <geom type="plane" size="2 2 0.1" pos="0 0 -0.3" rgba="0.45 0.45 0.45 1"/>
    <body name="board" mocap="true"><geom type="mesh" mesh="board" material="board" contype="0"
      conaffinity="0"/></body>
  </worldbody>
</mujoco>"""


def board_poses(
    n: int, board: Board, metres_per_unit: float, seed: int = 0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` poses ``(R, t)`` of the board's centre near the origin (where the cameras look), facing up
    towards the cameras (the board's -z towards +z of the world), tilted up to 45 degrees."""

    rng = np.random.default_rng(seed)
    flip = Rotation.from_euler("x", 180, degrees=True)  # board z down: its printed face looks up
    out = []
    for _ in range(n):
        tilt = Rotation.from_rotvec(np.r_[rng.uniform(-1, 1, 2), 0] * np.radians(45))
        spin = Rotation.from_euler("z", rng.uniform(-30, 30), degrees=True)
        R = (tilt * flip * spin).as_matrix()
        t = np.r_[rng.uniform(-0.04, 0.04, 2), rng.uniform(-0.03, 0.03)]
        out.append((R, t))
    return out


def render_board_rig(
    out: str | Path,
    board: Board,
    *,
    metres_per_unit: float = 0.001,
    cameras: int = 3,
    size: tuple[int, int] = (320, 256),
    fovy: float = 45.0,
    distance: float = 0.55,
    poses: int = 10,
    seed: int = 0,
) -> BoardRig:
    """Render ``poses`` board positions into ``cameras`` cameras on a ring ``distance`` m from the origin, 40
    degrees above it; one folder of PNGs per camera under ``out`` (``cam<i>/frame_<k>.png``)."""

    angles = np.linspace(0, 2 * np.pi, cameras, endpoint=False) + 0.3
    el = np.radians(50)
    eyes = np.stack(
        [
            distance * np.cos(el) * np.cos(angles),
            distance * np.cos(el) * np.sin(angles),
            np.full(cameras, distance * np.sin(el)),
        ],
        1,
    )
    image = _board_image(board)
    model = mujoco.MjModel.from_xml_string(_xml(board, metres_per_unit, eyes, fovy, image))
    tid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, "board")
    adr = int(model.tex_adr[tid])
    model.tex_data[adr : adr + image.size] = image.reshape(-1)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    W, H = size
    names = [f"cam{i}" for i in range(cameras)]
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, n) for n in names]
    truth = [
        mujoco_to_opencv(data.cam_xpos[i], data.cam_xmat[i], float(model.cam_fovy[i]), W, H) for i in ids
    ]
    folders = {n: Path(out) / n for n in names}
    for f in folders.values():
        f.mkdir(parents=True, exist_ok=True)
    with MultiViewRenderer(model, W, H) as renderer:
        for k, (R, t) in enumerate(board_poses(poses, board, metres_per_unit, seed)):
            data.mocap_pos[0] = t
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, R.ravel())
            data.mocap_quat[0] = quat
            mujoco.mj_forward(model, data)
            rgb = renderer.render(data, ids)["rgb"]
            for n, img in zip(names, rgb):
                cv2.imwrite(str(folders[n] / f"frame_{k:03d}.png"), img[..., ::-1])
    return BoardRig(
        names,
        np.stack([k for k, _, _ in truth]),
        np.stack([r for _, r, _ in truth]),
        np.stack([t for _, _, t in truth]),
        folders,
        (W, H),
    )
