"""The archive's upright object frame: turntable axis up, origin at the object's base.

Range maps live in the rig frame (the camera's: x right, y down, z forward); a
registration first puts them in the frame of its reference (a scan's camera frame, or
the object frame a capture recorded). Neither is upright, so every exported model would
open on its side or upside down. :func:`object_frame` finds one documented frame that
every archive output shares (aligned scans, .mlp, fused and simplified meshes, OBJ, PLY,
glTF, the Rerun views):

- **+Y up**: the turntable axis, estimated from the registered poses (the views of a
  turntable campaign are turned about one axis), its sign taken so that the cameras,
  held upright, agree; without a turntable (fewer than two views turned about a common
  axis, or an axis more than 45° from the cameras' up), the cameras' mean up direction.
- **+Z towards the reference view's camera** (horizontally), **+X = Y × Z**: the
  reference view is the front view, as glTF, MeshLab and Blender show a model.
- **Origin** on the turntable axis (without one: the centre of the object's horizontal
  extent) at the height of the object's base, so the object stands on the y = 0 plane.
- Millimetres, right-handed. glTF's metres, y up are a pure scale from it; Blender's
  glTF importer turns y up into its z up.

The rig frame is kept in the metadata: each pose is ``object_from_scan`` (the scan is in
its rig frame), and ``object_from_reference`` maps the registration's reference frame to
the object frame.

References
----------
.. [1] Fitzgibbon, Cross, Zisserman, "Automatic 3D model construction for turn-table
   sequences", SMILE 1998 (the turntable's single rotation axis).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

FRAME_AXES = "x right, y up (turntable axis), z towards the reference view's camera; mm"
FRAME_ORIGIN = "on the turntable axis at the object's base (the object stands on y = 0)"

MIN_TURN_DEG = 10.0
"""Pairs of views turned less than this are too close to tell an axis."""
AXIS_AGREEMENT_DEG = 3.0
"""Two pairs' rotation axes closer than this count as the same turntable axis."""
MAX_TILT_DEG = 45.0
"""A turntable axis further than this from the cameras' up is not taken as up."""
BASE_PERCENTILE = 0.1
"""The base height: this percentile of the points' heights (robust to stray samples)."""


