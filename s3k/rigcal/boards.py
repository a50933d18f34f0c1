"""Calibration boards and their detection: ChArUco (anipose's ``board.toml``) and plain checkerboards, found
with OpenCV (``cv2.aruco.CharucoDetector``, ``cv2.findChessboardCornersSB``) in synchronized videos or image
folders, one per camera.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from s3k.data import imageseq, video
from s3k.data.formats.labels2d import frame_id_from_path
from s3k.errors import UserError
from s3k.fileio import read_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@dataclass
class Board:
    """A planar calibration board, lengths in the rig's unit.

    Attributes:
        squares_x, squares_y: squares along x and y (a ChArUco or checkerboard of ``squares_x x squares_y``
            squares has ``(squares_x - 1) x (squares_y - 1)`` inner corners).
        square_length: side of a square (sets the world unit).
        marker_length: ArUco marker side (ChArUco only; 0 for a checkerboard).
        marker_bits, dict_size: the ArUco dictionary ``DICT_{bits}X{bits}_{size}``.
    """

    squares_x: int
    squares_y: int
    square_length: float
    marker_length: float = 0.0
    marker_bits: int = 4
    dict_size: int = 50

    @property
    def charuco(self) -> bool:
        return self.marker_length > 0

    @property
    def n_corners(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)

    @property
    def n_markers(self) -> int:
        return self.squares_x * self.squares_y // 2

    def corners3d(self) -> np.ndarray:
        """``(N, 3)`` inner corners in the board frame (z = 0), in OpenCV's ChArUco corner order (row-major,
        x fastest), the order :meth:`detect` returns ids in."""
        nx, ny = self.squares_x - 1, self.squares_y - 1
        gx, gy = np.meshgrid(np.arange(1, nx + 1), np.arange(1, ny + 1))
        xy = np.stack([gx.ravel(), gy.ravel()], 1) * self.square_length
        return np.concatenate([xy, np.zeros((len(xy), 1))], 1).astype(np.float64)

    def cv2_board(self):
        """OpenCV's ``CharucoBoard`` of this board; a dictionary OpenCV lacks is refused in one line."""
        name = f"DICT_{self.marker_bits}X{self.marker_bits}_{self.dict_size}"
        if not hasattr(cv2.aruco, name):
            raise UserError(f"no ArUco dictionary {name} in OpenCV", hint="check marker_bits and dict_size")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_length, self.marker_length, dictionary
        )

    def describe(self) -> str:
        kind = (
            f"ChArUco, markers {self.marker_length:g}, DICT_{self.marker_bits}X{self.marker_bits}_"
            f"{self.dict_size}"
            if self.charuco
            else "checkerboard"
        )
        return f"{self.squares_x}x{self.squares_y} squares of {self.square_length:g} ({kind})"


MAX_SQUARES = 100
"""The most squares along a side of a board (more would not be seen by a camera; 99999 exhausts memory)."""
DICT_SIZES = (50, 100, 250, 1000)
"""The sizes of OpenCV's predefined ArUco dictionaries (``DICT_{bits}X{bits}_{size}``, bits 4 to 7)."""

BOARD_FIELDS = ("board_x", "board_y", "square_length", "marker_length", "marker_bits", "dict_size")


def _whole(value: object, name: str, low: int, high: int, where: str) -> int:
    """``value`` as an integer in ``[low, high]`` (an integral float such as 8.0 allowed), or a one-line
    error naming ``where``, the field and its range."""
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    if number is None or not math.isfinite(number) or number != int(number) or not low <= number <= high:
        raise UserError(f"{where}{name} must be a whole number from {low} to {high}, got {value!r}")
    return int(number)


def _length(value: object, name: str, where: str, *, zero: bool = False, below: float = math.inf) -> float:
    """``value`` as a finite length (> 0, or >= 0 with ``zero``; < ``below``) or a one-line error."""
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    ok = number is not None and math.isfinite(number) and (number >= 0 if zero else number > 0)
    if not ok or not number < below:  # type: ignore[operator]
        allowed = (f"a length from 0 up to (not including) the square's side {below:g}" if zero
                   else "a finite length above 0")
        raise UserError(f"{where}{name} must be {allowed}, got {value!r}")
    return float(number)  # type: ignore[arg-type]


