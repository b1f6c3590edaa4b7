"""The turntable's rotation axis, calibrated from a board: capture a calibration board
standing on the turntable at several angles, find the board's pose in each view, and fit
the one axis about which every view is turned from the first.

With the axis known, a scan on that turntable records each view's pose
(``rig_from_object``, the object frame being the rig frame at the first angle), so
registration starts from the turntable's poses instead of searching for them.

Method: for views ``i`` with board poses ``P_i`` (``rig_from_board``) and commanded angles
``a_i``, the motion ``M_i = P_i P_0^-1`` is a turn by ``a_i - a_0`` about the axis line.
The direction ``d`` is the least-squares fit of ``sin(a_i - a_0) d`` to the skew part of
each ``M_i``'s rotation (so a positive angle turns right-handed about ``d``); a point ``p``
on the axis solves ``(I - R_i) p = t_i`` for all views by least squares, fixed along the
axis at the boards' mean height. The angles each view actually turned are measured about
``d`` and compared with the commanded ones: their ratio is the turntable's scale (1 when
the firmware's units are degrees), their scatter the fit's angular residual.

References
----------
Fitzgibbon, Cross, Zisserman, "Automatic 3D model construction for turn-table sequences",
SMILE 1998 (one rotation axis shared by every view of a turntable sequence).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError

KIND = "slscan-turntable-axis"
VERSION = 1


@dataclass(frozen=True)
class TurntableAxis:
    """A turntable's rotation axis in the rig frame (the camera's, mm, y down).

    point : (3,) mm, a point on the axis (at the boards' mean position along it)
    direction : (3,) unit; a positive turntable angle turns right-handed about it
    scale : degrees the table turned per degree commanded (1: the units are right)
    rms_angle_deg : RMS difference between measured and commanded turns (after ``scale``)
    rms_mm : RMS distance between the board corners as seen and as the axis predicts them
    views : how many board views were fitted
    angles_deg : (views,) the commanded angles used
    """

    point: np.ndarray
    direction: np.ndarray
    scale: float
    rms_angle_deg: float
    rms_mm: float
    views: int
    angles_deg: tuple[float, ...] = ()

    def pose(self, angle_deg: float, start_deg: float = 0.0) -> np.ndarray:
        """(4, 4) ``rig_from_object`` of the object turned to ``angle_deg`` when its frame is
        the rig frame at ``start_deg``."""
        from slscan.devices.turntable import turn_about_axis

        return turn_about_axis(self.point, self.direction, angle_deg - start_deg)

    def to_dict(self) -> dict:
        return {
            "kind": KIND, "version": VERSION, "frame": "rig (camera) frame, mm, y down",
            "point_mm": [float(v) for v in self.point], "direction": [float(v) for v in self.direction],
            "scale": self.scale, "rms_angle_deg": self.rms_angle_deg, "rms_mm": self.rms_mm,
            "views": self.views, "angles_deg": list(self.angles_deg),
        }

    @classmethod
    def from_dict(cls, d: dict, where: str = "turntable axis") -> TurntableAxis:
        if not isinstance(d, dict) or d.get("kind") != KIND:
            raise SlscanError(f"{where}: not a turntable axis file (expected \"kind\": \"{KIND}\"; "
                              "write one with slscan turntable-axis)")
        try:
            point = np.asarray(d["point_mm"], float).reshape(3)
            direction = np.asarray(d["direction"], float).reshape(3)
        except KeyError as exc:
            raise SlscanError(f"{where}: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError):
            raise SlscanError(f"{where}: point_mm and direction must be 3 numbers each") from None
        norm = float(np.linalg.norm(direction))
        if not (np.isfinite(point).all() and np.isfinite(direction).all() and norm > 0):
            raise SlscanError(f"{where}: direction must be a non-zero finite vector, point finite")
        return cls(point, direction / norm, float(d.get("scale", 1.0)), float(d.get("rms_angle_deg", 0.0)),
                   float(d.get("rms_mm", 0.0)), int(d.get("views", 0)),
                   tuple(float(a) for a in d.get("angles_deg", ())))


def save_turntable_axis(axis: TurntableAxis, path: str | os.PathLike) -> Path:
    """Write ``axis`` as JSON (to a temporary name, then renamed: never half-written)."""
    from slscan.fsio import write_json

    path = Path(path)
    write_json(path, axis.to_dict())
    return path


def load_turntable_axis(path: str | os.PathLike) -> TurntableAxis:
    """Read a file written by :func:`save_turntable_axis`; one clear error naming the file."""
    from slscan.fsio import read_json

    path = Path(path)
    d = read_json(path, "turntable axis file (write one with slscan turntable-axis)")
    return TurntableAxis.from_dict(d, str(path))


def _vee(r: np.ndarray) -> np.ndarray:
    """sin(angle) * axis of rotation ``r`` (3, 3): the vector of its skew part."""
    s = (r - r.T) / 2.0
    return np.array([s[2, 1], s[0, 2], s[1, 0]])


def fit_turntable_axis(
    rig_from_board: Sequence[np.ndarray],
    angles_deg: Sequence[float],
    *,
    points: np.ndarray | None = None,
) -> TurntableAxis:
    """Fit the turntable axis to board poses taken at known turntable angles.

    rig_from_board : (n, 4, 4) mm, the board's pose in each view (n >= 2)
    angles_deg : (n,) the commanded turntable angle of each view, degrees; at least one
        pair must differ by 10 degrees or more
    points : (m, 3) mm board-frame points for :attr:`TurntableAxis.rms_mm` (default: the
        origin and three unit-100 mm points)
    """
    poses = [np.asarray(p, float) for p in rig_from_board]
    angles = np.asarray(angles_deg, float)
    if len(poses) < 2 or len(poses) != len(angles):
        raise SlscanError(f"the turntable axis needs two or more board views with their angles "
                          f"(got {len(poses)} poses, {len(angles)} angles)")
    deltas = np.radians(angles - angles[0])
    if np.max(np.abs(np.sin(deltas[1:]))) < math.sin(math.radians(10)):
        raise SlscanError("the board views are turned less than 10 degrees (or a multiple of 180) from the "
                          "first: turn the table further between views (e.g. --stage-sweep 80)")
    inv0 = np.linalg.inv(poses[0])
    motions = [p @ inv0 for p in poses[1:]]
    vees = np.array([_vee(m[:3, :3]) for m in motions])
    weights = np.sin(deltas[1:])
    direction = (weights[:, None] * vees).sum(axis=0)
    direction /= np.linalg.norm(direction)
    # a point on the axis: (I - R_i) p = t_i, plus d . p = d . (mean board origin)
    centre = np.mean([p[:3, 3] for p in poses], axis=0)
    a = np.concatenate([np.eye(3) - m[:3, :3] for m in motions] + [direction[None, :]])
    b = np.concatenate([m[:3, 3] for m in motions] + [[direction @ centre]])
    point = np.linalg.lstsq(a, b, rcond=None)[0]
    measured = np.array([math.atan2(direction @ _vee(m[:3, :3]), (np.trace(m[:3, :3]) - 1) / 2) for m in motions])
    commanded = deltas[1:]
    scale = float((measured @ commanded) / (commanded @ commanded))
    rms_angle = float(np.degrees(np.sqrt(np.mean((measured - scale * commanded) ** 2))))
    from slscan.devices.turntable import turn_about_axis

    pts = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0], [100, 100, 0]], float) if points is None else points
    homog = np.c_[pts, np.ones(len(pts))]
    errors = []
    for pose, delta in zip(poses[1:], commanded, strict=True):
        predicted = turn_about_axis(point, direction, math.degrees(scale * delta)) @ poses[0] @ homog.T
        errors.append(np.linalg.norm((predicted - pose @ homog.T)[:3], axis=0))
    rms_mm = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
    return TurntableAxis(point, direction, scale, rms_angle, rms_mm, len(poses), tuple(float(x) for x in angles))


def board_on_turntable(board, *, in_front_mm: float = 60.0, lean_deg: float = 10.0) -> np.ndarray:
    """(4, 4) ``turntable_from_board`` of ``board`` standing on the virtual rig's turntable
    facing the camera at angle 0, its centre ``in_front_mm`` in front of the axis and leaning
    back ``lean_deg`` (the virtual rig's stand-in for a board propped on a real table)."""
    from slscan.rig import rotation_about_axis

    centre = np.array([*np.asarray(board.size, float) / 2, 0.0])
    r = rotation_about_axis([1, 0, 0], math.radians(lean_deg))
    pose = np.eye(4)
    pose[:3, :3] = r
    pose[:3, 3] = np.array([0.0, 0.0, -in_front_mm]) - r @ centre
    return pose


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    r = a[:3, :3] @ b[:3, :3].T
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def _nearer_of_flips(pose: np.ndarray, previous: np.ndarray, board) -> np.ndarray:
    """A chessboard's corners are found up to a half turn about the board's normal (its
    pattern looks the same turned 180 degrees): of ``pose`` and ``pose`` with the corners
    numbered from the other end, the one turned less from the ``previous`` view."""
    centre = board.object_points().mean(axis=0)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])
    flip[:3, 3] = 2 * centre * [1, 1, 0]
    flipped = pose @ flip
    return flipped if _rotation_deg(flipped, previous) < _rotation_deg(pose, previous) else pose


def board_poses_in_session(session, board, lens) -> tuple[list[np.ndarray], list[float], list[str]]:
    """The board's pose ``rig_from_board`` (4, 4) mm and the turntable angle of every view
    of ``session`` where the board is found in the white frame; views without a recorded
    ``turntable_deg`` are an error naming the session. Returns (poses, angles, view names)."""
    from slscan.calibrate.camera import detect_corners
    from slscan.calibrate.target import board_image_id, board_pose

    image_id = board_image_id(session)
    poses, angles, names = [], [], []
    for view in session.views:
        if view.turntable_deg is None:
            raise SlscanError(f"{session.root / view.name}: no turntable angle recorded (capture the board with "
                              "slscan scan --board ... --stage serial:PORT --stage-sweep 80 --stage-start -40)")
        rec = view.image_for(image_id)
        detection = detect_corners(session.read_image(view, rec), board, source=str(session.root / view.name))
        if not detection:
            continue
        pose = board_pose(lens, detection, board)
        if poses and board.kind == "chessboard":
            pose = _nearer_of_flips(pose, poses[-1], board)
        poses.append(pose)
        angles.append(float(view.turntable_deg))
        names.append(view.name)
    return poses, angles, names
