"""Calibrations that other tools publish, read into slscan's conventions.

One reader per format, each returning an :class:`ImportedCalibration` (the camera's lens,
the second device's lens and pose, the files, the units), which converts to slscan's
:class:`~slscan.calibrate.io.Calibration` (camera + projector) or to the two
:class:`~slscan.capture.multicam.CameraEntry` of a ``cameras.json`` (two cameras):

- :func:`read_opencv`: OpenCV FileStorage XML, YAML or JSON with any key names (a
  :class:`KeyMap`), the common layouts recognised: kamino410/procam-calibration,
  OpenCV stereo (``M1 D1 M2 D2 R T``), single-device files (``camera_matrix``, ``K``);
- :func:`read_bouguet`: Bouguet's Camera Calibration Toolbox ``Calib_Results_stereo.m``
  (and Moreno & Taubin's procam tool's file of the same form);
- :func:`read_text`: plain-text K / dist / R / T matrices, labelled or bare;
- :func:`read_3dunderworld`: 3DUNDERWORLD-SLS's per-camera ``calib.xml`` or its folder of
  ``cam_matrix.txt`` ... text files; two of them make a stereo pair.

Every reader names the file and the key it could not use: missing, wrong size, not a
number, a rotation that is not one, distortion terms slscan's lens model lacks.
Conventions are slscan's (``slscan.rig``): mm, poses ``a_from_b``, distortion
``(k1, k2, p1, p2, k3)``, pixel centres at integers. Details: ``docs/calibration.md``,
section "Importing another tool's calibration".

References
----------
- J.-Y. Bouguet. Camera Calibration Toolbox for Matlab (calib_doc, "Description of the
  calibration parameters"): pixel [0; 0] is the centre of the upper-left pixel;
  ``kc = [k1; k2; p1; p2; k3]``; in a stereo result ``XR = R * XL + T``, ``R = rodrigues(om)``.
- OpenCV ``stereoCalibrate``: ``R, T`` take points of the first camera to the second's.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from slscan.calibrate.options import IMPORT_FORMATS as FORMATS
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, Projector

if TYPE_CHECKING:
    from slscan.calibrate.io import Calibration
    from slscan.capture.multicam import CameraEntry
    from slscan.capture.session import Session

ROTATION_TOLERANCE = 1e-3
"""Largest |R·Rᵀ − I| entry orthonormalised away; a matrix further off is refused."""

# user words of a key map's direction -> what R, T map (x_to = R x_from + T)
DIRECTIONS = {
    "camera-to-projector": "camera-to-second",
    "projector-to-camera": "second-to-camera",
    "camera-to-camera2": "camera-to-second",
    "camera2-to-camera": "second-to-camera",
    "world-to-camera": "world-to-camera",
    "camera-to-world": "camera-to-world",
}
_DIST_COUNTS = (4, 5, 8, 12, 14)


# --- key maps ---------------------------------------------------------------------------


@dataclass(frozen=True)
class KeyMap:
    """Which keys of a file hold what.

    Each field names a key; ``"roration|rotation"`` lists alternatives (the first present
    is used), a trailing ``?`` makes it optional, ``"image_width+image_height"`` reads a
    size from two scalars. Keys of nested maps are written ``"Camera/Matrix"``.

    camera, camera_dist : the camera's 3×3 matrix (px) and distortion (OpenCV order)
    camera_size, camera_shape : its image size as (width, height) or as (rows, cols), px
    second, second_dist, second_size, second_shape : the same for the second device
    second_kind : {"projector", "camera"}, or None where the layout does not say
    rotation : 3×3 matrix or Rodrigues 3-vector; translation : 3-vector, file units
    direction : what ``x_to = R·x_from + T`` maps: {"camera-to-second",
        "second-to-camera"} between the two devices, {"world-to-camera",
        "camera-to-world"} for one device's extrinsics (the board's pose)
    rms : the tool's reprojection RMS, px (informative)
    name : the layout's name, in messages and in the written calibration's source
    """

    camera: str
    camera_dist: str | None = None
    camera_size: str | None = None
    camera_shape: str | None = None
    second: str | None = None
    second_dist: str | None = None
    second_size: str | None = None
    second_shape: str | None = None
    second_kind: str | None = None
    rotation: str | None = None
    translation: str | None = None
    direction: str = "camera-to-second"
    rms: str | None = None
    name: str = "key map"


KAMINO410 = KeyMap(
    name="kamino410",
    camera="cam_int",
    camera_dist="cam_dist",
    camera_shape="img_shape?",
    second="proj_int",
    second_dist="proj_dist",
    second_kind="projector",
    rotation="roration|rotation",
    translation="translation",
    rms="rms?",
)
OPENCV_STEREO = KeyMap(
    name="opencv-stereo",
    camera="M1|K1|cameraMatrix1",
    camera_dist="D1|distCoeffs1",
    camera_size="imageSize|image_size|image_width+image_height?",
    second="M2|K2|cameraMatrix2",
    second_dist="D2|distCoeffs2",
    second_size="imageSize|image_size|image_width+image_height?",
    second_kind="camera",
    rotation="R",
    translation="T",
    rms="rms|stereo_rms?",
)
THREEDUNDERWORLD = KeyMap(
    name="3dunderworld",
    camera="Camera/Matrix",
    camera_dist="Camera/Distortion",
    camera_size="Camera/Width+Camera/Height?",
    rotation="Camera/Rotation",
    translation="Camera/Translation",
    direction="world-to-camera",
)
THREEDUNDERWORLD_TEXT = KeyMap(
    name="3dunderworld (text files)",
    camera="cam_matrix.txt",
    camera_dist="cam_distortion.txt",
    rotation="cam_rotation_matrix.txt",
    translation="cam_trans_vectror.txt|cam_trans_vector.txt",
    direction="world-to-camera",
)
OPENCV_SINGLE = KeyMap(
    name="opencv-single",
    camera="camera_matrix|cameraMatrix|K|M|intrinsic|intrinsics",
    camera_dist="distortion_coefficients|dist_coeffs|distCoeffs|distortion|D|dist?",
    camera_size="image_width+image_height|imageSize|image_size?",
    rotation="R|rotation|rvec?",
    translation="T|translation|tvec?",
    direction="world-to-camera",
)
OPENCV_LAYOUTS = (KAMINO410, OPENCV_STEREO, THREEDUNDERWORLD, OPENCV_SINGLE)

TEXT_PROCAM = KeyMap(
    name="text camera+projector",
    camera="k_cam|k_camera",
    camera_dist="d_cam|dist_cam|dist_camera?",
    camera_size="size_cam|size_camera?",
    second="k_proj|k_projector",
    second_dist="d_proj|dist_proj|dist_projector?",
    second_size="size_proj|size_projector?",
    second_kind="projector",
    rotation="r|rotation|om",
    translation="t|translation",
)
TEXT_STEREO = KeyMap(
    name="text stereo",
    camera="k1|m1",
    camera_dist="d1|dist1?",
    camera_size="size1?",
    second="k2|m2",
    second_dist="d2|dist2?",
    second_size="size2?",
    second_kind="camera",
    rotation="r|rotation|om",
    translation="t|translation",
)
TEXT_SINGLE = KeyMap(
    name="text single device",
    camera="k|camera_matrix|intrinsics|a|m",
    camera_dist="dist|d|distortion|distortion_coefficients|kc?",
    camera_size="size|image_size?",
    rotation="r|rotation|om|rvec?",
    translation="t|translation|tvec?",
    direction="world-to-camera",
)
TEXT_LAYOUTS = (TEXT_PROCAM, TEXT_STEREO, TEXT_SINGLE)

_ROLES = {  # --keys word -> (KeyMap field, second device kind or None)
    "camera": ("camera", None),
    "camera_dist": ("camera_dist", None),
    "camera_size": ("camera_size", None),
    "camera_shape": ("camera_shape", None),
    "rotation": ("rotation", None),
    "translation": ("translation", None),
    "rms": ("rms", None),
    **{
        f"{kind}{suffix}": (f"second{suffix}", word)
        for kind, word in (("projector", "projector"), ("camera2", "camera"))
        for suffix in ("", "_dist", "_size", "_shape")
    },
}


def parse_keys(text: str) -> KeyMap:
    """A :class:`KeyMap` from ``--keys`` text: ``role=KEY`` items separated by commas.

    Roles: ``camera``, ``camera_dist``, ``camera_size``, ``camera_shape``, ``projector``
    (or ``camera2``) with the same suffixes, ``rotation``, ``translation``, ``rms`` and
    ``direction`` (one of :data:`DIRECTIONS`). Without ``direction``: R, T take camera
    points to the second device's, or, with one device, world (board) points to the
    camera's.
    """
    fields: dict[str, str] = {}
    kinds: set[str] = set()
    direction = None
    for item in filter(None, (part.strip() for part in text.split(","))):
        role, sep, key = (s.strip() for s in item.partition("="))
        if not sep or not key:
            raise SlscanError(f"--keys: {item!r} is not ROLE=KEY (e.g. camera=cam_int)")
        if role == "direction":
            if key not in DIRECTIONS:
                raise SlscanError(
                    f"--keys: direction {key!r} is not one of {', '.join(DIRECTIONS)}"
                )
            direction = key
            continue
        if role not in _ROLES:
            raise SlscanError(
                f"--keys: unknown role {role!r}; expected direction or one of {', '.join(_ROLES)}"
            )
        name, kind = _ROLES[role]
        if kind is not None:
            kinds.add(kind)
        if len(kinds) > 1:
            raise SlscanError("--keys: name a projector or a second camera (camera2), not both")
        if name in fields:
            raise SlscanError(f"--keys: {role!r} is named twice")
        fields[name] = key
    if "camera" not in fields:
        raise SlscanError("--keys: name the camera's matrix (camera=KEY)")
    kind = kinds.pop() if kinds else None
    if kind is None:
        if direction is None:
            direction = "world-to-camera"
        elif DIRECTIONS[direction] in ("camera-to-second", "second-to-camera"):
            raise SlscanError(
                f"--keys: direction {direction} names a second device the key map does not"
            )
    else:
        role = "projector" if kind == "projector" else "camera2"
        if "second" not in fields:
            raise SlscanError(f"--keys: name the {kind}'s matrix ({role}=KEY)")
        expected = (f"camera-to-{role}", f"{role}-to-camera")
        if direction is None:
            direction = expected[0]
        elif direction not in expected:
            raise SlscanError(
                f"--keys: direction {direction} does not fit a key map with {role}; expected "
                f"{' or '.join(expected)}"
            )
    return KeyMap(**fields, second_kind=kind, direction=DIRECTIONS[direction], name="key map")


# --- results ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ImportedLens:
    """One device's intrinsics as a file gave them.

    K : (3, 3) float64, px; dist : (5,) OpenCV ``(k1, k2, p1, p2, k3)``
    size : (width, height) px when the file says, else None
    file, key : where the matrix came from; size_key : where the size came from
    """

    K: np.ndarray
    dist: tuple[float, float, float, float, float]
    size: tuple[int, int] | None
    file: Path
    key: str
    size_key: str | None = None

    def lens(self, size: tuple[int, int], *, scale: float = 1.0) -> PinholeModel:
        """The :class:`PinholeModel` on a ``size`` (width, height) px sensor, its focal
        lengths and principal point multiplied by ``scale``."""
        k = self.K
        try:
            return PinholeModel(
                int(size[0]),
                int(size[1]),
                float(k[0, 0] * scale),
                float(k[1, 1] * scale),
                float(k[0, 2] * scale),
                float(k[1, 2] * scale),
                self.dist,
            )
        except SlscanError as exc:  # e.g. scaled to a sensor size the file's values overflow on
            raise SlscanError(f"{self.file}: key {self.key!r}: {exc}") from None


@dataclass(frozen=True, eq=False)
class ImportedCalibration:
    """What a reader found, in slscan's conventions.

    files : the file(s) read; format : {"opencv", "bouguet", "text", "3dunderworld"}
    layout : the layout recognised (e.g. "kamino410") or "key map"
    camera : the first device, always a camera; its frame is the rig frame
    second : the projector or the second camera, or None (a single-device file)
    second_kind : {"projector", "camera"}, or None where the file does not say
    camera_from_second : (4, 4) float64 mm, the second device's pose, or None
    camera_from_world : (4, 4) float64 mm, a single device's extrinsics (the board it was
        calibrated on, as 3DUNDERWORLD writes them), or None
    units_mm : mm per unit of the file's translations (already applied to the poses)
    rms_px : the tool's reprojection RMS, px, if the file gives it
    """

    files: tuple[Path, ...]
    format: str
    layout: str
    camera: ImportedLens
    second: ImportedLens | None = None
    second_kind: str | None = None
    camera_from_second: np.ndarray | None = None
    camera_from_world: np.ndarray | None = None
    units_mm: float = 1.0
    rms_px: float | None = None

    @property
    def where(self) -> str:
        return ", ".join(str(f) for f in self.files)

    def _require_pair(self, purpose: str) -> tuple[ImportedLens, np.ndarray]:
        if self.second is None or self.camera_from_second is None:
            raise SlscanError(
                f"{self.where}: holds one device ({self.layout}, key {self.camera.key!r}); {purpose} "
                "needs two: give the second device's file too"
            )
        return self.second, self.camera_from_second

    def source(self, **extra) -> dict:
        """JSON-ready record of where the calibration came from."""
        return {
            "imported_from": self.where,
            "format": self.format,
            "layout": self.layout,
            "units_mm": self.units_mm,
            **extra,
        }

    def to_calibration(
        self,
        *,
        camera_size: tuple[int, int] | None = None,
        projector_size: tuple[int, int] | None = None,
        projector_scale: float = 1.0,
        session: Session | None = None,
    ) -> Calibration:
        """slscan's :class:`~slscan.calibrate.io.Calibration`, the second device as the
        projector (an inverse camera).

        camera_size, projector_size : (width, height) px (``--camera-size``,
            ``--projector-size``); needed where the file does not say, and where it does
            they must agree, as must a ``session``'s camera and projector sizes
        projector_scale : pattern pixels per projector pixel of the file (0.5 for
            procam-calibration's ``graycode_step`` 2)

        Raises SlscanError naming the file and key, and both sizes, at a mismatch.
        """
        from slscan.calibrate.io import Calibration

        second, pose = self._require_pair("a camera + projector calibration")
        meta = None if session is None else session.root / "session.json"
        cam_size = agree_size(
            "camera",
            self.camera,
            ("--camera-size", camera_size),
            (f"{meta}: key 'camera'", None if session is None else session.camera_size),
        )
        file_size = second.size
        if file_size is not None and projector_scale != 1.0:
            file_size = (
                round(file_size[0] * projector_scale),
                round(file_size[1] * projector_scale),
            )
        proj_size = agree_size(
            "projector",
            dataclasses.replace(second, size=file_size),
            ("--projector-size", projector_size),
            (f"{meta}: key 'projector'", None if session is None else session.projector_size),
        )
        projector = Projector(second.lens(proj_size, scale=projector_scale), pose)
        return Calibration(
            camera=self.camera.lens(cam_size),
            projector_size=proj_size,
            projector=projector,
            residuals={} if self.rms_px is None else {"imported": {"stereo_rms_px": self.rms_px}},
            source=self.source(projector_scale=projector_scale),
        )

    def to_cameras(
        self,
        *,
        sizes: Sequence[tuple[int, int] | None] = (None, None),
        sessions: Sequence[Session] | None = None,
        names: Sequence[str] = ("cam0", "cam1"),
        folders: Sequence[str] | None = None,
    ) -> tuple[CameraEntry, CameraEntry]:
        """The two :class:`~slscan.capture.multicam.CameraEntry` of a ``cameras.json``,
        camera 0's frame the common one (its pose the identity).

        sizes : each camera's (width, height) px (``--camera-size``), needed where the file
            does not say; where it does they must agree, as must each camera's session
        names, folders : the entries' names and session folders (default: the names)
        """
        from slscan.capture.multicam import CameraEntry

        second, pose = self._require_pair("a stereo pair")
        folders = tuple(names) if folders is None else tuple(folders)
        lenses = []
        for i, lens in enumerate((self.camera, second)):
            session = None if sessions is None else sessions[i]
            size = agree_size(
                "camera",
                lens,
                ("--camera-size", sizes[i]),
                (f"{session.root / 'session.json'}: key 'camera'", session.camera_size)
                if session is not None
                else ("", None),
            )
            lenses.append(lens.lens(size))
        return (
            CameraEntry(names[0], folders[0], lenses[0], np.eye(4)),
            CameraEntry(names[1], folders[1], lenses[1], pose.copy()),
        )


def agree_size(
    what: str, lens: ImportedLens, *given: tuple[str, tuple[int, int] | None]
) -> tuple[int, int]:
    """The (width, height) px that the file's size key and each ``(label, size)`` given agree
    on; SlscanError naming the two that differ (file and key, and the other's label and
    size), or the file when nobody gives one."""
    known = [(f"{lens.file}: key {lens.size_key!r}", lens.size)] if lens.size is not None else []
    known += [(label, tuple(int(v) for v in size)) for label, size in given if size is not None]
    if not known:
        raise SlscanError(
            f"{lens.file}: the file gives no {what} image size (for key {lens.key!r}); "
            f"pass --{what}-size WxH or --session"
        )
    label0, size0 = known[0]
    for label, size in known[1:]:
        if size != size0:
            raise SlscanError(
                f"{label0} says the {what} is {size0[0]}x{size0[1]} px, {label} says {size[0]}x{size[1]}"
            )
    return size0


def rigid_inverse(pose: np.ndarray) -> np.ndarray:
    """The inverse (4, 4) of a rigid ``pose``, exactly: ``[Rᵀ | −Rᵀ t]``."""
    inv = np.eye(4)
    inv[:3, :3] = pose[:3, :3].T
    inv[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return inv


# --- shared checks on matrices ----------------------------------------------------------


def _count(n: int, counts: Sequence[int]) -> str:
    return " or ".join(str(c) for c in counts) + f" values, got {n}"


def numbers(value: object, file: Path, key: str, counts: Sequence[int]) -> np.ndarray:
    """``value`` as a flat float64 array of one of ``counts`` finite numbers, else
    SlscanError naming ``file`` and ``key``."""
    if isinstance(value, str) or value is None:
        shown = f" ({value[:60]!r})" if isinstance(value, str) else ""
        raise SlscanError(f"{file}: key {key!r} is not a list of numbers{shown}")
    arr = np.asarray(value, float).reshape(-1)
    if arr.size not in counts:
        raise SlscanError(
            f"{file}: key {key!r} has the wrong size: expected {_count(arr.size, counts)}"
        )
    if not np.isfinite(arr).all():
        raise SlscanError(f"{file}: key {key!r} holds non-finite numbers (NaN or inf)")
    return arr


def camera_matrix(value: object, file: Path, key: str) -> np.ndarray:
    """A 3×3 pinhole matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (row-major values)."""
    k = numbers(value, file, key, (9,)).reshape(3, 3)
    if k[2, 2] == 0 or k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0:
        raise SlscanError(
            f"{file}: key {key!r} is not a camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"
        )
    k = k / k[2, 2]
    if not (k[0, 0] > 0 and k[1, 1] > 0):
        raise SlscanError(
            f"{file}: key {key!r}: focal lengths must be positive (fx {k[0, 0]}, fy {k[1, 1]})"
        )
    if abs(k[0, 1]) > 1e-9 * k[0, 0]:
        raise SlscanError(
            f"{file}: key {key!r} has a skew of {k[0, 1]:g} px; slscan's lens model has none"
        )
    k[0, 1] = 0.0
    return k


def distortion(value: object, file: Path, key: str) -> tuple[float, float, float, float, float]:
    """OpenCV distortion (4, 5, 8, 12 or 14 values) as ``(k1, k2, p1, p2, k3)``.

    Terms beyond k3 (rational k4–k6, thin prism s1–s4, tilt) must be zero: slscan's lens
    model does not have them, and dropping them would move every pixel silently.
    """
    d = numbers(value, file, key, _DIST_COUNTS)
    if np.any(d[5:] != 0):
        raise SlscanError(
            f"{file}: key {key!r} has non-zero terms beyond k3 ({', '.join(f'{v:g}' for v in d[5:])}): "
            "slscan's lens model is k1 k2 p1 p2 k3 only; recalibrate without the rational, "
            "thin-prism and tilt terms"
        )
    out = np.zeros(5)
    out[: min(5, d.size)] = d[:5]
    return tuple(float(v) for v in out)


def rotation(value: object, file: Path, key: str) -> np.ndarray:
    """A 3×3 rotation from 9 values (row-major) or a Rodrigues 3-vector (rad).

    Orthonormalised when within :data:`ROTATION_TOLERANCE` of a rotation; else refused.
    """
    v = numbers(value, file, key, (3, 9))
    if v.size == 3:
        angle = float(np.linalg.norm(v))
        if not angle < 1e6:  # cv2.Rodrigues gives NaN or garbage (1e308 rad: norm overflows)
            raise SlscanError(f"{file}: key {key!r} is a rotation vector of {angle:.4g} rad; expected an angle "
                              "of a few radians")
        r = cv2.Rodrigues(v.reshape(3, 1))[0]
    else:
        r = v.reshape(3, 3)
    off = float(np.abs(r @ r.T - np.eye(3)).max())
    det = float(np.linalg.det(r))
    if off > ROTATION_TOLERANCE or det <= 0:
        raise SlscanError(
            f"{file}: key {key!r} is not a rotation (R·Rᵀ differs from I by {off:.2g}, "
            f"det {det:.4g}); expected an orthonormal matrix with det +1"
        )
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def image_size(value: object, file: Path, key: str, *, rows_cols: bool = False) -> tuple[int, int]:
    """(width, height) px from two whole positive numbers, (width, height) or (rows, cols)."""
    v = numbers(value, file, key, (2,))
    if np.any(v <= 0) or np.any(v != np.round(v)):
        raise SlscanError(f"{file}: key {key!r} is not an image size (two whole numbers of pixels)")
    w, h = (int(v[1]), int(v[0])) if rows_cols else (int(v[0]), int(v[1]))
    return w, h


def _pose(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = r, t
    return pose


def _check_units(units_mm: float) -> float:
    if not (np.isfinite(units_mm) and units_mm > 0):
        raise SlscanError(
            f"--units-mm: expected a positive number of mm per file unit, got {units_mm}"
        )
    return float(units_mm)


# --- files as keyed values --------------------------------------------------------------


@dataclass(frozen=True)
class _Values:
    """The values of one or two files by key (lower-case keys when ``fold_case``)."""

    files: tuple[Path, ...]
    values: dict[str, list[tuple[Path, object]]]
    fold_case: bool = False

    @classmethod
    def of(cls, pairs: Sequence[tuple[Path, dict]], fold_case: bool = False) -> _Values:
        values: dict[str, list[tuple[Path, object]]] = {}
        for file, d in pairs:
            for key, value in d.items():
                values.setdefault(key.lower() if fold_case else key, []).append((file, value))
        return cls(tuple(f for f, _ in pairs), values, fold_case)

    @property
    def where(self) -> str:
        return ", ".join(str(f) for f in self.files)

    def _hit(self, key: str) -> list[tuple[Path, object]] | None:
        return self.values.get(key.lower() if self.fold_case else key)

    def has(self, spec: str | None) -> bool:
        return spec is not None and any(
            all(self._hit(part) for part in alt.split("+")) for alt in spec.rstrip("?").split("|")
        )

    def find(self, spec: str | None) -> tuple[str, Path, object] | None:
        """The first alternative of ``spec`` present: (key, file, value); a ``W+H`` pair
        gives both scalars as one value. Raises when the key is in both files; when a
        required key is missing, naming it. None for an absent optional key or spec."""
        if spec is None:
            return None
        optional = spec.endswith("?")
        alts = spec.rstrip("?").split("|")
        for alt in alts:
            parts = alt.split("+")
            hits = [self._hit(part) for part in parts]
            if not all(hits):
                continue
            for part, hit in zip(parts, hits):
                if len(hit) > 1:
                    raise SlscanError(
                        f"{hit[0][0]}: key {part!r} is also in {hit[1][0]}; expected it in one file"
                    )
            if len(parts) == 1:
                return alt, hits[0][0][0], hits[0][0][1]
            value = [numbers(h[0][1], h[0][0], p, (1,))[0] for p, h in zip(parts, hits)]
            return alt, hits[0][0][0], value
        if optional:
            return None
        others = f" (or {', '.join(repr(a) for a in alts[1:])})" if len(alts) > 1 else ""
        raise SlscanError(f"{self.where}: missing key {alts[0]!r}{others}")


def _lens(
    values: _Values, matrix: str, dist: str | None, size: str | None, shape: str | None
) -> ImportedLens:
    key, file, value = values.find(matrix)
    k = camera_matrix(value, file, key)
    d = (0.0,) * 5
    hit = values.find(dist)
    if hit is not None:
        d = distortion(hit[2], hit[1], hit[0])
    found, size_key = None, None
    for spec, rows_cols in ((size, False), (shape, True)):
        hit = values.find(spec)
        if hit is not None and found is None:
            found, size_key = image_size(hit[2], hit[1], hit[0], rows_cols=rows_cols), hit[0]
    return ImportedLens(k, d, found, file, key, size_key)


def _from_keys(
    values: _Values, keys: KeyMap, *, format: str, units_mm: float
) -> ImportedCalibration:
    """Build an :class:`ImportedCalibration` from ``values`` as ``keys`` says."""
    camera = _lens(values, keys.camera, keys.camera_dist, keys.camera_size, keys.camera_shape)
    second = None
    if keys.second is not None:
        second = _lens(values, keys.second, keys.second_dist, keys.second_size, keys.second_shape)
    pose = None
    if second is not None and (keys.rotation is None or keys.translation is None):
        raise SlscanError(
            f"{values.where}: the key map names no rotation and translation for the second device"
        )
    r_hit, t_hit = values.find(keys.rotation), values.find(keys.translation)
    if (r_hit is None) != (t_hit is None):
        missing = keys.rotation if r_hit is None else keys.translation
        raise SlscanError(
            f"{values.where}: missing key {missing.rstrip('?').split('|')[0]!r} "
            "(a pose needs both rotation and translation)"
        )
    if r_hit is not None:
        r = rotation(r_hit[2], r_hit[1], r_hit[0])
        t = numbers(t_hit[2], t_hit[1], t_hit[0], (3,)) * units_mm
        pose = _pose(r, t)
    camera_from_second = camera_from_world = None
    if pose is not None:
        if keys.direction == "camera-to-second":
            camera_from_second = rigid_inverse(pose)
        elif keys.direction == "second-to-camera":
            camera_from_second = pose
        elif keys.direction == "world-to-camera":
            camera_from_world = pose
        else:
            camera_from_world = rigid_inverse(pose)
        if second is None and camera_from_second is not None:
            raise SlscanError(
                f"{values.where}: direction {keys.direction} needs a second device in the key map"
            )
        if second is not None and camera_from_second is None:
            raise SlscanError(
                f"{values.where}: direction {keys.direction} is for one device; the key map names two"
            )
    rms = None
    hit = values.find(keys.rms)
    if hit is not None:
        rms = float(numbers(hit[2], hit[1], hit[0], (1,))[0])
    return ImportedCalibration(
        files=values.files,
        format=format,
        layout=keys.name,
        camera=camera,
        second=second,
        second_kind=keys.second_kind if second is not None else None,
        camera_from_second=camera_from_second,
        camera_from_world=camera_from_world,
        units_mm=units_mm,
        rms_px=rms,
    )


def _detect(values: _Values, layouts: Sequence[KeyMap], two: bool) -> KeyMap | None:
    """The first layout (with two devices or one) whose matrices are all in ``values``;
    its other keys are then read by name, so a missing one is reported by name."""
    for keys in layouts:
        if (keys.second is not None) == two and all(
            values.has(s) for s in (keys.camera, keys.second) if s is not None
        ):
            return keys
    return None


def pair_devices(
    first: ImportedCalibration, second: ImportedCalibration, *, second_kind: str | None = None
) -> ImportedCalibration:
    """Two single-device results as one pair, camera 0 = ``first``.

    Each file's extrinsics are its device's pose relative to one world (the board both
    saw): ``camera_from_second = camera_from_world · (second_from_world)⁻¹``. A first file
    without extrinsics is the world itself (then the second's R, T take camera points
    to its own).
    """
    for part in (first, second):
        if part.second is not None:
            raise SlscanError(
                f"{part.where}: holds two devices ({part.layout}); with two files each must hold one"
            )
    if second.camera_from_world is None:
        raise SlscanError(
            f"{second.where}: has no pose (rotation and translation): the second device's "
            "pose relative to the first is needed"
        )
    if first.units_mm != second.units_mm:
        raise SlscanError("the two files must be read with the same --units-mm")
    world = first.camera_from_world if first.camera_from_world is not None else np.eye(4)
    return ImportedCalibration(
        files=first.files + second.files,
        format=first.format if first.format == second.format else f"{first.format}+{second.format}",
        layout=first.layout if first.layout == second.layout else f"{first.layout}+{second.layout}",
        camera=first.camera,
        second=second.camera,
        second_kind=second_kind,
        camera_from_second=world @ rigid_inverse(second.camera_from_world),
        units_mm=first.units_mm,
    )


def _read_keyed(
    paths: Sequence[Path],
    read,
    layouts: Sequence[KeyMap],
    *,
    keys: KeyMap | None,
    format: str,
    units_mm: float,
    fold_case: bool,
    single_kind: str | None = None,
) -> ImportedCalibration:
    """The engine of :func:`read_opencv` and :func:`read_text`: one file (or two files'
    keys together) with both devices, else one device per file, paired."""
    units_mm = _check_units(units_mm)
    per_file = [(p, read(p)) for p in paths]
    merged = _Values.of(per_file, fold_case)
    if keys is not None:
        if keys.second is not None or len(paths) == 1:
            return _from_keys(merged, keys, format=format, units_mm=units_mm)
        parts = [
            _from_keys(_Values.of([pf], fold_case), keys, format=format, units_mm=units_mm)
            for pf in per_file
        ]
        return pair_devices(*parts, second_kind=single_kind)
    found = _detect(merged, layouts, two=True)
    if found is not None:
        return _from_keys(merged, found, format=format, units_mm=units_mm)
    parts = []
    for pf in per_file:
        one = _Values.of([pf], fold_case)
        found = _detect(one, layouts, two=False)
        if found is None:
            tried = "; ".join(f"{k.name} ({k.camera.rstrip('?')}, ...)" for k in layouts)
            shown = ", ".join(sorted(one.values)[:12]) or "none"
            raise SlscanError(
                f"{pf[0]}: no known layout: tried {tried}; keys in the file: {shown}; "
                "name them with --keys camera=KEY,camera_dist=KEY,..."
            )
        parts.append(_from_keys(one, found, format=format, units_mm=units_mm))
    if len(parts) == 1:
        return parts[0]
    return pair_devices(*parts, second_kind=single_kind)


# --- OpenCV FileStorage -----------------------------------------------------------------


def _opencv_values(path: Path) -> dict[str, object]:
    """Every value of a FileStorage file by key ("Camera/Matrix" inside maps): float arrays
    for matrices, numbers and number lists, str for strings, None for anything else."""
    if not path.is_file():
        raise SlscanError(f"{path}: calibration file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV's parser raises on malformed files
        reason = str(exc.__cause__ or exc).strip().splitlines()[-1][:200]
        raise SlscanError(f"{path}: not a readable OpenCV FileStorage file ({reason})") from None
    if not fs.isOpened():
        raise SlscanError(f"{path}: not an OpenCV FileStorage file (XML, YAML or JSON)")
    out: dict[str, object] = {}
    try:
        _collect(fs.root(), "", out)
    except (cv2.error, SystemError, UnicodeDecodeError) as exc:  # a node OpenCV cannot walk or decode
        reason = str(exc.__cause__ or exc).strip().splitlines()[-1][:200]
        raise SlscanError(f"{path}: not a readable OpenCV FileStorage file ({reason})") from None
    finally:
        fs.release()
    return out


_MAX_MATRIX_VALUES = 1 << 24
"""More values than this in one FileStorage matrix: not a calibration (refused unread)."""


def _fs_int(node: cv2.FileNode) -> int | None:
    if not node.isInt():
        return None
    value = node.real()
    return int(value) if math.isfinite(value) and 0 <= value <= _MAX_MATRIX_VALUES else None


def _fs_matrix(node: cv2.FileNode) -> np.ndarray | None:
    """A FileStorage matrix (``rows``/``cols`` or ``sizes``, ``dt``, ``data``) as a float array,
    or None when its fields disagree. Built here from the data, not with ``FileNode.mat()``:
    OpenCV allocates what ``rows`` and ``cols`` say before it checks the data (a ``cols`` of
    ``inf`` asks for 51 GB) and corrupts its heap on some mismatches (a native crash)."""
    if "sizes" in set(node.keys()):
        sizes = node.getNode("sizes")
        dims = [_fs_int(sizes.at(i)) for i in range(sizes.size())] if sizes.isSeq() else [_fs_int(sizes)]
    else:
        dims = [_fs_int(node.getNode("rows")), _fs_int(node.getNode("cols"))]
    dt = node.getNode("dt").string() if node.getNode("dt").isString() else ""
    match = re.fullmatch(r"(\d*)[ucwsifdhr]", dt.strip())
    channels = int(match.group(1) or 1) if match else None
    if None in dims or not dims or channels is None or not 1 <= channels <= 4:
        return None
    data = node.getNode("data")
    if data.isSeq():
        if data.size() > _MAX_MATRIX_VALUES:
            return None
        items = [data.at(i) for i in range(data.size())]
    else:
        items = [data]
    if not all(it.isReal() or it.isInt() for it in items):
        return None
    values = np.array([it.real() for it in items], float)
    shape = tuple(dims) + ((channels,) if channels > 1 else ())
    if int(np.prod(shape)) != len(values):
        return None
    return values.reshape(shape)


def _collect(node: cv2.FileNode, prefix: str, out: dict[str, object]) -> None:
    for key in node.keys():  # noqa: SIM118 (a FileNode, not a dict)
        child, name = node.getNode(key), prefix + key
        fields = set(child.keys()) if child.isMap() else set()
        if child.isMap():
            if "data" in fields and fields & {"rows", "sizes"}:
                out[name] = _fs_matrix(child)
            else:
                _collect(child, name + "/", out)
        elif child.isSeq():
            items = [child.at(i) for i in range(child.size())]
            numeric = all(it.isReal() or it.isInt() for it in items)
            out[name] = np.array([it.real() for it in items], float) if numeric else None
        elif child.isReal() or child.isInt():
            out[name] = np.array([child.real()])
        elif child.isString():
            out[name] = child.string()
        else:
            out[name] = None


def read_opencv(
    path: str | os.PathLike,
    path2: str | os.PathLike | None = None,
    *,
    keys: KeyMap | None = None,
    units_mm: float = 1.0,
) -> ImportedCalibration:
    """Read an OpenCV FileStorage calibration (XML, YAML or JSON).

    path, path2 : one file with both devices, two files whose keys together hold them
        (OpenCV's ``stereo_calib`` writes ``intrinsics.yml`` and ``extrinsics.yml``), or
        one device per file (paired by :func:`pair_devices`)
    keys : which key holds what; None recognises :data:`OPENCV_LAYOUTS`: kamino410
        (R, T camera to projector), OpenCV stereo (``M1 D1 M2 D2 R T``, R, T camera 1 to
        camera 2), 3DUNDERWORLD and single-device files (R, T, if any, world to camera)
    units_mm : mm per unit of the file's translation

    Raises
    ------
    SlscanError
        Naming the file and the key: missing, wrong size, NaN, not a rotation, skew or
        distortion terms slscan cannot model; or the layouts tried.
    """
    paths = [Path(p) for p in (path, path2) if p is not None]
    result = _read_keyed(
        paths,
        _opencv_values,
        OPENCV_LAYOUTS,
        keys=keys,
        format="opencv",
        units_mm=units_mm,
        fold_case=False,
    )
    if result.layout == OPENCV_STEREO.name:
        _check_rectification(paths, result, units_mm)
    return result


def _check_rectification(
    paths: Sequence[Path], result: ImportedCalibration, units_mm: float
) -> None:
    """Where a stereo file has ``R1 R2 P2`` too, they must agree with ``R, T`` (rectified
    frames share one orientation; ``P2``'s baseline is ``|T|``): else one was edited."""
    values = _Values.of([(p, _opencv_values(p)) for p in paths])
    hits = {k: values.find(k + "?") for k in ("R1", "R2", "P2")}
    if any(h is None for h in hits.values()):
        return
    r1 = rotation(hits["R1"][2], hits["R1"][1], "R1")
    r2 = rotation(hits["R2"][2], hits["R2"][1], "R2")
    p2 = numbers(hits["P2"][2], hits["P2"][1], "P2", (12,)).reshape(3, 4)
    second_from_camera = rigid_inverse(result.camera_from_second)
    r, t = second_from_camera[:3, :3], second_from_camera[:3, 3] / units_mm
    if np.abs(r2 @ r - r1).max() > 1e-4:
        raise SlscanError(
            f"{hits['R1'][1]}: keys 'R1', 'R2' disagree with 'R' (R2·R ≠ R1); was one of them edited?"
        )
    baseline = max(abs(p2[0, 3] / p2[0, 0]), abs(p2[1, 3] / p2[1, 1]))
    if abs(baseline - np.linalg.norm(t)) > 1e-3 * np.linalg.norm(t):
        raise SlscanError(
            f"{hits['P2'][1]}: key 'P2' gives a baseline of {baseline:.6g}, 'T' one of "
            f"{np.linalg.norm(t):.6g} (file units); was one of them edited?"
        )


# --- plain text -------------------------------------------------------------------------

_TOKEN = re.compile(
    r"(?P<num>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?![\w.])|[-+]?(?:nan|inf)(?!\w))"
    r"|(?P<label>[A-Za-z_][\w.]*)|(?P<skip>[\s,;:=\[\](){}]+)",
    re.IGNORECASE,
)


def _text_blocks(path: Path) -> dict[str, list[float]]:
    """Labelled blocks of numbers: a label (a word, maybe followed by ``:`` or ``=``) and the
    numbers after it, up to the next label (lower-cased; numbers before any label under
    ""); ``#``, ``%`` and ``//`` start comments; a label without numbers is a heading."""
    if not path.is_file():
        raise SlscanError(f"{path}: calibration file not found")
    try:
        text = path.read_text(encoding="utf-8-sig", errors="strict")
    except (OSError, UnicodeDecodeError) as exc:
        raise SlscanError(f"{path}: not a readable text file ({exc})") from None
    blocks: dict[str, list[float]] = {}
    first_line: dict[str, int] = {}
    label = ""
    for number, line in enumerate(text.splitlines(), 1):
        line = re.split(r"#|%|//", line, maxsplit=1)[0]
        pos = 0
        while pos < len(line):
            m = _TOKEN.match(line, pos)
            if m is None:
                raise SlscanError(
                    f"{path}: line {number}: cannot read {line[pos : pos + 12]!r} "
                    "(expected labels and numbers)"
                )
            pos = m.end()
            if m.group("num"):
                blocks.setdefault(label, []).append(float(m.group("num")))
            elif m.group("label"):
                label = m.group("label").lower()
                if label in blocks:
                    raise SlscanError(
                        f"{path}: line {number}: label {label!r} appears twice "
                        f"(first on line {first_line[label]})"
                    )
                first_line[label] = number
    return blocks


def _text_values(path: Path) -> dict[str, object]:
    """:func:`_text_blocks` as arrays; a file of bare numbers is split by count: K (9),
    K + distortion (13, 14, 17, 21, 23), K + distortion + R + T (25, 26, 29, 33, 35)."""
    blocks = _text_blocks(path)
    if not blocks:
        raise SlscanError(f"{path}: no numbers (expected labelled matrices: K:, dist:, R:, T:)")
    if list(blocks) == [""]:
        bare = blocks.pop("")
        n = len(bare)
        if n == 9:
            blocks = {"k": bare}
        elif n - 9 in _DIST_COUNTS:
            blocks = {"k": bare[:9], "dist": bare[9:]}
        elif n - 21 in _DIST_COUNTS:
            blocks = {
                "k": bare[:9],
                "dist": bare[9 : n - 12],
                "r": bare[n - 12 : n - 3],
                "t": bare[n - 3 :],
            }
        else:
            raise SlscanError(
                f"{path}: {n} unlabelled numbers: expected K (9), K + distortion (13, 14, 17, "
                "21, 23) or K + distortion + R + T (25, 26, 29, 33, 35); or label the blocks "
                "(K:, dist:, R:, T:)"
            )
    return {k: np.asarray(v, float) for k, v in blocks.items()}


def read_text(
    path: str | os.PathLike,
    path2: str | os.PathLike | None = None,
    *,
    keys: KeyMap | None = None,
    units_mm: float = 1.0,
) -> ImportedCalibration:
    """Read plain-text matrices: numbers separated by spaces, commas or semicolons.

    Labels (case-insensitive) recognised without ``keys`` (:data:`TEXT_LAYOUTS`):

    - one device per file: ``K`` (3×3, row-major), ``dist`` (4, 5, 8, 12 or 14),
      optional ``R`` (3×3 or Rodrigues 3-vector) and ``T``, which take world (board)
      points to the device's, and ``size`` (width height); two such files are a pair
      (:func:`pair_devices`: a first file without R, T is the world);
    - camera + projector in one file: ``K_cam dist_cam K_proj dist_proj R T`` (R, T
      camera to projector);
    - two cameras in one file: ``K1 D1 K2 D2 R T`` (R, T camera 1 to camera 2);
    - no labels at all: K, K + dist, or K + dist + R + T, by the count of numbers.

    Raises SlscanError naming the file and the label it could not use.
    """
    paths = [Path(p) for p in (path, path2) if p is not None]
    return _read_keyed(
        paths,
        _text_values,
        TEXT_LAYOUTS,
        keys=keys,
        format="text",
        units_mm=units_mm,
        fold_case=True,
    )


# --- 3DUNDERWORLD -----------------------------------------------------------------------


def _underworld_values(path: Path) -> dict[str, object]:
    if path.is_dir():
        out: dict[str, object] = {}
        for name in (
            "cam_matrix.txt",
            "cam_distortion.txt",
            "cam_rotation_matrix.txt",
            "cam_trans_vectror.txt",
            "cam_trans_vector.txt",
        ):
            if (path / name).is_file():
                blocks = _text_blocks(path / name)
                if set(blocks) - {""}:
                    raise SlscanError(f"{path / name}: expected numbers only (the tool's export)")
                out[name] = np.asarray(blocks.get("", []), float)
        return out
    values = _opencv_values(path)
    flag = values.get("Camera/Calibrated")
    if isinstance(flag, np.ndarray) and flag.size == 1 and flag[0] == 0:
        raise SlscanError(
            f"{path}: key 'Camera/Calibrated' is 0: the tool did not calibrate this camera"
        )
    return values


def read_3dunderworld(
    path: str | os.PathLike, path2: str | os.PathLike | None = None, *, units_mm: float = 1.0
) -> ImportedCalibration:
    """Read 3DUNDERWORLD-SLS's per-camera calibration; two files make a stereo pair.

    Each camera is either its ``calib.xml`` (OpenCV FileStorage: ``Camera`` with
    ``Matrix``, ``Distortion``, ``Rotation``, ``Translation``, ``Width``, ``Height``) or the
    folder of the text files the tool exports and its reconstruction reads
    (``cam_matrix.txt``, ``cam_distortion.txt``, ``cam_rotation_matrix.txt``,
    ``cam_trans_vectror.txt`` [sic]; no image size). Rotation and translation are
    ``solvePnP``'s: board points to camera points (``x_cam = R·x_board + T``), board squares
    in mm. The pair's pose is camera 1 relative to camera 0 through the shared board.
    """
    paths = [Path(p) for p in (path, path2) if p is not None]
    parts = []
    for p in paths:
        if not (p.is_file() or p.is_dir()):
            raise SlscanError(f"{p}: calibration file not found")
        layout = THREEDUNDERWORLD_TEXT if p.is_dir() else THREEDUNDERWORLD
        values = _Values.of([(p, _underworld_values(p))])
        one = _from_keys(values, layout, format="3dunderworld", units_mm=_check_units(units_mm))
        if p.is_dir():
            one = dataclasses.replace(one, files=(p,))
        parts.append(one)
    if len(parts) == 1:
        return parts[0]
    return pair_devices(*parts, second_kind="camera")


# --- Bouguet ----------------------------------------------------------------------------

_ASSIGN = re.compile(r"(?<![\w.])([A-Za-z]\w*)\s*=(?!=)\s*")


def _matlab_assignments(text: str) -> dict[str, tuple[np.ndarray | None, str]]:
    """``name = value`` statements of a MATLAB script: numbers and numeric ``[...]``
    matrices (rows by ``;`` or new lines, a trailing ``'`` transposes); anything else is
    kept as text (value None). A later assignment replaces an earlier one."""
    src = "\n".join(line.split("%", 1)[0] for line in text.splitlines())
    out: dict[str, tuple[np.ndarray | None, str]] = {}
    pos = 0
    while (m := _ASSIGN.search(src, pos)) is not None:
        start = m.end()
        if src.startswith("[", start):
            end = src.find("]", start)
            end = len(src) if end < 0 else end + 1
            transposed = src.startswith("'", end)
            raw = src[start : end + transposed]
            rows = [
                r.split()
                for r in re.split(
                    r"[;\n]", src[start + 1 : end - 1].replace("...", " ").replace(",", " ")
                )
            ]
            rows = [r for r in rows if r]
            try:
                if len({len(r) for r in rows}) == 1:
                    value = np.array([[float(x) for x in r] for r in rows])
                else:
                    value = np.array([float(x) for r in rows for x in r])
                value = value.T if transposed else value
            except ValueError:
                value = None
            pos = end
        else:
            end = len(src)
            for stop in (";", "\n", ","):
                i = src.find(stop, start)
                end = min(end, i) if i >= 0 else end
            raw = src[start:end].strip()
            try:
                value = np.array([float(raw)])
            except ValueError:
                value = None
            pos = max(end, start + 1)
        out[m.group(1)] = (value, raw)
    return out


def read_bouguet(path: str | os.PathLike, *, units_mm: float = 1.0) -> ImportedCalibration:
    """Read Bouguet's ``Calib_Results_stereo.m`` (MATLAB assignments).

    Keys: ``fc_left cc_left kc_left alpha_c_left`` and the same ``_right``, ``om``
    (Rodrigues, rad; or ``R``) and ``T``, with ``XR = R·XL + T`` (left-camera points to
    right-camera points, T in the unit of the board squares: ``units_mm``), and the image
    size ``nx ny`` when present (both cameras). Bouguet's pixel [0; 0] is the centre of the
    upper-left pixel, as in OpenCV and slscan, so ``cc`` is used as is; ``kc`` is
    ``[k1; k2; p1; p2; k3]``, OpenCV's order. A non-zero skew ``alpha_c`` is refused.

    The right device is a projector when the file says "parameters of projector" (the
    form Moreno & Taubin's procam calibration writes), else a camera.
    """
    path = Path(path)
    units_mm = _check_units(units_mm)
    if not path.is_file():
        raise SlscanError(f"{path}: calibration file not found")
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise SlscanError(f"{path}: cannot read ({exc.strerror})") from None
    assigned = _matlab_assignments(text)

    def get(name: str, counts: Sequence[int], required: bool = True) -> np.ndarray | None:
        if name not in assigned:
            if required:
                raise SlscanError(
                    f"{path}: missing key {name!r} (Bouguet's Calib_Results_stereo.m)"
                )
            return None
        value, raw = assigned[name]
        return numbers(raw if value is None else value, path, name, counts)

    size = None
    nx, ny = get("nx", (1,), False), get("ny", (1,), False)
    if nx is not None and ny is not None:
        size = image_size([nx[0], ny[0]], path, "nx")

    def lens(side: str, size: tuple[int, int] | None) -> ImportedLens:
        fc, cc = get(f"fc_{side}", (2,)), get(f"cc_{side}", (2,))
        alpha = get(f"alpha_c_{side}", (1,), False)
        if alpha is not None and alpha[0] != 0:
            raise SlscanError(
                f"{path}: key 'alpha_c_{side}' is {alpha[0]:g}: a skewed pixel grid; slscan's lens model has none"
            )
        kc = get(f"kc_{side}", _DIST_COUNTS)
        k = np.array([[fc[0], 0.0, cc[0]], [0.0, fc[1], cc[1]], [0.0, 0.0, 1.0]])
        return ImportedLens(
            camera_matrix(k, path, f"fc_{side}"),
            distortion(kc, path, f"kc_{side}"),
            size,
            path,
            f"fc_{side}",
            None if size is None else "nx, ny",
        )

    projector = re.search(r"parameters of (?:the )?projector", text, re.IGNORECASE) is not None
    left, right = lens("left", size), lens("right", None if projector else size)
    if "om" in assigned or "R" not in assigned:
        r = rotation(get("om", (3,)), path, "om")
    else:
        r = rotation(get("R", (9,)), path, "R")
    right_from_left = _pose(r, get("T", (3,)) * units_mm)
    return ImportedCalibration(
        files=(path,),
        format="bouguet",
        layout="bouguet-stereo",
        camera=left,
        second=right,
        second_kind="projector" if projector else "camera",
        camera_from_second=rigid_inverse(right_from_left),
        units_mm=units_mm,
    )


# --- any format -------------------------------------------------------------------------


def guess_format(path: Path) -> str:
    """The format of ``path`` from its name and content: a folder is 3DUNDERWORLD's text
    files; ``.m`` Bouguet; ``.xml .yml .yaml .json`` OpenCV (3DUNDERWORLD when its top
    key is ``Camera``); ``.txt`` text; anything else is tried as each in turn."""
    if path.is_dir():
        return "3dunderworld"
    if not path.is_file():
        raise SlscanError(f"{path}: calibration file not found")
    suffix = path.suffix.lower()
    if suffix == ".m":
        return "bouguet"
    if suffix == ".txt":
        return "text"
    tried = []
    try:
        values = _opencv_values(path)
        return "3dunderworld" if "Camera/Matrix" in values else "opencv"
    except SlscanError as exc:
        if suffix in (".xml", ".yml", ".yaml", ".json"):
            raise
        tried.append(f"OpenCV FileStorage ({str(exc).split(': ', 1)[-1]})")
    head = path.read_bytes()[:65536].decode("utf-8", "replace")
    if "fc_left" in head:
        return "bouguet"
    tried.append("Bouguet (no fc_left)")
    try:
        _text_values(path)
        return "text"
    except SlscanError as exc:
        tried.append(f"plain text ({str(exc).split(': ', 1)[-1]})")
    raise SlscanError(f"{path}: not a calibration format slscan reads: tried {'; '.join(tried)}")


def read_calibration(
    paths: Sequence[str | os.PathLike],
    *,
    format: str = "auto",
    keys: KeyMap | None = None,
    units_mm: float = 1.0,
) -> ImportedCalibration:
    """Read one or two calibration files in ``format`` ({"auto", "opencv", "bouguet",
    "text", "3dunderworld"}; "auto" guesses from the first file, :func:`guess_format`)."""
    paths = [Path(p) for p in paths]
    if not 1 <= len(paths) <= 2:
        raise SlscanError(f"--import takes one or two files, got {len(paths)}")
    if format not in FORMATS:
        raise SlscanError(
            f"unknown calibration format {format!r}: expected one of {', '.join(FORMATS)}"
        )
    if format == "auto":
        format = guess_format(paths[0])
    for p in paths:
        if p.is_dir() and format != "3dunderworld":
            hint = (
                " (a capture session: give it as --session)"
                if (p / "session.json").is_file()
                else ""
            )
            raise SlscanError(f"{p}: is a folder; expected a calibration file ({format}){hint}")
    if keys is not None and format not in ("opencv", "text"):
        raise SlscanError(f"--keys is for OpenCV and text files; {paths[0]} is read as {format}")
    if format == "bouguet":
        if len(paths) > 1:
            raise SlscanError(
                f"{paths[1]}: Bouguet's Calib_Results_stereo.m holds both cameras; give it alone"
            )
        return read_bouguet(paths[0], units_mm=units_mm)
    reader = {"opencv": read_opencv, "text": read_text, "3dunderworld": read_3dunderworld}[format]
    kwargs = {"keys": keys} if format in ("opencv", "text") else {}
    return reader(*paths, units_mm=units_mm, **kwargs)


def import_opencv_xml(
    path: str | os.PathLike,
    *,
    projector_size: tuple[int, int],
    camera_size: tuple[int, int] | None = None,
    units_mm: float = 1.0,
    projector_scale: float = 1.0,
) -> Calibration:
    """Read a procam calibration in OpenCV FileStorage XML (kamino410/procam-calibration).

    Parameters
    ----------
    path : the ``.xml`` file: ``cam_int``, ``cam_dist``, ``proj_int``, ``proj_dist`` (3x3 and
        5 values), ``roration`` (sic; ``rotation`` also read) and ``translation``, which take
        camera points to projector points; optional ``img_shape`` (rows, cols) and ``rms``
    projector_size : (width, height) px of the pattern images (the file does not say)
    camera_size : (width, height) px; default from ``img_shape`` (must agree with it)
    units_mm : millimetres per unit of the file's translation (the board square's unit)
    projector_scale : pattern pixels per projector pixel of the file: the file's projector
        intrinsics are multiplied by it (0.5 for a file whose projector coordinates are
        twice the patterns', as with procam-calibration's ``graycode_step`` 2)

    Raises
    ------
    SlscanError
        Missing file or key (named), or a key of the wrong size.
    """
    imported = read_opencv(path, keys=KAMINO410, units_mm=units_mm)
    return imported.to_calibration(
        camera_size=camera_size, projector_size=projector_size, projector_scale=projector_scale
    )
