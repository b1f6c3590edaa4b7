"""Where a scene stands on the virtual rig's turntable: the units of a mesh file and the
object's pose, given on the command line or in a recipe.

The **turntable frame** is the rig frame moved to the turntable's centre: origin on the
camera axis at the working distance (1300 mm by default), axes parallel to the rig's
(x right, y down: the turntable axis, z away from the camera), mm. A scene's
**placement** is ``turntable_from_object`` (4, 4): where its object frame (a mesh file's
own coordinates, in mm after its units) stands on the turntable. View ``k`` of ``n``
turns the turntable by ``360 k / n`` degrees about its axis, so each view records

    rig_from_object = translate(0, 0, working_distance) · rotate_y(360 k / n) · placement

— the exact transform from the mesh file's coordinates (mm) to the rig frame.

**Default placement** of a mesh file (what ``--scene-pose`` left out does): turned 180°
about x, so that the file's +y (up in glTF and the Stanford scans) points up in the rig
(rig −y) and its +z (glTF's front) faces the camera (rig −z), and moved so that the
centre of its bounding box is the turntable's centre. The built-in scenes are modelled in
place (centred, y down, front towards the camera): their default placement is the
identity.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.rig import rotation_about_axis

UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
"""Millimetres per unit of a mesh file, by unit name."""

AUTO_METRES_BELOW = 10.0
"""``units = "auto"``: a mesh less than this many units across is taken to be in metres."""

POSE_SUFFIXES = (".json", ".txt")

FLIP_Y_Z = np.diag([1.0, -1.0, -1.0, 1.0])
"""The default placement's turn: 180° about x (a y-up, front +z file to the rig's y down,
front towards the camera)."""


def parse_units(value: str | float | None, what: str = "scene_units") -> float | None:
    """Millimetres per file unit for ``value``: a unit name {"mm", "cm", "m", "in"}, a
    positive number (mm per unit, e.g. 25.4), or None / "auto" (None: decide by size)."""
    if value is None or (isinstance(value, str) and value.strip().lower() == "auto"):
        return None
    if isinstance(value, str):
        text = value.strip().lower()
        if text in UNITS:
            return UNITS[text]
        try:
            number = float(text)
        except ValueError:
            raise SlscanError(f"{what}: unknown units {value!r}; expected auto, {', '.join(UNITS)} "
                              "or a number of mm per unit (e.g. 25.4)") from None
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        number = float(value)
    else:
        raise SlscanError(f"{what}: expected a unit name or a number of mm per unit, got {value!r}")
    if not (math.isfinite(number) and number > 0):
        raise SlscanError(f"{what}: mm per unit must be a positive number, got {value!r}")
    return number


def pose_from_euler(rx: float, ry: float, rz: float, tx: float, ty: float, tz: float) -> np.ndarray:
    """``turntable_from_object`` (4, 4): turn by ``rx`` about x, then ``ry`` about y, then
    ``rz`` about z (degrees, about the fixed turntable axes: R = Rz · Ry · Rx), then move by
    ``(tx, ty, tz)`` mm."""
    r = (rotation_about_axis([0, 0, 1], math.radians(rz)) @ rotation_about_axis([0, 1, 0], math.radians(ry))
         @ rotation_about_axis([1, 0, 0], math.radians(rx)))
    pose = np.eye(4)
    pose[:3, :3] = r
    pose[:3, 3] = [tx, ty, tz]
    return pose


def is_pose_file(text: str) -> bool:
    return Path(text.strip()).suffix.lower() in POSE_SUFFIXES


def check_pose_text(text: str | None, what: str = "scene_pose") -> None:
    """Refuse a malformed pose given as text, without reading a pose file (see :func:`parse_pose`)."""
    if text is None or is_pose_file(text) or text.strip().lower() == "default":
        return
    _euler(text, what)


def _euler(text: str, what: str) -> np.ndarray:
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise SlscanError(f"{what}: expected \"rx,ry,rz,tx,ty,tz\" (degrees, mm), a 4x4 matrix file "
                          f"(.json or .txt) or \"default\", got {text!r}")
    return pose_from_euler(*values)


def rigid(matrix, what: str) -> np.ndarray:
    """``matrix`` as a (4, 4) float64 rigid transform, or an error naming ``what``."""
    try:
        pose = np.asarray(matrix, dtype=float)
    except (TypeError, ValueError):
        raise SlscanError(f"{what}: expected a 4x4 matrix of numbers") from None
    if pose.shape != (4, 4):
        raise SlscanError(f"{what}: expected a 4x4 matrix, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)) or not np.allclose(pose[3], [0, 0, 0, 1]):
        raise SlscanError(f"{what}: the last row of a rigid transform must be 0 0 0 1")
    r = pose[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise SlscanError(f"{what}: the 3x3 part is not a rotation (no scale or mirror: units set the scale)")
    return pose


def load_pose_file(path: str | os.PathLike) -> np.ndarray:
    """A 4×4 ``turntable_from_object`` from a file: ``.txt``, four rows of four numbers
    (as MeshLab's "Apply matrix" takes); ``.json``, a 4×4 list, or an object with a
    ``turntable_from_object`` 4×4 list (what ``session.json`` records under
    ``device.scene_placement``)."""
    path = Path(path)
    if not path.is_file():
        raise SlscanError(f"{path}: pose file not found")
    if path.suffix.lower() == ".txt":
        try:
            matrix = np.loadtxt(path, dtype=float, ndmin=2)
        except ValueError as exc:
            raise SlscanError(f"{path}: expected 4 rows of 4 numbers ({exc})") from None
    else:
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise SlscanError(f"{path}: not valid JSON ({exc})") from None
        matrix = data.get("turntable_from_object") if isinstance(data, dict) else data
        if matrix is None:
            raise SlscanError(f"{path}: expected a 4x4 list or an object with \"turntable_from_object\"")
    return rigid(matrix, str(path))


def parse_pose(text: str | None, what: str = "scene_pose") -> np.ndarray | None:
    """``turntable_from_object`` (4, 4) for a pose given as text, or None for the default
    placement: ``"rx,ry,rz,tx,ty,tz"`` (see :func:`pose_from_euler`), a ``.json`` or
    ``.txt`` file (see :func:`load_pose_file`), or ``"default"``."""
    if text is None or text.strip().lower() == "default":
        return None
    if is_pose_file(text):
        return load_pose_file(text.strip())
    return _euler(text, what)


def default_placement(vertices: np.ndarray) -> np.ndarray:
    """The default ``turntable_from_object`` of a mesh file with ``vertices`` (n, 3) mm:
    turned 180° about x (y up and front +z to the rig's y down, front to the camera), the
    bounding box's centre on the turntable's centre."""
    centre = (vertices.max(axis=0) + vertices.min(axis=0)) / 2
    pose = FLIP_Y_Z.copy()
    pose[:3, 3] = -pose[:3, :3] @ centre
    return pose


def placement_record(placement: np.ndarray | None, mm_per_unit: float, explicit: bool) -> dict:
    """What a session records of a scene's placement (``session.json``, ``device``)."""
    return {
        "turntable_from_object": (np.eye(4) if placement is None else placement).tolist(),
        "mm_per_unit": mm_per_unit,
        "pose": "given" if explicit else "default",
    }