def board_from_fields(fields: Mapping[str, object], where: str = "",
                      names: Mapping[str, str] | None = None) -> Board:
    """The board of anipose's fields (``board_x``, ``board_y``, ``square_length``, ``marker_length`` (0 for
    a checkerboard), ``marker_bits``, ``dict_size``), every one checked: the one check of a board, for
    ``board.toml`` (:func:`read_board_toml`) and ``s3k calibrate``'s options alike.

    Args:
        fields: the values as read (numbers, or anything a file holds).
        where: the message's prefix (``"board.toml: "``).
        names: how the message names a field (``{"board_x": "--squares (x)"}``); by default its own name.

    Raises:
        UserError: naming the field, its allowed range and the value.
    """
    names = {k: (names or {}).get(k, k) for k in BOARD_FIELDS}
    sx = _whole(fields["board_x"], names["board_x"], 2, MAX_SQUARES, where)
    sy = _whole(fields["board_y"], names["board_y"], 2, MAX_SQUARES, where)
    square = _length(fields["square_length"], names["square_length"], where)
    marker = _length(fields.get("marker_length", 0.0), names["marker_length"], where, zero=True, below=square)
    bits = _whole(fields.get("marker_bits", 4), names["marker_bits"], 4, 7, where)
    size = fields.get("dict_size", 50)
    if isinstance(size, bool) or size not in DICT_SIZES:
        raise UserError(f"{where}{names['dict_size']} must be one of {', '.join(map(str, DICT_SIZES))} (the "
                        f"sizes of OpenCV's ArUco dictionaries), got {size!r}")
    board = Board(sx, sy, square, marker, bits, int(size))  # type: ignore[call-overload]
    if board.charuco and board.n_markers > board.dict_size:
        raise UserError(f"{where}a ChArUco board of {sx}x{sy} squares has {board.n_markers} markers, more "
                        f"than the {board.dict_size} of its dictionary ({names['dict_size']})",
                        hint="check the board's size and dictionary")
    return board


def read_board_toml(path) -> Board:
    """Read anipose's ``board.toml`` (``board_x``, ``board_y``, ``square_length``, and for ChArUco
    ``marker_length``, ``marker_bits``, ``dict_size``; ``board_type = "checkerboard"`` or no
    ``marker_length`` gives a checkerboard), checked by :func:`board_from_fields`."""
    path = Path(path)
    if not path.is_file():
        raise UserError(
            f"{path}: board file not found", hint="pass --board FILE or --squares/--square-length"
        )
    try:
        data = tomllib.loads(read_text(path))
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc})") from exc
    for key in ("board_x", "board_y", "square_length"):
        if key not in data:
            raise UserError(f"{path}: no field {key!r} (a board needs board_x, board_y, square_length)")
    if str(data.get("board_type", "")).lower() == "checkerboard":
        data["marker_length"] = 0.0
    return board_from_fields(data, f"{path}: ")


@dataclass
class Detections:
    """One camera's board detections: ``{frame: (ids (n,) int, corners (n, 2) float64 px)}`` and its image
    size ``(W, H)``; ``markers_seen`` counts ArUco markers found (for the board-size check)."""

    frames: dict[int, tuple[np.ndarray, np.ndarray]]
    size: tuple[int, int]
    images: int = 0
    marker_ids: tuple[int, ...] = ()