@dataclass(frozen=True)
class ObjectFrame:
    """Where the upright object frame sits in the registration's reference frame.

    object_from_reference : (4, 4) float64, mm, rigid: reference frame → object frame
    up_from : {"turntable", "cameras"}: what gave +Y
    turntable_views : views whose poses agree on the turntable axis (empty without one)
    axis_spread_deg : RMS angle between those views' pair axes and the fitted axis
    tilt_deg : angle between the turntable axis and the cameras' mean up
    """

    object_from_reference: np.ndarray
    up_from: str
    turntable_views: tuple[str, ...] = ()
    axis_spread_deg: float = float("nan")
    tilt_deg: float = float("nan")

    def apply(self, poses: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``reference_from_scan`` poses → ``object_from_scan``."""
        return {k: self.object_from_reference @ np.asarray(v, float) for k, v in poses.items()}

    def to_json(self) -> dict[str, Any]:
        def num(x: float) -> float | None:
            return None if not math.isfinite(x) else round(float(x), 4)

        return {
            "name": "object",
            "axes": FRAME_AXES,
            "origin": FRAME_ORIGIN,
            "up_from": self.up_from,
            "turntable_views": list(self.turntable_views),
            "axis_spread_deg": num(self.axis_spread_deg),
            "tilt_deg": num(self.tilt_deg),
            "object_from_reference": self.object_from_reference.tolist(),
        }


def rotation_axis_angle(rotation: np.ndarray) -> tuple[np.ndarray, float]:
    """Unit axis (3,) and angle (rad, in [0, π]) of a (3, 3) rotation."""
    r = np.asarray(rotation, float)
    angle = math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0)))
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if np.linalg.norm(w) > 1e-6:
        return w / np.linalg.norm(w), angle
    # 0 or 180 degrees: the axis is the eigenvector of eigenvalue +1
    values, vectors = np.linalg.eigh((r + r.T) / 2.0)
    return vectors[:, int(np.argmax(values))], angle


def turntable_axis(
    poses: Mapping[str, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, tuple[str, ...], float] | None:
    """The common rotation axis of views taken on a turntable, or None.

    poses : {name: (4, 4) reference_from_scan, mm}
    Returns ``(direction (3,), point (3,), views, spread_deg)``: a unit direction (sign
    arbitrary), a point on the axis, the views whose pairwise motions turn about it, and
    the RMS angle between their pairs' axes and the fitted one. The largest set of pairs
    whose rotation axes agree within :data:`AXIS_AGREEMENT_DEG` and which rotate without
    moving along the axis wins; it needs at least one pair turned more than
    :data:`MIN_TURN_DEG` (two views), more when there are more views.
    """
    names = list(poses)
    mats = [np.asarray(poses[n], float) for n in names]
    motions = []  # (i, j, axis, R, t) of M = T_j T_i^-1: a rotation about the axis line
    for i in range(len(mats)):
        inv_i = np.linalg.inv(mats[i])
        for j in range(i + 1, len(mats)):
            m = mats[j] @ inv_i
            axis, angle = rotation_axis_angle(m[:3, :3])
            if math.degrees(angle) < MIN_TURN_DEG:
                continue
            # a turn about a fixed line moves nothing along it
            if abs(m[:3, 3] @ axis) > max(1.0, 0.05 * np.linalg.norm(m[:3, 3])):
                continue
            motions.append((i, j, axis, m[:3, :3], m[:3, 3]))
    if not motions:
        return None
    axes = np.array([m[2] for m in motions])
    agree = np.abs(axes @ axes.T) > math.cos(math.radians(AXIS_AGREEMENT_DEG))
    best = int(np.argmax(agree.sum(axis=1)))
    inliers = [motions[k] for k in np.flatnonzero(agree[best])]
    views = sorted({m[0] for m in inliers} | {m[1] for m in inliers})
    if len(mats) > 2 and len(views) < 3:
        return None
    # direction: the null vector of the stacked (R - I); point: least squares of (R - I) p = -t
    stack = np.concatenate([m[3] - np.eye(3) for m in inliers])
    direction = np.linalg.svd(stack)[2][-1]
    rhs = -np.concatenate([m[4] for m in inliers])
    point = np.linalg.lstsq(stack, rhs, rcond=None)[0]
    point -= (point @ direction) * direction
    cos = np.clip(np.abs(np.array([m[2] for m in inliers]) @ direction), -1.0, 1.0)
    spread = float(np.sqrt(np.mean(np.degrees(np.arccos(cos)) ** 2)))
    return direction, point, tuple(names[v] for v in views), spread


def object_frame(
    poses: Mapping[str, np.ndarray],
    points: np.ndarray,
    *,
    camera_up: Mapping[str, np.ndarray] | None = None,
    view_directions: Mapping[str, np.ndarray] | None = None,
    reference: str | None = None,
) -> ObjectFrame:
    """The upright object frame of a registered set (see the module docstring).

    poses : {name: (4, 4) reference_from_scan, mm}, at least one
    points : (n, 3) float, the object's surface samples in the reference frame, mm (a
        subsample of the aligned scans is plenty)
    camera_up : {name: (3,) the sensor's up in the scan frame}; default (0, -1, 0) for
        every scan (OpenCV camera axes, y down)
    view_directions : {name: (3,) from the surface towards the sensor, scan frame} (a
        :class:`~slscan.register.rangescan.RangeScan`'s ``view_direction``); default:
        towards the scan frame's origin (a perspective camera's centre)
    reference : the view whose camera faces +Z (default: the first in ``poses``)
    """
    if not poses:
        raise ValueError("object_frame: no poses")
    names = list(poses)
    reference = reference if reference in poses else names[0]
    mats = {n: np.asarray(poses[n], float) for n in names}
    ups = []
    for n in names:
        u = np.asarray((camera_up or {}).get(n, (0.0, -1.0, 0.0)), float)
        ups.append(mats[n][:3, :3] @ (u / np.linalg.norm(u)))
    mean_up = np.mean(ups, axis=0)
    if np.linalg.norm(mean_up) < 1e-6:  # cameras all around in every direction
        mean_up = ups[names.index(reference)]
    mean_up /= np.linalg.norm(mean_up)

    pts = np.asarray(points, float).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    found = turntable_axis(mats) if len(mats) > 1 else None
    up, point, views, spread, tilt = mean_up, None, (), float("nan"), float("nan")
    if found is not None:
        direction, axis_point, axis_views, axis_spread = found
        if direction @ mean_up < 0:
            direction = -direction
        axis_tilt = math.degrees(math.acos(float(np.clip(direction @ mean_up, -1.0, 1.0))))
        if axis_tilt <= MAX_TILT_DEG:
            up, point, views, spread, tilt = direction, axis_point, axis_views, axis_spread, axis_tilt

    # +Z: towards the reference camera, horizontally (from above: its viewing direction)
    centre = pts.mean(axis=0) if len(pts) else np.zeros(3)
    if view_directions is not None and reference in view_directions:
        toward = mats[reference][:3, :3] @ np.asarray(view_directions[reference], float)
    else:
        toward = mats[reference][:3, 3] - (point if point is not None else centre)
    z = toward - (toward @ up) * up
    if np.linalg.norm(z) < 1e-6 * max(1.0, np.linalg.norm(toward)):
        back = -mats[reference][:3, 2]
        z = back - (back @ up) * up
    if np.linalg.norm(z) < 1e-9:  # degenerate: any horizontal direction
        z = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 0.0, 1.0])
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    rotation = np.stack([x, up, z])  # rows: the object axes in the reference frame

    heights = pts @ up if len(pts) else np.zeros(1)
    base = float(np.percentile(heights, BASE_PERCENTILE))
    if point is None:  # no axis: the middle of the object's horizontal extent
        flat = pts - np.outer(heights, up) if len(pts) else np.zeros((1, 3))
        lo, hi = (flat @ rotation.T).min(axis=0), (flat @ rotation.T).max(axis=0)
        point = rotation.T @ ((lo + hi) / 2.0)
    origin = point - (point @ up) * up + base * up
    frame = np.eye(4)
    frame[:3, :3] = rotation
    frame[:3, 3] = -rotation @ origin
    return ObjectFrame(frame, "turntable" if views else "cameras", views, spread, tilt)


def sample_points(scans: Sequence, poses: Mapping[str, np.ndarray], *, count: int = 50_000,
                  seed: int = 0) -> np.ndarray:
    """(≤ count, 3) vertices of ``scans`` (with ``name``, ``vertices``) under their poses."""
    rng = np.random.default_rng(seed)
    chosen = [s for s in scans if s.name in poses]
    total = sum(len(s.vertices) for s in chosen)
    out = []
    for s in chosen:
        v = np.asarray(s.vertices, float)
        if total > count:
            v = v[rng.random(len(v)) < count / total]
        pose = np.asarray(poses[s.name], float)
        out.append(v @ pose[:3, :3].T + pose[:3, 3])
    return np.concatenate(out) if out else np.zeros((0, 3))


def to_object_frame(scans: Sequence, result) -> tuple[Any, ObjectFrame]:
    """A registration ``result`` (a :class:`~slscan.register.multiview.MultiviewResult`) with
    its poses moved into the upright object frame, and that frame.

    scans : the registered :class:`~slscan.register.rangescan.RangeScan` objects (their
        vertices place the base, their ``up_direction`` the sign of +Y)
    """
    from dataclasses import replace

    frame = object_frame(
        result.poses, sample_points(scans, result.poses),
        camera_up={s.name: s.up_direction for s in scans},
        view_directions={s.name: s.view_direction for s in scans}, reference=result.reference,
    )
    return replace(result, poses=frame.apply(result.poses)), frame


def preview_frame(scans: Sequence, poses: Mapping[str, np.ndarray] | None) -> ObjectFrame | None:
    """The object frame of the starting poses (None without them): to show the scans
    upright before registration has run."""
    if not poses:
        return None
    return object_frame(poses, sample_points(scans, poses, count=10_000),
                        camera_up={s.name: s.up_direction for s in scans},
                        view_directions={s.name: s.view_direction for s in scans})


def read_frame(path) -> ObjectFrame | None:
    """The object frame recorded in a ``registration.json`` (None when it records none: a
    registration written before the object frame existed)."""
    from slscan.errors import SlscanError
    from slscan.fsio import read_json

    entry = read_json(path, "registration result").get("frame")
    if entry is None:
        return None
    try:
        matrix = np.asarray(entry["object_from_reference"], float).reshape(4, 4)
        return ObjectFrame(matrix, str(entry["up_from"]), tuple(entry.get("turntable_views", ())),
                           float(entry.get("axis_spread_deg") or float("nan")),
                           float(entry.get("tilt_deg") or float("nan")))
    except (KeyError, TypeError, ValueError):
        raise SlscanError(f"{path}: 'frame' needs 'object_from_reference' (4x4) and 'up_from'") from None
