"""The registered views a model is textured from: un-shaded image, camera and pose per view.

A view's albedo comes from the albedo stage (``VIEW_albedo.png``: 16-bit linear RGB,
``VIEW_valid.png``: its mask), its camera model from the capture session the albedo was
computed from, and its pose from the registration (``registration.json`` or an
``aligned.mlp``: ``world_from_scan`` per range map, the scan frame being the view's camera
frame). The world frame is that of the registration's reference scan, in mm.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import read_json
from slscan.rig import PinholeModel

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class TextureView:
    """One registered view.

    camera : the view's pinhole model with distortion (OpenCV; pixel centres integer)
    world_from_camera : (4, 4) camera → world, mm, OpenCV camera axes (x right, y down,
        z forward)
    albedo : (h, w, 3) float32 linear RGB reflectance, NaN where unknown
    image_file : the albedo PNG it was read from (for messages), or ""
    """

    name: str
    camera: PinholeModel
    world_from_camera: np.ndarray
    albedo: np.ndarray
    image_file: str = ""

    def __post_init__(self) -> None:
        h, w = self.albedo.shape[:2]
        if self.albedo.ndim != 3 or self.albedo.shape[2] != 3:
            raise SlscanError(f"view {self.name}: albedo must be (h, w, 3), got {self.albedo.shape}")
        if (w, h) != (self.camera.width, self.camera.height):
            raise SlscanError(
                f"view {self.name}: albedo image {self.image_file or ''} is {w}x{h} but the "
                f"camera is {self.camera.width}x{self.camera.height}"
            )
        _check_pose(self.name, np.asarray(self.world_from_camera, float))

    @property
    def camera_from_world(self) -> np.ndarray:
        m = np.asarray(self.world_from_camera, float)
        out = np.eye(4)
        out[:3, :3] = m[:3, :3].T
        out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
        return out

    def load(self) -> TextureView:
        """The view itself (its albedo is in memory already; see :meth:`ViewFile.load`)."""
        return self


@dataclass(frozen=True, eq=False)
class ViewFile:
    """A registered view whose un-shaded image stays on disk until :meth:`load`: what a
    texture task carries to the process that bakes it (a few hundred bytes instead of the
    image, 16.6 MB at 1440 x 960), so that no process holds every view's albedo at once.

    image_path, valid_path : absolute paths of ``VIEW_albedo.png`` and ``VIEW_valid.png``
        (a Dask worker must see them at the same paths)
    image_file : the albedo PNG as the albedo folder was named (for messages, the manifest)
    """

    name: str
    camera: PinholeModel
    world_from_camera: np.ndarray
    image_path: str
    valid_path: str
    image_file: str = ""

    def load(self) -> TextureView:
        """Read the view's albedo: a :class:`TextureView`.

        Raises
        ------
        SlscanError
            An image is missing where this process looks (a worker without the albedo
            folder at the caller's path), naming the file.
        """
        from slscan.colour import read_albedo_png

        for f in (self.image_path, self.valid_path):
            if not Path(f).is_file():
                raise SlscanError(f"{f}: un-shaded image of view {self.name} not found (a worker needs the "
                                  "albedo folder at the same path as the caller)")
        albedo = read_albedo_png(self.image_path, self.valid_path)
        return TextureView(self.name, self.camera, np.asarray(self.world_from_camera, float), albedo,
                           self.image_file or self.image_path)


def read_poses(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """``world_from_scan`` per scan name from a registration result.

    path : ``registration.json`` (the register stage's), an ``.mlp`` MeshLab project, or
        a folder holding either
    """
    path = Path(path)
    if path.is_dir():
        for name in ("registration.json", "aligned.mlp"):
            if (path / name).is_file():
                return read_poses(path / name)
        raise SlscanError(f"{path}: no registration.json or aligned.mlp in this folder")
    if not path.is_file():
        raise SlscanError(f"{path}: pose file not found")
    if path.suffix.lower() == ".mlp":
        from slscan.register.meshlab import read_mlp

        return {file.stem: np.asarray(matrix, float) for file, matrix in read_mlp(path, check_files=False)}
    data = read_json(path, "registration result")
    try:
        poses = {str(k): np.asarray(v, float).reshape(4, 4) for k, v in data["poses"].items()}
    except (KeyError, TypeError, AttributeError, ValueError):
        raise SlscanError(f"{path}: expected a 'poses' object of name -> 4x4 matrix") from None
    bad = [name for name, m in poses.items() if not np.isfinite(m).all()]
    if bad:
        raise SlscanError(f"{path}: the poses of {', '.join(bad)} hold NaN or inf; expected finite 4x4 matrices")
    return poses


def load_views(
    albedo_dir: str | os.PathLike,
    poses: dict[str, np.ndarray] | str | os.PathLike | None = None,
    *,
    session: str | os.PathLike | None = None,
) -> list[TextureView]:
    """The views of an albedo-stage folder, each with its camera, pose and albedo in memory
    (:func:`view_files` without reading the images: what the texture stage uses)."""
    return [v.load() for v in view_files(albedo_dir, poses, session=session)]


def view_files(
    albedo_dir: str | os.PathLike,
    poses: dict[str, np.ndarray] | str | os.PathLike | None = None,
    *,
    session: str | os.PathLike | None = None,
) -> list[ViewFile]:
    """The views of an albedo-stage folder, each with its camera and pose, their images
    left on disk (checked to exist).

    poses : ``world_from_camera`` per view name, or a file/folder for :func:`read_poses`.
        None: the session's recorded object poses, the object frame being the world (as
        registering range maps from their recorded poses gives; turntable angles are
        approximate, a warning says so); a single view without one gets the identity. Views without a pose are left out with a
        warning (the registration left them out).
    session : the capture session (default: the one ``albedo.json`` names)
    """
    from slscan.capture.session import load_session

    albedo_dir = Path(albedo_dir)
    index = albedo_dir / "albedo.json"
    if not index.is_file():
        raise SlscanError(f"{albedo_dir}: no albedo.json; expected the output folder of `slscan albedo`")
    meta = read_json(index, "albedo index")
    try:
        entries = list(meta["views"])
        session_path = Path(session) if session is not None else Path(meta["session"])
    except (KeyError, TypeError):
        raise SlscanError(f"{index}: expected 'views' and 'session' entries") from None
    if not entries:
        raise SlscanError(f"{index}: lists no views")
    sess = load_session(session_path, validate=False)
    if sess.calibration is None:
        raise SlscanError(f"{sess.root}: the session has no camera calibration; texturing needs the camera model")
    camera = sess.calibration.camera

    if poses is not None and not isinstance(poses, dict):
        poses = read_poses(poses)
    if poses is None:
        poses = _recorded_poses(sess, [e.get("view") for e in entries], index)

    views = []
    for e in entries:
        try:
            name, image, valid = e["view"], e["image"], e["valid"]
        except (KeyError, TypeError):
            raise SlscanError(f"{index}: each view needs 'view', 'image' and 'valid' entries") from None
        if name not in poses:
            log.warning("view %s has no pose in the registration: left out of the texture", name)
            continue
        for f in (image, valid):
            if not (albedo_dir / f).is_file():
                raise SlscanError(f"{albedo_dir / f}: un-shaded image of view {name} not found")
        pose = np.asarray(poses[name], float)
        _check_pose(name, pose)
        views.append(ViewFile(name, camera, pose, str((albedo_dir / image).resolve()),
                              str((albedo_dir / valid).resolve()), str(albedo_dir / image)))
    if not views:
        raise SlscanError(f"{albedo_dir}: none of its views ({', '.join(e.get('view', '?') for e in entries)}) has a pose")
    return views


def _check_pose(name: str, m: np.ndarray) -> None:
    """The checks of :class:`TextureView` on a pose, before any image is read."""
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise SlscanError(f"view {name}: world_from_camera must be a finite 4x4 matrix")
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise SlscanError(f"view {name}: world_from_camera is not a rigid transform")


def _recorded_poses(sess, names: list[str], index: Path) -> dict[str, np.ndarray]:
    """Poses from the session: the object frame is the world (as the registration of
    range maps with recorded poses has it); a lone view without one: its camera frame."""
    records = {v.name: v for v in sess.views}
    missing = [n for n in names if n not in records or records[n].rig_from_object is None]
    if len(names) == 1 and missing:
        return {names[0]: np.eye(4)}
    if missing:
        raise SlscanError(
            f"{index}: {len(names)} views but no registration given and views {missing} record no "
            "object pose; pass the registration (registration.json or aligned.mlp)"
        )
    if len(names) > 1:
        log.warning("no registration given: using the session's recorded object poses (approximate)")
    return {n: np.linalg.inv(np.asarray(records[n].rig_from_object, float)) for n in names}
