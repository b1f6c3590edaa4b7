"""Calibration files: slscan's JSON (``docs/calibration.md``) and OpenCV FileStorage XML.

The JSON file holds the camera, the projector as an inverse camera and/or as a light-plane
model, and each method's residuals. It is written atomically; reading it checks the format,
the version and every required field, naming the one missing. The XML written is the
layout of kamino410/procam-calibration's ``calibration_result.xml`` (``cam_int``,
``cam_dist``, ``proj_int``, ``proj_dist``, ``roration`` [sic], ``translation``,
``img_shape``, ``rms``); reading it, and other tools' formats, is
:mod:`slscan.calibrate.importers` (``import_opencv_xml`` is re-exported here).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from slscan import __version__
from slscan.calibrate.importers import import_opencv_xml  # noqa: F401 (re-exported for callers)
from slscan.calibrate.planes import LightPlaneModel, MeasuredPlanes
from slscan.calibrate.target import Board
from slscan.capture.session import Session
from slscan.decode.samples import LightPlanes
from slscan.decode.triangulate import RigPlanes
from slscan.errors import SlscanError, about_file
from slscan.fsio import atomic_output_file, read_json, write_json
from slscan.rig import Light, PinholeModel, Projector, Rig, _as_pose

log = logging.getLogger(__name__)

CALIBRATION_FORMAT = "slscan.calibration"
CALIBRATION_VERSION = 1
PLANE_SOURCES = ("auto", "planes", "raw-planes", "inverse-camera")


@dataclass(frozen=True, eq=False)
class Calibration:
    """A calibrated rig as measured: camera, projector models and residuals.

    camera : the camera lens; its frame is the rig frame (mm)
    projector_size : (width, height) px
    projector : the projector as an inverse camera (pose and lens), or None
    light_planes : the light-plane model of the global fit, or None
    raw_columns, raw_planes : (m,), (m, 4) the light planes as measured per feature, or None
    residuals : per method, JSON-ready (see ``docs/calibration.md``)
    board : the target calibrated with, if known
    source : where it came from (session, methods, tool), JSON-ready
    """

    camera: PinholeModel
    projector_size: tuple[int, int]
    projector: Projector | None = None
    light_planes: LightPlaneModel | None = None
    raw_columns: np.ndarray | None = None
    raw_planes: np.ndarray | None = None
    residuals: dict = field(default_factory=dict)
    board: Board | None = None
    source: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.projector is None and self.light_planes is None:
            raise SlscanError(
                "a calibration needs a projector model: inverse camera or light planes"
            )
        w, h = (int(v) for v in self.projector_size)
        object.__setattr__(self, "projector_size", (w, h))
        if self.projector is not None and (
            self.projector.lens.width,
            self.projector.lens.height,
        ) != (w, h):
            raise SlscanError(
                f"calibration: projector lens is {self.projector.lens.width}x{self.projector.lens.height}, "
                f"projector_size says {w}x{h}"
            )

    @property
    def methods(self) -> tuple[str, ...]:
        """The projector models present: "inverse-camera" and/or "planes"."""
        return tuple(
            m
            for m, present in (
                ("inverse-camera", self.projector is not None),
                ("planes", self.light_planes is not None),
            )
            if present
        )

    def rig(self, *, lights: tuple[Light, ...] = (), working_distance: float = 1300.0) -> Rig:
        """A :class:`Rig` for triangulation: the inverse-camera projector when there is one,
        else the light-plane model's projector (``fy = fx``, centre row as ``cy``)."""
        projector = self.projector
        if projector is None:
            projector = self.light_planes.projector(self.projector_size[1])
        return Rig(self.camera, projector, tuple(lights), working_distance)

    def to_dict(self) -> dict:
        d: dict = {
            "format": CALIBRATION_FORMAT,
            "version": CALIBRATION_VERSION,
            "written_by": f"slscan {__version__}",
            "units": "mm",
            "frame": "rig frame = camera frame: x right, y down, z forward (OpenCV); "
            "pixel centres at integers",
            "source": self.source,
            "board": None if self.board is None else self.board.to_dict(),
            "camera": self.camera.to_dict(),
            "projector_size": list(self.projector_size),
            "projector": None if self.projector is None else self.projector.to_dict(),
            "light_planes": None,
            "residuals": self.residuals,
        }
        if self.light_planes is not None:
            planes: dict = {"model": self.light_planes.to_dict()}
            if self.raw_columns is not None and self.raw_planes is not None:
                planes["raw"] = {
                    "columns": np.asarray(self.raw_columns, float).tolist(),
                    "planes": np.asarray(self.raw_planes, float).tolist(),
                }
            d["light_planes"] = planes
        return d

    @classmethod
    def from_dict(cls, d: dict, where: str = "calibration") -> Calibration:
        if not isinstance(d, dict):
            raise SlscanError(f"{where}: expected a JSON object")
        if d.get("format") != CALIBRATION_FORMAT:
            raise SlscanError(f"{where}: not an slscan calibration (format {d.get('format')!r})")
        if d.get("version") != CALIBRATION_VERSION:
            raise SlscanError(
                f"{where}: calibration version {d.get('version')!r} is not supported "
                f"(this slscan reads version {CALIBRATION_VERSION})"
            )
        for key in ("camera", "projector_size"):
            if key not in d:
                raise SlscanError(f"{where}: missing field {key!r}")
        camera = PinholeModel.from_dict(_object(d["camera"], where, "camera"), f"{where}: camera")
        try:
            size = tuple(int(v) for v in d["projector_size"])
        except (TypeError, ValueError):
            raise SlscanError(f"{where}: field 'projector_size' must be [width, height]") from None
        if len(size) != 2:
            raise SlscanError(f"{where}: field 'projector_size' must be [width, height]")
        projector = None
        if d.get("projector") is not None:
            p = _object(d["projector"], where, "projector")
            for key in ("lens", "rig_from_projector"):
                if key not in p:
                    raise SlscanError(f"{where}: missing field 'projector.{key}'")
            lens = PinholeModel.from_dict(
                _object(p["lens"], where, "projector.lens"), f"{where}: projector.lens"
            )
            pose = _as_pose(p["rig_from_projector"], f"{where}: projector.rig_from_projector")
            projector = Projector(lens, pose)
        light_planes = raw_columns = raw_planes = None
        if d.get("light_planes") is not None:
            lp = _object(d["light_planes"], where, "light_planes")
            if "model" not in lp:
                raise SlscanError(f"{where}: missing field 'light_planes.model'")
            light_planes = LightPlaneModel.from_dict(
                _object(lp["model"], where, "light_planes.model"), f"{where}: light_planes.model"
            )
            if lp.get("raw") is not None:
                raw = _object(lp["raw"], where, "light_planes.raw")
                for key in ("columns", "planes"):
                    if key not in raw:
                        raise SlscanError(f"{where}: missing field 'light_planes.raw.{key}'")
                try:
                    raw_columns = np.asarray(raw["columns"], float).reshape(-1)
                    raw_planes = np.asarray(raw["planes"], float).reshape(-1, 4)
                except (TypeError, ValueError):
                    raise SlscanError(
                        f"{where}: 'light_planes.raw' must hold numbers (columns, 4-vector planes)"
                    ) from None
                if len(raw_columns) != len(raw_planes):
                    raise SlscanError(
                        f"{where}: 'light_planes.raw' has {len(raw_columns)} columns and {len(raw_planes)} planes"
                    )
        if projector is None and light_planes is None:
            raise SlscanError(
                f"{where}: missing field 'projector' or 'light_planes' (a projector model)"
            )
        board = (
            None
            if d.get("board") is None
            else Board.from_dict(_object(d["board"], where, "board"), f"{where}: board")
        )
        return cls(
            camera=camera,
            projector_size=size,
            projector=projector,
            light_planes=light_planes,
            raw_columns=raw_columns,
            raw_planes=raw_planes,
            residuals=dict(d.get("residuals") or {}),
            board=board,
            source=dict(d.get("source") or {}),
        )


