"""Multi-camera sessions: one ordinary capture session per camera, and ``cameras.json``.

Layout (full description in ``docs/stereo.md``)::

    SESSION/
      cameras.json            format "slscan.multi-camera": the cameras, their lenses and
                              poses in one common frame
      cam0/                   an ordinary capture session (session.json, view_000/, ...)
      cam1/                   the same pattern set and view names, seen by camera 1

Every single-camera stage works on each camera's folder as it is; only the stereo
reconstruction (:mod:`slscan.decode.stereo`) reads ``cameras.json``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan import __version__
from slscan.capture.session import SESSION_FILE, Session, load_session, locate_metadata
from slscan.errors import SlscanError
from slscan.fsio import read_json, write_json
from slscan.rig import PinholeModel, _as_pose

MULTICAM_FORMAT = "slscan.multi-camera"
MULTICAM_VERSION = 1
MULTICAM_FILE = "cameras.json"


@dataclass(frozen=True, eq=False)
class CameraEntry:
    """One camera of a multi-camera session.

    name : the camera's name (e.g. "cam0")
    folder : its capture-session folder, relative to the multi-camera folder
    lens : its intrinsics and distortion, or None when not calibrated
    rig_from_camera : (4, 4) float64 mm, its pose in the common (rig) frame, or None
    """

    name: str
    folder: str
    lens: PinholeModel | None = None
    rig_from_camera: np.ndarray | None = None

    @property
    def calibrated(self) -> bool:
        return self.lens is not None and self.rig_from_camera is not None

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "session": self.folder,
            "lens": None if self.lens is None else self.lens.to_dict(),
            "rig_from_camera": None if self.rig_from_camera is None else np.asarray(self.rig_from_camera).tolist(),
        }


@dataclass(frozen=True, eq=False)
class MultiCamSession:
    """A multi-camera session read from ``root``: its cameras and each one's capture session.

    frame : what the common frame is, in words (slscan writes "camera 0")
    calibration_source : where the cameras' calibration comes from (free text), or None
    sessions : one :class:`~slscan.capture.session.Session` per camera, in camera order
    """

    root: Path
    cameras: tuple[CameraEntry, ...]
    sessions: tuple[Session, ...]
    frame: str = "camera 0"
    calibration_source: str | None = None

    @property
    def view_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.sessions[0].views)

    def camera(self, name: str) -> tuple[CameraEntry, Session]:
        for cam, session in zip(self.cameras, self.sessions):
            if cam.name == name:
                return cam, session
        raise SlscanError(f"{self.root / MULTICAM_FILE}: no camera named {name!r}")

    def require_calibrated(self, purpose: str = "stereo reconstruction") -> None:
        """Raise naming the first camera without a lens or a pose."""
        for cam in self.cameras:
            if not cam.calibrated:
                missing = "lens" if cam.lens is None else "pose (rig_from_camera)"
                raise SlscanError(
                    f"{self.root / MULTICAM_FILE}: camera {cam.name!r} has no calibration ({missing} is null); "
                    f"{purpose} needs every camera's lens and pose"
                )


def is_multicam(path: str | os.PathLike) -> bool:
    """True when folder ``path`` holds a ``cameras.json``."""
    return (Path(path) / MULTICAM_FILE).is_file()


def write_cameras_json(
    root: str | os.PathLike,
    cameras: Sequence[CameraEntry],
    *,
    frame: str = "camera 0",
    calibration_source: str | None = None,
) -> Path:
    """Write ``root/cameras.json`` (atomically) for ``cameras``, whose session folders are in ``root``."""
    path = Path(root) / MULTICAM_FILE
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise SlscanError(f"{path}: camera names must be unique, got {names}")
    write_json(path, {
        "format": MULTICAM_FORMAT,
        "version": MULTICAM_VERSION,
        "written_by": f"slscan {__version__}",
        "frame": frame,
        "calibration_source": calibration_source,
        "cameras": [c.to_dict() for c in cameras],
    })
    return path


def _camera_entry(d: object, i: int, meta: Path) -> CameraEntry:
    if not isinstance(d, dict):
        raise SlscanError(f"{meta}: camera {i} is not a JSON object; expected name, session, lens, rig_from_camera")
    try:
        name, folder = str(d["name"]), str(d.get("session", d["name"]))
    except KeyError as exc:
        raise SlscanError(f"{meta}: camera {i} lacks field {exc.args[0]!r}") from None
    lens = d.get("lens")
    pose = d.get("rig_from_camera")
    return CameraEntry(
        name, folder,
        None if lens is None else PinholeModel.from_dict(lens, f"{meta}: camera {name!r} lens"),
        None if pose is None else _as_pose(pose, f"{meta}: camera {name!r} rig_from_camera"),
    )


def _missing_gray_bits_only(p0: list[dict], p1: list[dict]) -> bool:
    """Whether two cameras' pattern sets differ only by the last Gray-code bits (pattern and
    inverse) one of them lacks (bits a camera never captured, imported with
    ``--missing-bits drop``): the cameras are then matched on the bits both have
    (:func:`slscan.decode.stereo.coarsened`)."""
    a = {p["id"]: p for p in p0}
    b = {p["id"]: p for p in p1}
    common = a.keys() & b.keys()
    if any(a[k] != b[k] for k in common):
        return False
    for extra in (a.keys() - common, b.keys() - common):
        found: dict[tuple[str, int], set[bool]] = {}
        for k in extra:
            p = (a | b)[k]
            if p.get("family") != "gray" or "bit" not in p:
                return False
            found.setdefault((p["axis"], int(p["bit"])), set()).add(bool(p.get("inverse")))
        for (axis, bit), kinds in found.items():
            kept = [int(p["bit"]) for k, p in (a | b).items() if k in common and p.get("family") == "gray"
                    and p.get("axis") == axis and "bit" in p]
            if kinds != {False, True} or (kept and bit <= max(kept)):
                return False  # a bit without its inverse, or a bit missing before one present
    return True


def _check_same_set(meta: Path, first: tuple[str, Session], other: tuple[str, Session]) -> None:
    """Every camera's session must hold the same pattern set and the same view names (one
    camera may lack Gray-code bits the other has)."""
    (name0, s0), (name1, s1) = first, other
    p0 = [p.to_dict() for p in s0.patterns]
    p1 = [p.to_dict() for p in s1.patterns]
    if p0 != p1 and not _missing_gray_bits_only(p0, p1):
        ids0, ids1 = [p["id"] for p in p0], [p["id"] for p in p1]
        diff = sorted(set(ids0) ^ set(ids1)) or [a for a, b in zip(p0, p1) if a != b][:1]
        raise SlscanError(
            f"{meta}: cameras {name0!r} and {name1!r} have different pattern sets "
            f"({len(p0)} vs {len(p1)} patterns; first difference: {diff[0] if diff else '?'}); "
            "expected the same patterns in every camera's session.json"
        )
    v0, v1 = [v.name for v in s0.views], [v.name for v in s1.views]
    if v0 != v1:
        raise SlscanError(
            f"{meta}: cameras {name0!r} and {name1!r} have different views ({v0} vs {v1}); "
            "expected the same view names in every camera's session"
        )
    if s0.projector_size != s1.projector_size:
        raise SlscanError(
            f"{meta}: cameras {name0!r} and {name1!r} name different projector sizes "
            f"({s0.projector_size} vs {s1.projector_size})"
        )


def load_multicam(path: str | os.PathLike, *, validate: bool = True) -> MultiCamSession:
    """Read ``cameras.json`` in folder ``path`` and each camera's capture session.

    Checks that every camera folder holds a session (validated image by image unless
    ``validate=False``), that all sessions share one pattern set and the same view names,
    and that each calibrated lens has its session's image size.

    Raises
    ------
    SlscanError
        Naming ``cameras.json`` or the camera folder at fault, and what was expected.
    """
    root, meta = locate_metadata(path, MULTICAM_FILE, "multi-camera session")
    d = read_json(meta, "multi-camera description (cameras.json)")
    if not isinstance(d, dict) or d.get("format") != MULTICAM_FORMAT:
        got = d.get("format") if isinstance(d, dict) else type(d).__name__
        raise SlscanError(f"{meta}: not an slscan multi-camera description (format {got!r}, expected {MULTICAM_FORMAT!r})")
    if d.get("version") != MULTICAM_VERSION:
        raise SlscanError(
            f"{meta}: multi-camera format version {d.get('version')} is not supported (this slscan reads {MULTICAM_VERSION})"
        )
    raw = d.get("cameras")
    if not isinstance(raw, list) or len(raw) < 2:
        n = len(raw) if isinstance(raw, list) else 0
        raise SlscanError(f"{meta}: expected a list of at least 2 cameras, got {n}")
    cameras = tuple(_camera_entry(c, i, meta) for i, c in enumerate(raw))
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise SlscanError(f"{meta}: camera names must be unique, got {names}")
    sessions = []
    for cam in cameras:
        folder = root / cam.folder
        if not folder.resolve().is_relative_to(root.resolve()):
            raise SlscanError(f"{meta}: camera {cam.name!r} folder {cam.folder!r} is outside {root}; expected a sub-folder")
        if not (folder / SESSION_FILE).is_file():
            raise SlscanError(
                f"{meta}: camera {cam.name!r}: {folder} has no {SESSION_FILE}; expected a capture-session folder"
            )
        session = load_session(folder, validate=validate)
        if cam.lens is not None and (cam.lens.width, cam.lens.height) != session.camera_size:
            raise SlscanError(
                f"{meta}: camera {cam.name!r} lens is {cam.lens.width}x{cam.lens.height}, its images "
                f"({folder}) are {session.camera_size[0]}x{session.camera_size[1]}"
            )
        sessions.append(session)
    for cam, session in zip(cameras[1:], sessions[1:]):
        _check_same_set(meta, (cameras[0].name, sessions[0]), (cam.name, session))
    return MultiCamSession(
        root=root, cameras=cameras, sessions=tuple(sessions),
        frame=str(d.get("frame", "camera 0")), calibration_source=d.get("calibration_source"),
    )
