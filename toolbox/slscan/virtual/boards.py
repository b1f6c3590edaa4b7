"""Calibration boards as virtual-rig scenes, their poses, and calibration sessions to capture.

A board is a thin box whose front face (z = 0 of the board frame, looking towards -z,
see :mod:`slscan.calibrate.target`) carries the printed chessboard or ChArUco pattern on
a white margin; its other faces are grey card. The pattern is a texture rendered by
OpenCV and blurred by a Gaussian of ``edge_sigma`` mm before it is sampled: the virtual
camera samples albedo at pixel centres without averaging over the pixel, and an
unblurred texture would alias the square edges and bias the corners. The blur is
symmetric about every edge, so the corners stay exactly where :meth:`Board.object_points`
puts them: the session's calibration (the true rig) and the views' ``rig_from_object``
are the ground truth of a calibration.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from slscan.calibrate.target import Board
from slscan.capture.session import Session
from slscan.errors import SlscanError
from slscan.rig import Rig, rotation_about_axis
from slscan.virtual.scenes import Scene

BLACK_ALBEDO = 0.05
WHITE_ALBEDO = 0.85
CARD_ALBEDO = 0.5
DEFAULT_MARGIN_SQUARES = 0.75
"""White margin around the squares, in squares (OpenCV's detectors want a quiet zone)."""

BOARD_POSES = (
    # (turn about y, tilt about x, roll about z) degrees, offset (x, y, z) mm from the working point
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ((32.0, 0.0, 4.0), (-30.0, 10.0, -120.0)),
    ((-30.0, 4.0, -6.0), (30.0, -10.0, 100.0)),
    ((0.0, 30.0, 8.0), (0.0, -20.0, 60.0)),
    ((4.0, -30.0, -8.0), (10.0, 25.0, -60.0)),
    ((22.0, 22.0, -12.0), (-20.0, -15.0, 150.0)),
    ((-22.0, -22.0, 14.0), (20.0, 15.0, -150.0)),
    ((26.0, -18.0, 2.0), (-10.0, 0.0, 0.0)),
)
"""A spread of board orientations for Zhang's method: turns and tilts of 20-30 degrees."""


@dataclass(frozen=True)
class _BoardAlbedo:
    """Albedo of a board box: the blurred pattern texture on the front face, card elsewhere."""

    texture: np.ndarray  # (th, tw) float32 albedo
    texels_per_mm: float
    origin: tuple[float, float]  # board-frame (x, y) mm of the texture's top-left pixel edge
    card: float

    def _front(self, points: np.ndarray) -> np.ndarray:
        th, tw = self.texture.shape
        x = (points[:, 0] - self.origin[0]) * self.texels_per_mm - 0.5
        y = (points[:, 1] - self.origin[1]) * self.texels_per_mm - 0.5
        x, y = np.clip(x, 0, tw - 1.001), np.clip(y, 0, th - 1.001)
        x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
        fx, fy = x - x0, y - y0
        t = self.texture
        top = t[y0, x0] * (1 - fx) + t[y0, x0 + 1] * fx
        bottom = t[y0 + 1, x0] * (1 - fx) + t[y0 + 1, x0 + 1] * fx
        return top * (1 - fy) + bottom * fy

    def _values(self, points: np.ndarray) -> np.ndarray:
        value = np.full(len(points), self.card, np.float64)
        front = np.abs(points[:, 2]) < 1e-3
        if front.any():
            value[front] = self._front(points[front])
        return np.repeat(value.astype(np.float32)[:, None], 3, axis=1)

    def at(self, points, triangle_ids, bary):
        return self._values(np.asarray(points, float))

    def vertex_colors(self, vertices):
        return self._values(np.asarray(vertices, float))


def board_scene(
    board: Board,
    *,
    margin: float | None = None,
    thickness: float = 4.0,
    edge_sigma: float = 0.5,
    texels_per_mm: float | None = None,
    black: float = BLACK_ALBEDO,
    white: float = WHITE_ALBEDO,
) -> Scene:
    """A virtual-rig scene of ``board``: a thin box with the pattern on its front face.

    Parameters
    ----------
    board : the target (its squares area spans ``[0, w] x [0, h]`` mm of the board frame)
    margin : white border around the squares, mm; default ``0.75 * square``
    thickness : mm, the box extends from z = 0 (front) to z = +thickness
    edge_sigma : mm, Gaussian blur of the printed pattern (anti-aliasing; about half the
        camera pixel's footprint on the board is right)
    texels_per_mm : texture resolution; default: 3 texels per ``edge_sigma``, 4 at least
    black, white : albedo of the ink and of the paper

    Returns
    -------
    Scene
        Named ``"<kind>-<columns>x<rows>"``, matte, object frame = board frame.
    """
    if edge_sigma <= 0:
        raise SlscanError(f"edge_sigma must be positive, got {edge_sigma}")
    margin = DEFAULT_MARGIN_SQUARES * board.square if margin is None else float(margin)
    if margin < 0 or thickness <= 0:
        raise SlscanError("board margin must be >= 0 and thickness > 0")
    tpm = float(texels_per_mm or max(4.0, 3.0 / edge_sigma))
    px_per_square = max(4, round(board.square * tpm))
    tpm = px_per_square / board.square  # whole texels per square: corners on texel edges
    margin_px = math.ceil(margin * tpm) + math.ceil(4 * edge_sigma * tpm)
    printed = board.image(px_per_square, margin_px).astype(np.float32) / 255.0
    texture = cv2.GaussianBlur(printed, (0, 0), edge_sigma * tpm, borderType=cv2.BORDER_REPLICATE)
    texture = black + (white - black) * texture
    origin = (-margin_px / tpm, -margin_px / tpm)

    w, h = board.size
    x0, y0, x1, y1 = -margin, -margin, w + margin, h + margin
    corners = np.array(
        [[x, y, z] for z in (0.0, thickness) for y in (y0, y1) for x in (x0, x1)], float
    )
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int32)
    centroid = corners.mean(axis=0)
    v = corners[tris]
    face_n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", face_n, v.mean(axis=1) - centroid) < 0
    tris[flip] = tris[flip][:, ::-1]  # faces wind outwards
    albedo = _BoardAlbedo(texture.astype(np.float32), tpm, origin, CARD_ALBEDO)
    return Scene(f"{board.kind}-{board.columns}x{board.rows}", corners, tris, None, albedo)