def _object(value, where: str, key: str) -> dict:
    if not isinstance(value, dict):
        raise SlscanError(f"{where}: field {key!r} must be an object")
    return value


def save_calibration(calibration: Calibration, path: str | os.PathLike) -> Path:
    """Write ``calibration`` as JSON to ``path``, atomically; return the path."""
    path = Path(path)
    write_json(path, calibration.to_dict())
    return path


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a calibration JSON file.

    Raises
    ------
    SlscanError
        Not found, not JSON, another format, an unsupported version, or a missing or
        malformed field (named).
    """
    path = Path(path)
    data = read_json(path, "calibration file")
    with about_file(path, "calibration file"):
        return Calibration.from_dict(data, str(path))


# --- use in decoding --------------------------------------------------------------------------


def calibration_planes(calibration: Calibration, *, source: str = "auto") -> LightPlanes:
    """The light planes decoding should use with ``calibration``.

    source : {"auto", "planes", "raw-planes", "inverse-camera"}: the global light-plane
        model; the raw measured planes (interpolated between measured columns); the
        inverse camera (its whole model: distortion, and the projector rows where the
        captures code them); "auto" takes the light-plane model when there is one, else
        the inverse camera, and the inverse camera when the rig's geometry makes the
        projector rows pin depth better than the columns the light planes have
        (:func:`slscan.decode.triangulate.choose_axes`: a projector above or below the
        camera; kamino410's captures: leave-one-out flatness 0.40 mm RMS against 4.5 mm,
        ``benchmarks/real_flatness.py``)
    """
    if source not in PLANE_SOURCES:
        raise SlscanError(
            f"unknown plane source {source!r}: expected one of {', '.join(PLANE_SOURCES)}"
        )
    if source == "auto":
        source = "planes" if calibration.light_planes is not None else "inverse-camera"
        if source == "planes" and calibration.projector is not None:
            from slscan.decode.triangulate import choose_axes, rig_conditioning

            conditioning = rig_conditioning(calibration.camera, calibration.projector)
            if choose_axes(conditioning) == "both":
                log.info(
                    "decoding with the calibration's inverse camera, not its light planes: the projector's "
                    "rows pin depth %.1fx better than its columns, which are all the light planes have "
                    "(%.1f against %.1f mm per projector px at 1.3 m); --planes planes to use the light planes",
                    conditioning.rows_gain, conditioning.both, conditioning.columns)
                source = "inverse-camera"
    if source in ("planes", "raw-planes"):
        if calibration.light_planes is None:
            raise SlscanError(
                "the calibration has no light-plane model (calibrate with --method planes)"
            )
        if source == "raw-planes" and calibration.raw_columns is None:
            raise SlscanError("the calibration has no raw light planes")
        return MeasuredPlanes(
            calibration.light_planes,
            calibration.raw_columns,
            calibration.raw_planes,
            use_raw=source == "raw-planes",
        )
    if calibration.projector is None:
        raise SlscanError(
            "the calibration has no inverse-camera projector (calibrate with --method inverse-camera)"
        )
    return RigPlanes(calibration.projector)


def apply_calibration(
    session: Session, calibration: Calibration, *, source: str = "measured"
) -> Session:
    """``session`` with its calibration replaced by ``calibration``'s rig (lights kept).

    Use with :func:`calibration_planes` to decode with a measured calibration::

        decode_view(apply_calibration(session, cal), view, planes=calibration_planes(cal))

    Raises SlscanError when the camera or projector size differs from the session's.
    """
    if (calibration.camera.width, calibration.camera.height) != session.camera_size:
        raise SlscanError(
            f"{session.root}: the calibration is for a {calibration.camera.width}x{calibration.camera.height} "
            f"camera, the session's is {session.camera_size[0]}x{session.camera_size[1]}"
        )
    if calibration.projector_size != session.projector_size:
        raise SlscanError(
            f"{session.root}: the calibration is for a {calibration.projector_size[0]}x"
            f"{calibration.projector_size[1]} projector, the session's is "
            f"{session.projector_size[0]}x{session.projector_size[1]}"
        )
    old = session.calibration
    rig = calibration.rig(
        lights=old.lights if old is not None else (),
        working_distance=old.working_distance if old is not None else 1300.0,
    )
    return dataclasses.replace(session, calibration=rig, calibration_source=source)


# --- OpenCV FileStorage XML ------------------------------------------------------------------


def export_opencv_xml(calibration: Calibration, path: str | os.PathLike) -> Path:
    """Write the camera and the inverse-camera projector as procam-calibration's XML.

    The field names are the tool's, ``roration`` included, so its readers load it.

    Raises
    ------
    SlscanError
        The calibration has no inverse-camera projector (a light-plane model alone leaves
        the projector's rows unknown).
    """
    if calibration.projector is None:
        raise SlscanError(
            "XML export needs the projector as an inverse camera (calibrate with --method "
            "inverse-camera or both); light planes alone do not fix the projector's rows"
        )
    path = Path(path)
    cam, proj = calibration.camera, calibration.projector
    projector_from_camera = np.linalg.inv(proj.rig_from_projector)
    rms = calibration.residuals.get("inverse_camera", {}).get("stereo_rms_px")
    if rms is None:
        rms = calibration.residuals.get("imported", {}).get("stereo_rms_px")
    with atomic_output_file(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_XML)
        if not fs.isOpened():
            raise SlscanError(f"{path}: cannot write here")
        fs.write("img_shape", np.array([[float(cam.height)], [float(cam.width)]]))
        if rms is not None:
            fs.write("rms", float(rms))
        fs.write("cam_int", cam.K)
        fs.write("cam_dist", cam.dist_array.reshape(1, 5))
        fs.write("proj_int", proj.lens.K)
        fs.write("proj_dist", proj.lens.dist_array.reshape(1, 5))
        fs.write("roration", projector_from_camera[:3, :3].copy())
        fs.write("translation", projector_from_camera[:3, 3].reshape(3, 1).copy())
        fs.release()
        if not tmp.read_bytes().rstrip().endswith(b"</opencv_storage>"):  # OpenCV does not report short writes
            from slscan.fsio import write_error

            raise write_error(path, written=tmp.stat().st_size)
    return path
