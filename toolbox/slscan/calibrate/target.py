"""Printed calibration targets: chessboard and ChArUco boards, their corners and their images;
the corners found in a camera image and the board pose they give.

Board frame (mm): origin at the outer top-left corner of the squares, x along a row of
squares (right), y down, z into the board, so its printed face looks towards -z (towards
the camera when the board is held in front of it, like a scene of the virtual rig).
Inner corner ``k = j * columns + i`` (``i < columns``, ``j < rows``) lies at
``((i + 1) square, (j + 1) square, 0)``: the order of OpenCV's chessboard detector and of
ChArUco corner ids. The top-left square is black.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from slscan.calibrate.options import BOARD_KINDS, DEFAULT_DICTIONARY
from slscan.errors import SlscanError

if TYPE_CHECKING:
    from slscan.capture.session import Session
    from slscan.rig import PinholeModel

MARKER_FRACTION = 0.75
"""Default ChArUco marker side, as a fraction of the square."""
MIN_CORNERS = 6
"""Fewest corners a view needs to count as a view of the board."""


@dataclass(frozen=True)
class Board:
    """A planar calibration target.

    kind : {"chessboard", "charuco"}
    columns, rows : inner corners along x and along y (a 9 x 7 board has 10 x 8 squares)
    square : side of a square, mm (or the unit the rest of the calibration is in)
    marker : ChArUco marker side, mm; 0 means ``MARKER_FRACTION * square``
    dictionary : ChArUco marker dictionary, a ``cv2.aruco`` name such as "DICT_4X4_100"
    """

    kind: str = "chessboard"
    columns: int = 9
    rows: int = 7
    square: float = 50.0
    marker: float = 0.0
    dictionary: str = DEFAULT_DICTIONARY

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise SlscanError(
                f"unknown board kind {self.kind!r}: expected one of {', '.join(BOARD_KINDS)}"
            )
        if self.columns < 2 or self.rows < 2:
            raise SlscanError(
                f"a board needs at least 2 x 2 inner corners, got {self.columns}x{self.rows}"
            )
        if not self.square > 0:
            raise SlscanError(f"board square must be positive, got {self.square}")
        if self.kind == "charuco":
            if not 0 <= self.marker < self.square:
                raise SlscanError(
                    f"ChArUco marker side {self.marker} must be below the square side {self.square}"
                )
            if not hasattr(cv2.aruco, self.dictionary):
                raise SlscanError(
                    f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_4X4_100)"
                )
            n_markers = ((self.columns + 1) * (self.rows + 1)) // 2
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
            if dictionary.bytesList.shape[0] < n_markers:
                raise SlscanError(
                    f"dictionary {self.dictionary} has {dictionary.bytesList.shape[0]} markers, "
                    f"a {self.columns}x{self.rows} ChArUco board needs {n_markers}"
                )

    # --- geometry ---------------------------------------------------------------------

    @property
    def squares(self) -> tuple[int, int]:
        """Number of squares along x and y."""
        return self.columns + 1, self.rows + 1

    @property
    def size(self) -> tuple[float, float]:
        """Width and height of the squares area, mm."""
        return self.squares[0] * self.square, self.squares[1] * self.square

    @property
    def n_corners(self) -> int:
        return self.columns * self.rows

    @property
    def marker_side(self) -> float:
        """ChArUco marker side, mm."""
        return self.marker if self.marker > 0 else MARKER_FRACTION * self.square

    def object_points(self, ids: np.ndarray | None = None) -> np.ndarray:
        """Inner corners (n, 3) float64 in the board frame, mm; all of them, or ``ids`` (n,)."""
        k = np.arange(self.n_corners) if ids is None else np.asarray(ids, int).reshape(-1)
        if k.size and (k.min() < 0 or k.max() >= self.n_corners):
            raise SlscanError(f"corner ids must lie in 0..{self.n_corners - 1}")
        i, j = k % self.columns, k // self.columns
        return np.stack([(i + 1) * self.square, (j + 1) * self.square, np.zeros(len(k))], axis=1)

    def outline(self, margin: float = 0.0) -> np.ndarray:
        """The squares area grown by ``margin`` mm: its 4 corners (4, 3), board frame."""
        w, h = self.size
        m = margin
        return np.array([[-m, -m, 0], [w + m, -m, 0], [w + m, h + m, 0], [-m, h + m, 0]], float)

    # --- OpenCV -----------------------------------------------------------------------

    def aruco_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV ChArUco board of a ``"charuco"`` board (mm units)."""
        if self.kind != "charuco":
            raise SlscanError("only a ChArUco board has an ArUco board")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            self.squares, float(self.square), float(self.marker_side), dictionary
        )

    def image(self, px_per_square: int, margin_px: int = 0) -> np.ndarray:
        """The printed board (h, w) uint8, black 0 on white 255, ``px_per_square`` px a square.

        The squares area spans pixels ``margin_px .. margin_px + squares * px_per_square``
        (pixel edges), so board coordinate ``x`` mm is at pixel edge
        ``margin_px + x / square * px_per_square``.
        """
        px_per_square = int(px_per_square)
        sx, sy = self.squares
        w, h = sx * px_per_square + 2 * margin_px, sy * px_per_square + 2 * margin_px
        if self.kind == "charuco":
            image = self.aruco_board().generateImage((w, h), marginSize=margin_px, borderBits=1)
            if image.shape != (h, w):
                raise SlscanError("OpenCV drew the ChArUco board at an unexpected size")
            return image
        checks = (np.add.outer(np.arange(sy), np.arange(sx)) % 2).astype(np.uint8) * 255
        image = np.full((h, w), 255, np.uint8)
        image[margin_px : h - margin_px, margin_px : w - margin_px] = np.kron(
            checks, np.ones((px_per_square, px_per_square), np.uint8)
        )
        return image

    # --- serialisation ------------------------------------------------------------------

    def describe(self) -> str:
        text = f"{self.kind} {self.columns}x{self.rows} inner corners, {self.square:g} mm squares"
        if self.kind == "charuco":
            text += f", {self.marker_side:g} mm markers ({self.dictionary})"
        return text

    def to_dict(self) -> dict:
        d = asdict(self)
        if self.kind == "chessboard":
            d.pop("marker")
            d.pop("dictionary")
        return d

    @classmethod
    def from_dict(cls, d: dict, what: str = "board") -> Board:
        try:
            return cls(
                kind=str(d["kind"]),
                columns=int(d["columns"]),
                rows=int(d["rows"]),
                square=float(d["square"]),
                marker=float(d.get("marker", 0.0)),
                dictionary=str(d.get("dictionary", DEFAULT_DICTIONARY)),
            )
        except KeyError as exc:
            raise SlscanError(f"{what}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise SlscanError(f"{what}: {exc}") from None


def parse_board_size(text: str) -> tuple[int, int]:
    """``"9x7"`` → (9, 7): inner corners along x and along y."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text)
    if not m:
        raise SlscanError(f"board size {text!r}: expected COLUMNSxROWS of inner corners, e.g. 9x7")
    return int(m.group(1)), int(m.group(2))


# --- the board found in an image ---------------------------------------------------------


@dataclass(frozen=True)
class CornerDetection:
    """Board corners found in one image.

    source : the image's file (or another label), for messages
    corners : (k, 2) float64 px, OpenCV pixel centres
    ids : (k,) int corner ids, rows of :meth:`Board.object_points`
    reason : why the board was not found ("" when it was)

    False when fewer than :data:`MIN_CORNERS` corners were found.
    """

    source: str
    corners: np.ndarray
    ids: np.ndarray
    reason: str = ""

    def __bool__(self) -> bool:
        return len(self.ids) >= MIN_CORNERS

    @classmethod
    def failed(cls, source: str, reason: str) -> CornerDetection:
        return cls(source, np.zeros((0, 2)), np.zeros(0, int), reason)


def board_image_id(session: Session) -> str:
    """The pattern id of the all-white frame, in which the board's corners are found."""
    for p in session.patterns:
        if p.family == "flat" and list(p.params.get("value", [])) == [255, 255, 255]:
            return p.id
    raise SlscanError(f"{session.root}: the session has no all-white frame to find the board in")


def pose_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """4x4 pose from OpenCV's rotation vector and translation."""
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))[0]
    pose[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return pose


def board_pose(lens: PinholeModel, detection: CornerDetection, board: Board) -> np.ndarray:
    """The board's pose (4, 4) ``camera_from_board`` from its corners seen by ``lens``."""
    obj = board.object_points(detection.ids)
    ok, rvec, tvec = cv2.solvePnP(
        obj,
        detection.corners.reshape(-1, 1, 2),
        lens.K,
        lens.dist_array,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    if not ok:
        raise SlscanError(f"{detection.source}: the board's pose could not be found")
    return pose_matrix(rvec, tvec)
