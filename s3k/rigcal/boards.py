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

from s3k.base.errors import UserError
from s3k.base.fileio import read_text
from s3k.data import imageseq, video
from s3k.data.formats.labels2d import frame_id_from_path

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
    size ``(W, H)``; what detection took and left: ``marker_ids`` the board's ArUco ids seen, ``inverted``
    and ``back`` the frames found on an inverted print or on a two-sided board's back face, ``stray`` the
    markers whose ids the board does not have (dropped) in ``stray_frames`` of the ``marker_frames`` images
    that showed markers, with ``stray_ids`` their ids."""

    frames: dict[int, tuple[np.ndarray, np.ndarray]]
    size: tuple[int, int]
    images: int = 0
    marker_ids: tuple[int, ...] = ()
    inverted: int = 0
    back: int = 0
    stray: int = 0
    stray_frames: int = 0
    marker_frames: int = 0
    stray_ids: tuple[int, ...] = ()
    faces: Faces | None = None


@dataclass(frozen=True)
class Faces:
    """Which prints of the board detection tries, in order, when the one before finds nothing: the board as
    printed, the board printed inverted (white squares and markers on black: the image is inverted before
    detection), and a two-sided board's back face (the front printed through, so the camera behind it sees it
    mirrored: the image is flipped left-right, detected, and the corners flipped back; the corners are the
    front's, the board's thickness neglected)."""

    normal: bool = True
    inverted: bool = True
    back: bool = True

    def tries(self, charuco: bool) -> list[tuple[bool, bool]]:
        """``[(inverted, back)]`` in the order tried; a checkerboard's back face is not told from its front
        (its corner order is read from the image's handedness), so it is not tried for one."""
        prints = [p for p, on in ((False, self.normal), (True, self.inverted)) if on]
        sides = [False, True] if self.back and charuco else [False]
        return [(p, s) for s in sides for p in prints]


@dataclass
class ImageHit:
    """One image's detection: ``(ids, corners px)`` or None, the board's marker ids seen, the stray ids (not
    the board's; dropped) and how the board was found."""

    hit: tuple[np.ndarray, np.ndarray] | None
    markers: tuple[int, ...] = ()
    stray: tuple[int, ...] = ()
    inverted: bool = False
    back: bool = False


class BoardDetector:
    """Finds a board in images, trying the prints of ``faces`` in turn (see :class:`Faces`)."""

    def __init__(self, board: Board, faces: Faces | None = None, min_corners: int = 6):
        self.board, self.faces, self.min_corners = board, faces or Faces(), min_corners
        if board.charuco:
            cv2_board = board.cv2_board()
            self.markers = cv2.aruco.ArucoDetector(cv2_board.getDictionary(), cv2.aruco.DetectorParameters())
            self.charuco = cv2.aruco.CharucoDetector(cv2_board)

    def _charuco(self, gray: np.ndarray) -> ImageHit:
        corners, ids, _ = self.markers.detectMarkers(gray)
        ids_ = [] if ids is None else [int(i) for i in ids.reshape(-1)]
        keep = [i for i, m in enumerate(ids_) if m < self.board.n_markers]
        stray = tuple(m for m in ids_ if m >= self.board.n_markers)
        markers = tuple(ids_[i] for i in keep)
        if len(keep) < 2:
            return ImageHit(None, markers, stray)
        kept_corners = tuple(corners[i] for i in keep)
        kept_ids = np.array([[ids_[i]] for i in keep], np.int32)
        cc, cids, _, _ = self.charuco.detectBoard(gray, markerCorners=kept_corners, markerIds=kept_ids)
        if cids is None or len(cids) < self.min_corners:
            return ImageHit(None, markers, stray)
        return ImageHit((cids.reshape(-1).astype(int), cc.reshape(-1, 2).astype(np.float64)), markers, stray)

    def _checkerboard(self, gray: np.ndarray) -> ImageHit:
        nx, ny = self.board.squares_x - 1, self.board.squares_y - 1
        ok, corners = cv2.findChessboardCornersSB(gray, (nx, ny), flags=cv2.CALIB_CB_NORMALIZE_IMAGE)  # type: ignore[call-overload]
        if not ok:
            return ImageHit(None)
        uv = _first_square_dark(gray, corners.reshape(-1, 2).astype(np.float64), nx)
        return ImageHit((np.arange(nx * ny), uv))

    def detect(self, image: np.ndarray) -> ImageHit:
        """The board in one image (grey or RGB): the first print of :attr:`faces` that gives ``min_corners``
        corners; when none does, the first try's markers (for the messages)."""
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        first: ImageHit | None = None
        for inverted, back in self.faces.tries(self.board.charuco):
            view = 255 - gray if inverted else gray
            view = np.ascontiguousarray(view[:, ::-1]) if back else view
            found = self._charuco(view) if self.board.charuco else self._checkerboard(view)
            first = first or found
            if found.hit is not None:
                ids, uv = found.hit
                if back:  # the flipped image's column u is the image's W - 1 - u (pixel centres at integers)
                    uv = np.column_stack([gray.shape[1] - 1 - uv[:, 0], uv[:, 1]])
                return ImageHit((ids, uv), found.markers, found.stray, inverted, back)
        return first or ImageHit(None)


def detect_image(image: np.ndarray, board: Board, detector, min_corners: int):
    """One image's board corners ``(ids, corners px)`` (None with fewer than ``min_corners``), and the ArUco
    marker ids seen; ``detector`` a :class:`BoardDetector` (made here when None)."""
    if not isinstance(detector, BoardDetector):
        detector = BoardDetector(board, min_corners=min_corners)
    found = detector.detect(image)
    return found.hit, found.markers


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


def detect_images(items, detector: BoardDetector) -> Detections:
    """The board in ``(frame key, image)`` pairs: one camera's :class:`Detections` with what detection
    took (inverted prints, back faces) and dropped (stray marker ids)."""
    det = Detections({}, (0, 0), faces=detector.faces)
    seen: set[int] = set()
    stray: set[int] = set()
    for key, image in items:
        det.size, det.images = (image.shape[1], image.shape[0]), det.images + 1
        found = detector.detect(image)
        seen.update(found.markers)
        if found.markers or found.stray:
            det.marker_frames += 1
        if found.stray:
            det.stray += len(found.stray)
            det.stray_frames += 1
            stray.update(found.stray)
        if found.hit is not None:
            det.frames[key] = found.hit
            det.inverted += found.inverted
            det.back += found.back
    det.marker_ids, det.stray_ids = tuple(sorted(seen)), tuple(sorted(stray))
    return det


def detect_board(source: str | Path, board: Board, *, every: int = 1, min_corners: int = 6,
                 faces: Faces | None = None) -> Detections:
    """Detect the board in every ``every``-th frame of a video or image sequence, trying the prints of
    ``faces`` (default: as printed, inverted, the back face)."""
    detector = BoardDetector(board, faces, min_corners)
    keys, files = frames_of(source)

    def images():
        if files is not None:
            for i, (key, file) in enumerate(zip(keys, files)):
                if i % every == 0:
                    image = cv2.imread(str(file), cv2.IMREAD_GRAYSCALE)
                    if image is None:
                        raise UserError(f"{file}: cannot read image")
                    yield key, image
        else:
            for i, image in video.iter_frames(source):
                if i % every == 0:
                    yield i, image

    return detect_images(images(), detector)


STRAY_SHARE = 0.5
"""Ids beyond the board's in more than this share of the images showing markers mean a board of another size
(refused); in fewer, they are stray detections (dropped and counted)."""


def check_board_matches(name: str, source, det: Detections, board: Board) -> None:
    """A one-line error naming the cause when the board seen does not match ``board``: ArUco ids beyond the
    board's in most images (its size), markers but no corners, or no board at all. Ids beyond the board's in
    a few images are stray detections, dropped (:attr:`Detections.stray`)."""
    if not board.charuco and (board.squares_x + board.squares_y) % 2 == 0:
        raise UserError(
            f"checkerboard {board.describe()}: with an even number of squares in all it looks the same "
            "turned by 180 degrees, so the cameras cannot agree on its corners",
            hint="use a board with an odd squares_x + squares_y (e.g. 8x11 or 7x6)",
        )
    where = f"camera {name} ({source})"
    faces = det.faces or Faces()
    untried = "".join([
        "" if faces.back or not board.charuco else "; if it sees a two-sided board's back face (mirrored), "
        "leave out --one-sided, which skips it",
        "" if faces.inverted else "; a board printed inverted (white on black) is not looked for "
        "(pass --inverted)",
        "" if faces.normal else "; the board is looked for printed inverted only (--inverted): leave it out "
        "for "        "a board printed black on white"])
    if board.charuco and det.stray_frames > STRAY_SHARE * max(det.marker_frames, 1):
        raise UserError(
            f"{where}: {det.stray_frames} of the {det.marker_frames} images showing ArUco markers show ids "
            f"beyond the board's 0-{board.n_markers - 1} (up to {max(det.stray_ids)}): the board "
            f"{board.describe()} is smaller than the one filmed",
            hint="check board_x, board_y in board.toml (or --squares)" + untried,
        )
    if not det.frames:
        if not board.charuco:
            what = "no checkerboard"
            hint = ("check board_x, board_y (--squares: squares, not inner corners) and that the board is in "
                    "view and in focus")
        elif det.marker_ids:
            what = (f"ArUco markers {_ranges(det.marker_ids)} but no ChArUco corners (fewer than 6 in every "
                    "image)")
            hint = ("check the board's size and marker length (board_x, board_y, marker_length; --squares, "
                    "--marker-length) against the printed board, and that more of it is in view")
        else:
            what = "no ArUco marker of the board's dictionary" + (
                f" (only stray ids {_ranges(det.stray_ids)})" if det.stray_ids else "")
            tried = [w for w, on in (("inverted prints", faces.inverted), ("a two-sided board's back face",
                                                                        faces.back)) if on]
            hint = ("check the dictionary (dict_size, marker_bits; --dict) and that the board is in view and "
                    "in focus" + (f"; also tried: {', '.join(tried)}" if tried else ""))
        raise UserError(f"{where}: {what} in {det.images} image(s) for the board {board.describe()}",
                        hint=hint + untried)


def _ranges(ids) -> str:
    """``0-4, 7, 9-10``: sorted ids as runs."""
    runs: list[list[int]] = []
    ids = sorted(ids)
    for i in ids:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)