def detect_image(image: np.ndarray, board: Board, detector, min_corners: int):
    """One image's board corners ``(ids, corners px)`` (None with fewer than ``min_corners``), and the ArUco
    marker ids seen (for the board-size check; empty for a checkerboard)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if board.charuco:
        corners, ids, _marker_corners, marker_ids = detector.detectBoard(gray)
        seen = () if marker_ids is None else tuple(int(i) for i in marker_ids.reshape(-1))
        if ids is None or len(ids) < min_corners:
            return None, seen
        return (ids.reshape(-1).astype(int), corners.reshape(-1, 2).astype(np.float64)), seen
    nx, ny = board.squares_x - 1, board.squares_y - 1
    ok, corners = cv2.findChessboardCornersSB(gray, (nx, ny), flags=cv2.CALIB_CB_NORMALIZE_IMAGE)  # type: ignore[call-overload]
    if not ok:
        return None, ()
    return (np.arange(nx * ny), _first_square_dark(gray, corners.reshape(-1, 2).astype(np.float64), nx)), ()


def _first_square_dark(gray: np.ndarray, uv: np.ndarray, nx: int) -> np.ndarray:
    """OpenCV returns a checkerboard's corners from any of its four ends, rows along x or mirrored. s3k's
    board frame (x right, y down the printed side, as OpenCV's and ChArUco boards) turns clockwise in the
    image and has a dark square at its origin, so the square inside the first four corners is dark. A
    mirrored order is reversed along x; then, when that square is the lighter, the order is turned by 180
    degrees (unambiguous when ``squares_x + squares_y`` is odd, which :func:`check_board_matches`
    requires)."""
    grid = uv.reshape(-1, nx, 2)
    ex, ey = grid[0, 1] - grid[0, 0], grid[1, 0] - grid[0, 0]
    if ex[0] * ey[1] - ex[1] * ey[0] < 0:
        grid = grid[:, ::-1]

    def level(i: int) -> float:
        x, y = grid[:2, i : i + 2].reshape(-1, 2).mean(0)
        return float(gray[int(round(y)), int(round(x))])

    if level(0) > level(1):
        grid = grid[::-1, ::-1]
    return np.ascontiguousarray(grid.reshape(-1, 2))


def frames_of(source: str | Path) -> tuple[list[int], list[Path] | None]:
    """``(frame keys, reader)`` of a video or image folder/glob: a video's frames are keyed by index, an image
    sequence's by the last number in each file name (anipose's ``<camera>-<time>-<index>.jpg``), which pairs
    the views of one board position."""

    if imageseq.is_sequence(source):
        files = imageseq.sequence_files(source)
        keys = [frame_id_from_path(str(f)) for f in files]
        if any(k is None for k in keys) or len(set(keys)) != len(keys):
            keys = list(range(len(files)))  # no usable numbers: the sorted order pairs the views
        return [int(k) for k in keys], files  # type: ignore[arg-type]
    if not Path(source).is_file():
        raise UserError(f"{source}: no such video, image folder or pattern")
    return [], None


def detect_board(source: str | Path, board: Board, *, every: int = 1, min_corners: int = 6) -> Detections:
    """Detect the board in every ``every``-th frame of a video or image sequence."""


    detector = cv2.aruco.CharucoDetector(board.cv2_board()) if board.charuco else None
    keys, files = frames_of(source)
    found: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    seen: set[int] = set()
    size = (0, 0)
    images = 0
    if files is not None:
        items = ((k, f) for i, (k, f) in enumerate(zip(keys, files)) if i % every == 0)
        for key, file in items:
            image = cv2.imread(str(file), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise UserError(f"{file}: cannot read image")
            size, images = (image.shape[1], image.shape[0]), images + 1
            hit, markers = detect_image(image, board, detector, min_corners)
            seen.update(markers)
            if hit is not None:
                found[key] = hit
    else:
        for i, image in video.iter_frames(source):
            if i % every:
                continue
            size, images = (image.shape[1], image.shape[0]), images + 1
            hit, markers = detect_image(image, board, detector, min_corners)
            seen.update(markers)
            if hit is not None:
                found[i] = hit
    return Detections(found, size, images, tuple(sorted(seen)))


def check_board_matches(name: str, source, det: Detections, board: Board) -> None:
    """A one-line error when the board seen does not match ``board``: ArUco markers whose ids the board does
    not have, or no detection at all."""
    if not board.charuco and (board.squares_x + board.squares_y) % 2 == 0:
        raise UserError(
            f"checkerboard {board.describe()}: with an even number of squares in all it looks the same "
            "turned by 180 degrees, so the cameras cannot agree on its corners",
            hint="use a board with an odd squares_x + squares_y (e.g. 8x11 or 7x6)",
        )
    if board.charuco and det.marker_ids and max(det.marker_ids) >= board.n_markers:
        raise UserError(
            f"camera {name} ({source}): the images show ArUco markers with ids up to "
            f"{max(det.marker_ids)}, but "
            f"the board {board.describe()} has markers 0-{board.n_markers - 1}: the board's size does not "
            "match the detections",
            hint="check board_x, board_y in board.toml (or --squares)",
        )
    if not det.frames:
        what = (
            f"{len(det.marker_ids)} ArUco marker ids but no ChArUco corners" if det.marker_ids else "no board"
        )
        raise UserError(
            f"camera {name} ({source}): {what} found in {det.images} image(s) for the board "
            f"{board.describe()}",
            hint="check the board's size and dictionary (board.toml, --squares, "
            "--dict) and that the board is in view",
        )