def board_poses(
    rig: Rig,
    board: Board,
    n: int = 6,
    *,
    distance: float | None = None,
) -> list[np.ndarray]:
    """``n`` poses ``rig_from_object`` (4, 4) of ``board`` for calibration, mm.

    The board's centre sits near the point on the camera axis at ``distance`` (default:
    the rig's working distance), turned and tilted by 20-30 degrees about varied axes
    (:data:`BOARD_POSES`, used in order; when ``n`` exceeds them they repeat mirrored —
    turns, tilts and offsets negated — and each further round 10 % further away, so the
    board stays inside both frusta). The first pose faces the camera.
    """
    if n < 1:
        raise SlscanError(f"need at least one board pose, got {n}")
    distance = rig.working_distance if distance is None else float(distance)
    centre = np.array([*np.asarray(board.size) / 2, 0.0])
    poses = []
    for k in range(n):
        (turn, tilt, roll), offset = BOARD_POSES[k % len(BOARD_POSES)]
        cycle = k // len(BOARD_POSES)
        offset = np.asarray(offset, np.float64)
        if cycle:
            turn, tilt, roll = (-turn, -tilt, roll) if cycle % 2 else (turn, tilt, roll)
            offset = np.array([-offset[0], -offset[1], offset[2] + 0.1 * cycle * distance])
        r = (
            rotation_about_axis([0, 1, 0], math.radians(turn))
            @ rotation_about_axis([1, 0, 0], math.radians(tilt))
            @ rotation_about_axis([0, 0, 1], math.radians(roll))
        )
        pose = np.eye(4)
        pose[:3, :3] = r
        pose[:3, 3] = np.array([0.0, 0.0, distance]) + offset - r @ centre
        poses.append(pose)
    return poses


def default_edge_sigma(rig: Rig, distance: float | None = None) -> float:
    """Blur (mm) of a board's print: 0.6 camera pixel footprints at ``distance``."""
    distance = rig.working_distance if distance is None else float(distance)
    return 0.6 * distance / rig.camera.fx


def capture_calibration_session(
    out: str | os.PathLike,
    board: Board,
    *,
    patterns: str | None = None,
    config=None,
    poses: Sequence[np.ndarray] | None = None,
    n_poses: int = 6,
    rig: Rig | None = None,
    overwrite: bool = False,
    rec=None,
    progress: Callable[[str], None] | None = None,
) -> Session:
    """Capture a calibration session of ``board`` on the virtual rig into folder ``out``.

    patterns : the coded patterns after white and black, a set name of
        :func:`slscan.patterns.set_names` or several joined by "+": "both" (hybrid and Gray
        code, the default), "phase" (phase shifting), "gray+phase" (both families on the
        same poses, to compare them), ...; they code the projector rows too. Replaces
        ``config.patterns`` when both are given.
    config : a :class:`~slscan.virtual.device.VirtualCaptureConfig`; default: the
        paper's rig, ``patterns`` with row codes, no ring-light images. Its ``scene`` and
        ``views`` are ignored.
    poses : ``rig_from_object`` of each view; default :func:`board_poses` (``n_poses``)
    rig : default ``config.rig()``

    Returns the written session; its calibration is the true rig and each view's
    ``rig_from_object`` the board's true pose.
    """
    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    if config is None:
        config = VirtualCaptureConfig(patterns=patterns or "both", gray_rows=True, lit_images=False)
    elif patterns is not None:
        config = replace(config, patterns=patterns)
    rig = rig or config.rig()
    poses = list(poses) if poses is not None else board_poses(rig, board, n_poses)
    scene = board_scene(board, edge_sigma=default_edge_sigma(rig))
    config = replace(config, views=len(poses))
    return capture_session(
        config,
        out,
        overwrite=overwrite,
        rec=rec,
        progress=progress,
        scene=scene,
        poses=poses,
        rig=rig,
    )
