"""MeshLab projects (``.mlp``) of aligned range scans and registered rasters: write, read back.

A project lists meshes by file name (relative to the project's folder) with a 4×4
transform each, written in ``<MLMatrix44>`` as 16 numbers row by row (translation in the
last column), the same world_from_scan pose this package uses. The meshes keep their
own frame; MeshLab (and ``pymeshlab.MeshSet().load_project``) applies the matrix when
showing them, and "Freeze matrix" bakes it in.

A project may also hold *rasters*: images registered to the model by a camera in VCG's
convention (``<MLRaster><VCGCamera/><Plane/></MLRaster>``), which MeshLab uses to show
the model from the camera and to project colour onto it ("Project active rasters color
to current mesh", "Parameterization + texturing from registered rasters"). A
:class:`Raster` holds the camera the OpenCV way; :func:`vcg_camera` and
:func:`raster_from_vcg_camera` convert between the two exactly.
"""

from __future__ import annotations

import logging
import os
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir, atomic_output_file
from slscan.register.rangescan import RangeScan, load_range_scan, write_range_scan

log = logging.getLogger(__name__)


# --- rasters: cameras in VCG's convention (see vcg_camera) -------------------------------------

_FLIP_YZ = np.diag([1.0, -1.0, -1.0])
_FILM_WIDTH_MM = 36.0
_RIGID_TOL = 1e-5  # MeshLab writes 6 significant digits; accept its rotations


@dataclass(frozen=True, eq=False)
class Raster:
    """An image registered to the model: an undistorted pinhole camera, OpenCV conventions.

    label : the raster's name in MeshLab
    image : image file (8-bit PNG, undistorted), relative to the project's folder
    width, height : int, px
    fx, fy, cx, cy : float, px; pixel centres at integer coordinates, x right, y down
    world_from_camera : (4, 4) float64; camera (x right, y down, z forward) to the
        project's world frame, in the model's units (mm)
    """

    label: str
    image: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_from_camera: np.ndarray

    def __post_init__(self) -> None:
        what = f"raster {self.label!r}"
        if not isinstance(self.label, str):
            raise SlscanError(f"{what}: label must be a string")
        if not isinstance(self.image, str) or not self.image.strip():
            raise SlscanError(f"{what}: image must be a non-empty file name, got {self.image!r}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise SlscanError(f"{what}: {name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy", "cx", "cy"):
            try:
                value = float(getattr(self, name))
            except (TypeError, ValueError):
                raise SlscanError(
                    f"{what}: {name} must be a number, got {getattr(self, name)!r}"
                ) from None
            if not np.isfinite(value):
                raise SlscanError(f"{what}: {name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        if not (self.fx > 0 and self.fy > 0):
            raise SlscanError(
                f"{what}: focal lengths must be positive, got fx={self.fx}, fy={self.fy}"
            )
        try:
            m = np.array(self.world_from_camera, dtype=np.float64)
        except (TypeError, ValueError):
            raise SlscanError(
                f"{what}: world_from_camera must be a 4x4 matrix of numbers"
            ) from None
        if m.shape != (4, 4):
            raise SlscanError(f"{what}: world_from_camera must be 4x4, got shape {m.shape}")
        if not np.all(np.isfinite(m)):
            raise SlscanError(f"{what}: world_from_camera holds non-finite numbers")
        rotation = m[:3, :3]
        deviation = max(
            float(np.abs(rotation.T @ rotation - np.eye(3)).max()),
            float(np.abs(m[3] - (0.0, 0.0, 0.0, 1.0)).max()),
        )
        if deviation > _RIGID_TOL or np.linalg.det(rotation) <= 0:
            raise SlscanError(
                f"{what}: world_from_camera is not a rigid transform (rotation part must be "
                f"orthonormal with determinant +1, last row 0 0 0 1; off by {deviation:.2g})"
            )
        m.flags.writeable = False
        object.__setattr__(self, "world_from_camera", m)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Raster):
            return NotImplemented
        return self._scalars() == other._scalars() and np.array_equal(
            self.world_from_camera, other.world_from_camera
        )

    def _scalars(self) -> tuple:
        return (self.label, self.image, self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    __hash__ = None  # holds an array

    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix (3, 3), px."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def vcg_camera(raster: Raster) -> dict[str, str]:
    """The ``<VCGCamera>`` attributes of ``raster``, as MeshLab reads them (full precision).

    Notes
    -----
    A VCG camera (``vcg::Shot``) projects a world point p to viewport pixels as
    ``Shot::Project`` [1]_, ``Camera::Project`` and ``LocalToViewportPx`` [2]_ do::

        c = Rot · (p − ViewPoint);  c.z = −c.z        # looks along its −z, +y up
        q = (c.x, c.y) · FocalMm / c.z                 # mm on the image plane
        px = q / PixelSizeMm + CenterPx                # origin bottom-left, y up

    ``<VCGCamera>`` holds ``TranslationVector = (−ViewPoint, 1)`` and ``RotationMatrix =
    Rot`` row by row [3]_. Viewport coordinates put pixel *edges* at integers: MeshLab's
    colour projection reads ``QImage::pixel(int(px.x), int(ViewportPx.y − px.y))`` [4]_
    (rows from the top). OpenCV puts pixel *centres* at integers, x right, y down. With
    world_from_camera = [R | C] (OpenCV axes) and F = diag(1, −1, −1)::

        RotationMatrix    = [[F · Rᵀ, 0], [0, 1]]
        TranslationVector = (−C, 1)
        CenterPx          = (cx + ½, height − (cy + ½))
        ViewportPx        = (width, height)
        FocalMm / PixelSizeMm = (fx, fy), PixelSizeMm.x = 36 mm / width (the 35 mm
                                equivalent MeshLab gives a raster loaded alone)

    so a point seen at OpenCV pixel (u, v) lands at px = (u + ½, height − ½ − v) and
    MeshLab samples the pixel (round(u), round(v)), the nearest centre. LensDistortion is
    "0 0" (the image is undistorted), CameraType 0 (perspective).

    Older vcglib (``shot_qt.h`` before its ``BinaryData`` attribute) parsed CenterPx with
    ``toInt()``, reading a fractional principal point as 0; current MeshLab (pymeshlab
    2025.7) reads it as a real number.

    References
    ----------
    .. [1] vcglib ``vcg/math/shot.h``: ``Shot::Project``, ``ConvertWorldToCameraCoordinates``.
    .. [2] vcglib ``vcg/math/camera.h``: ``Camera::Project``, ``LocalToViewportPx``,
       ``GetFrustum``.
    .. [3] vcglib ``wrap/qt/shot_qt.h``: ``ReadShotFromQDomNode``, ``WriteShotToQDomNode``;
       MeshLab ``src/meshlabplugins/io_base/load_project.cpp`` (``loadMLP``: the camera is
       the raster's first child, one ``<Plane>`` per raster).
    .. [4] MeshLab ``src/meshlabplugins/filter_color_projection/filter_color_projection.cpp``.
    """
    if not isinstance(raster, Raster):
        raise SlscanError(f"expected a Raster, got {type(raster).__name__}")
    m = raster.world_from_camera
    rotation = np.eye(4)
    rotation[:3, :3] = _FLIP_YZ @ m[:3, :3].T
    rotation = rotation + 0.0  # no "-0" in the file
    pixel_mm = _FILM_WIDTH_MM / raster.width
    focal_mm = raster.fx * pixel_mm
    return {
        "TranslationVector": _numbers([*(0.0 - m[:3, 3]), 1.0]),
        "RotationMatrix": _numbers(rotation.reshape(-1)),
        "FocalMm": _numbers([focal_mm]),
        "PixelSizeMm": _numbers([pixel_mm, focal_mm / raster.fy]),
        "CenterPx": _numbers([raster.cx + 0.5, raster.height - (raster.cy + 0.5)]),
        "ViewportPx": f"{raster.width} {raster.height}",
        "LensDistortion": "0 0",
        "CameraType": "0",
        "BinaryData": "0",
    }


def raster_from_vcg_camera(attributes: Mapping[str, str], *, label: str, image: str) -> Raster:
    """The :class:`Raster` of a ``<VCGCamera>``'s attributes (the inverse of :func:`vcg_camera`).

    Raises
    ------
    SlscanError
        A missing or malformed attribute, a camera that is not a perspective one without
        lens distortion, or values no camera can have (non-finite, non-positive sizes or
        focal length, a rotation that is not one); the message names the raster.
    """
    what = f"raster {label!r}"

    def numbers(name: str, count: int, *, at_least: bool = False) -> list[float]:
        text = attributes.get(name)
        if text is None:
            raise SlscanError(f"{what}: <VCGCamera> has no {name} attribute")
        try:
            values = [float(x) for x in text.split()]
        except ValueError:
            raise SlscanError(
                f"{what}: {name}={text!r} holds something that is not a number"
            ) from None
        if len(values) < count or (not at_least and len(values) != count):
            raise SlscanError(f"{what}: {name} has {len(values)} numbers; expected {count}")
        if not all(np.isfinite(values)):
            raise SlscanError(f"{what}: {name}={text!r} holds non-finite numbers")
        return values

    if attributes.get("BinaryData", "0").strip() not in ("0", ""):
        raise SlscanError(
            f"{what}: binary <VCGCamera> (BinaryData=1, .mlb projects) is not supported"
        )
    if attributes.get("CameraType", "0").strip() != "0":
        raise SlscanError(
            f"{what}: CameraType={attributes['CameraType']!r}; only perspective cameras (0) are supported"
        )
    if "LensDistortion" in attributes and any(numbers("LensDistortion", 2, at_least=True)):
        raise SlscanError(f"{what}: lens distortion is not supported; undistort the image first")
    translation = numbers("TranslationVector", 3, at_least=True)[:3]
    rotation = np.array(numbers("RotationMatrix", 16)).reshape(4, 4)
    if np.abs(rotation[3, :3]).max() > _RIGID_TOL or np.abs(rotation[:3, 3]).max() > _RIGID_TOL:
        raise SlscanError(
            f"{what}: RotationMatrix is not a rotation (its last row or column is not 0 0 0 1)"
        )
    (focal_mm,) = numbers("FocalMm", 1)
    pixel_x, pixel_y = numbers("PixelSizeMm", 2)
    center_x, center_y = numbers("CenterPx", 2)
    width_f, height_f = numbers("ViewportPx", 2)
    if not (width_f == int(width_f) and height_f == int(height_f) and width_f > 0 and height_f > 0):
        raise SlscanError(
            f"{what}: ViewportPx must be two positive integers, got {attributes['ViewportPx']!r}"
        )
    if not (focal_mm > 0 and pixel_x > 0 and pixel_y > 0):
        raise SlscanError(
            f"{what}: FocalMm and PixelSizeMm must be positive, got {focal_mm} and {pixel_x} {pixel_y}"
        )
    width, height = int(width_f), int(height_f)
    world_from_camera = np.eye(4)
    world_from_camera[:3, :3] = (_FLIP_YZ @ rotation[:3, :3]).T
    world_from_camera[:3, 3] = [-t for t in translation]
    return Raster(
        label=label,
        image=image,
        width=width,
        height=height,
        fx=focal_mm / pixel_x,
        fy=focal_mm / pixel_y,
        cx=center_x - 0.5,
        cy=height - center_y - 0.5,
        world_from_camera=world_from_camera + 0.0,
    )


# --- projects ----------------------------------------------------------------------------------


def format_mlp(
    entries: Sequence[tuple[str, str, np.ndarray]], *, rasters: Sequence[Raster] = ()
) -> str:
    """Text of a MeshLab project: ``entries`` are (label, file name, (4, 4) transform).

    rasters : registered images, written in ``<RasterGroup>`` (see :func:`vcg_camera`)

    Notes
    -----
    MeshLab's OpenGL paths have two faults of their own (pymeshlab 2025.7; its colour
    lookup is unaffected): vcglib's ``Camera::GetFrustum`` sets ``glFrustum`` left =
    −(ViewportPx.x − CenterPx.x), right = CenterPx.x, mirroring the principal point
    horizontally, so a raster's rendered view and the depth maps of the colour projection
    filters are shifted by 2·(CenterPx.x − ViewportPx.x / 2) px; and
    ``filter_color_projection`` renders its depth maps with the mesh's matrix applied
    twice. Either fails the depth test and leaves vertices black. Rasters undistorted to
    cx = (width − 1) / 2 and a model with the identity matrix avoid both; a warning is
    logged otherwise.
    """
    lines = ["<!DOCTYPE MeshLabDocument>", "<MeshLabProject>", " <MeshGroup>"]
    for label, filename, matrix in entries:
        m = np.asarray(matrix, np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise SlscanError(
                f"MeshLab project: transform of {label!r} must be a finite 4x4 matrix"
            )
        numbers = " ".join(f"{x:.17g}" for x in m.reshape(-1))
        lines += [
            f'  <MLMesh label="{_xml_attr(label)}" visible="1" filename="{_xml_attr(filename)}">',
            "   <MLMatrix44>",
            numbers + " ",
            "</MLMatrix44>",
            "  </MLMesh>",
        ]
    lines.append(" </MeshGroup>")
    _warn_meshlab_gl_faults(entries, rasters)
    if not rasters:
        lines.append(" <RasterGroup/>")
    else:
        lines.append(" <RasterGroup>")
        for raster in rasters:
            # MeshLab reads the raster's *first child* as its camera: VCGCamera goes first.
            camera = " ".join(f'{k}="{_xml_attr(v)}"' for k, v in vcg_camera(raster).items())
            lines += [
                f'  <MLRaster label="{_xml_attr(raster.label)}">',
                f"   <VCGCamera {camera}/>",
                f'   <Plane semantic="1" fileName="{_xml_attr(raster.image)}"/>',
                "  </MLRaster>",
            ]
        lines.append(" </RasterGroup>")
    lines += ["</MeshLabProject>", ""]
    return "\n".join(lines)


def write_mlp(
    path: str | os.PathLike,
    meshes: Sequence[tuple[str | os.PathLike, np.ndarray]],
    *,
    rasters: Sequence[Raster] = (),
) -> Path:
    """Write a MeshLab project naming existing mesh files, atomically.

    meshes : (mesh file, (4, 4) transform) pairs; a relative file name is relative to the
        project's folder (as MeshLab reads it), so pass paths relative to the current folder
        absolute; files are written relative to the project's folder when they lie under
        it, absolute otherwise
    rasters : registered images (their ``image`` names are written as they are: relative
        to the project's folder)
    """
    path = Path(path)
    base = path.parent.resolve()
    entries = []
    for file, matrix in meshes:
        file = Path(file)
        resolved = (base / file) if not file.is_absolute() else file
        try:
            name = resolved.resolve().relative_to(base).as_posix()
        except ValueError:
            name = str(resolved.resolve())
        entries.append((Path(name).name, name, matrix))
    text = format_mlp(entries, rasters=rasters)
    with atomic_output_file(path) as tmp:
        tmp.write_text(text)
    return path


def write_mesh_project(mesh: str | os.PathLike, project: str | os.PathLike | None = None) -> Path:
    """Write a MeshLab project opening one model, atomically: ``NAME.mlp`` beside ``NAME.ply``.

    The model keeps its own frame: the project's matrix is the identity. The fused and
    simplified meshes of the pipeline are written in the upright object frame (mm, y up;
    see :mod:`slscan.register.frame`), so MeshLab opens them upright, like the aligned set
    (``aligned.mlp``) and the textured model (``model.mlp``).

    mesh : the mesh file (it need not exist yet: the stages write both into a temporary
        folder); named in the project relative to the project's folder
    project : the project's path (default: ``mesh`` with the suffix ``.mlp``)
    """
    mesh = Path(mesh)
    project = Path(project) if project is not None else mesh.with_suffix(".mlp")
    if project.suffix.lower() != ".mlp" or project.resolve() == mesh.resolve():
        raise SlscanError(f"{project}: a MeshLab project must be a .mlp file beside its mesh {mesh.name}")
    return write_mlp(project, [(mesh.resolve(), np.eye(4))])


def write_scan_project(
    folder: str | os.PathLike,
    scans: Sequence[RangeScan],
    poses: Mapping[str, np.ndarray],
    *,
    project_name: str = "aligned.mlp",
    overwrite: bool = False,
) -> Path:
    """Write an aligned set: each scan as ``NAME.ply`` (scan frame, mm) and a project.

    The folder is written atomically (see :func:`slscan.fsio.atomic_output_dir`); scans
    without a pose are left out of it. Returns the project's path.
    """
    folder = Path(folder)
    missing = [s.name for s in scans if s.name not in poses]
    if missing:
        raise SlscanError(f"{folder}: no pose for scans {missing}")
    names = [s.name for s in scans]
    if len(set(names)) != len(names) or any(not n or "/" in n or "\\" in n for n in names):
        raise SlscanError(
            f"{folder}: scan names must be distinct, non-empty file names, got {names}"
        )
    with atomic_output_dir(folder, overwrite=overwrite) as tmp:
        entries = []
        for scan in scans:
            write_range_scan(scan, tmp / f"{scan.name}.ply")
            entries.append((scan.name, f"{scan.name}.ply", poses[scan.name]))
        (tmp / project_name).write_text(format_mlp(entries))
    return folder / project_name


def read_mlp(
    path: str | os.PathLike, *, check_files: bool = True, allow_outside: bool = False
) -> list[tuple[Path, np.ndarray]]:
    """Read a MeshLab project: [(mesh file path, (4, 4) float64 transform)], in order.

    Relative file names are resolved against the project's folder. A mesh without a
    ``MLMatrix44`` gets the identity. Rasters are read by :func:`read_mlp_rasters`.
    With ``check_files``, mesh files that resolve (symlinks followed) outside the
    project's folder are refused unless ``allow_outside``, and then named in a warning.

    Raises
    ------
    SlscanError
        Missing or malformed project, a bad or non-finite matrix, or (with ``check_files``)
        mesh files that do not exist or lie outside the project's folder (all of them named).
    """
    path = Path(path)
    root = _parse_project(path)
    out = []
    for mesh in root.iter("MLMesh"):
        filename = mesh.get("filename")
        if not filename:
            raise SlscanError(f"{path}: an <MLMesh> has no filename attribute")
        matrix = np.eye(4)
        node = mesh.find("MLMatrix44")
        if node is not None and (node.text or "").strip():
            try:
                values = [float(x) for x in node.text.split()]
            except ValueError:
                raise SlscanError(
                    f"{path}: MLMatrix44 of {filename!r} holds something that is not a number"
                ) from None
            if len(values) != 16:
                raise SlscanError(
                    f"{path}: MLMatrix44 of {filename!r} has {len(values)} numbers; expected 16"
                )
            matrix = np.array(values).reshape(4, 4)
            if not np.isfinite(matrix).all():
                raise SlscanError(f"{path}: MLMatrix44 of {filename!r} holds non-finite numbers")
        file = Path(filename)
        out.append((file if file.is_absolute() else path.parent / file, matrix))
    if check_files:
        missing = [str(f) for f, _ in out if not f.is_file()]
        if missing:
            raise SlscanError(
                f"{path}: the project names mesh files that do not exist: {', '.join(missing)}"
            )
        _check_outside(path, [f for f, _ in out], "mesh", allow_outside)
    return out


def _check_outside(
    path: Path, files: Sequence[Path], what: str, allow_outside: bool, *, owner: str = "project"
) -> None:
    """Refuse (or, with ``allow_outside``, warn about) ``files`` of project ``path`` (the
    ``owner``: a project, a .conf) that resolve outside its folder."""
    base = path.parent.resolve()
    outside = [str(f) for f in files if not Path(f).resolve().is_relative_to(base)]
    if not outside:
        return
    if not allow_outside:
        raise SlscanError(
            f"{path}: the {owner} names {what} files outside its folder: {', '.join(outside)} "
            "(pass --allow-outside to read them)"
        )
    log.warning("%s: reading %s files outside the %s's folder: %s", path, what, owner, ", ".join(outside))


def read_mlp_rasters(
    path: str | os.PathLike, *, check_files: bool = True, allow_outside: bool = False
) -> list[Raster]:
    """Read the rasters of a MeshLab project, in order (the inverse of ``rasters=`` in :func:`write_mlp`).

    Each ``Raster.image`` is the file name as the project has it (relative to the
    project's folder, or absolute); a raster with several planes keeps the first, as
    MeshLab does. Projects saved by MeshLab read too (at the 6 significant digits it
    writes).

    Raises
    ------
    SlscanError
        Missing or malformed project, a raster without camera or image, a camera that
        is not an undistorted perspective one or holds impossible values, or (with
        ``check_files``) image files that do not exist (all of them named).
    """
    path = Path(path)
    root = _parse_project(path)
    out = []
    for k, node in enumerate(root.iter("MLRaster")):
        label = node.get("label", f"raster {k}")
        camera = node.find("VCGCamera")
        if camera is None:
            raise SlscanError(f"{path}: raster {label!r} has no <VCGCamera>")
        plane = node.find("Plane")
        image = plane.get("fileName") if plane is not None else None
        if not image:
            raise SlscanError(f"{path}: raster {label!r} has no <Plane fileName=...> image")
        try:
            out.append(raster_from_vcg_camera(camera.attrib, label=label, image=image))
        except SlscanError as exc:
            raise SlscanError(f"{path}: {exc}") from None
    if check_files:
        missing = [r.image for r in out if not (path.parent / r.image).is_file()]
        if missing:
            raise SlscanError(
                f"{path}: the project names image files that do not exist: {', '.join(missing)}"
            )
        _check_outside(path, [path.parent / r.image for r in out], "image", allow_outside)
    return out


def load_scan_project(
    path: str | os.PathLike, *, allow_outside: bool = False
) -> tuple[list[RangeScan], dict[str, np.ndarray]]:
    """Scans and world_from_scan poses (mm) of a MeshLab project of range scans.

    Scans are named by their file stems, which must be distinct. Mesh files outside the
    project's folder are read only with ``allow_outside`` (see :func:`read_mlp`).
    """
    scans, poses = [], {}
    for file, matrix in read_mlp(path, allow_outside=allow_outside):
        scan = load_range_scan(file)
        if scan.name in poses:
            raise SlscanError(f"{path}: two meshes are named {scan.name!r}")
        scans.append(scan)
        poses[scan.name] = matrix
    if not scans:
        raise SlscanError(f"{path}: the project lists no meshes")
    return scans, poses


def iter_scan_project(
    path: str | os.PathLike, *, allow_outside: bool = False
) -> Iterator[tuple[RangeScan, np.ndarray]]:
    """:func:`load_scan_project` one scan at a time: (scan, (4, 4) world_from_scan, mm) in the
    project's order, each mesh file read only when its turn comes (the caller may drop a
    scan before the next is read). The project itself is read, and its mesh files checked
    to exist, before the first is yielded; a file that turns out broken is a
    :class:`SlscanError` naming it when its turn comes."""
    entries = read_mlp(path, allow_outside=allow_outside)
    if not entries:
        raise SlscanError(f"{path}: the project lists no meshes")
    names: set[str] = set()
    for file, matrix in entries:
        scan = load_range_scan(file)
        if scan.name in names:
            raise SlscanError(f"{path}: two meshes are named {scan.name!r}")
        names.add(scan.name)
        yield scan, matrix
        del scan  # not held while the next one is read


def _xml_attr(text: str) -> str:
    return (
        str(text)
        .replace("&", "&amp;")
        .replace('"', "&quot;")
        .replace("<", "&lt;")
        .replace(">", "&gt;")
    )


def _warn_meshlab_gl_faults(
    entries: Sequence[tuple[str, str, np.ndarray]], rasters: Sequence[Raster]
) -> None:
    """Log where MeshLab's OpenGL depth test will go wrong (see :func:`format_mlp`)."""
    if not rasters:
        return
    moved = [label for label, _, m in entries if not np.allclose(m, np.eye(4), rtol=0, atol=1e-12)]
    if moved:
        log.warning(
            "MeshLab project: meshes %s have a matrix; MeshLab's colour projection from "
            "rasters applies it twice in its depth maps and leaves vertices black: write "
            "the model in the world frame (or Freeze Matrix in MeshLab) before projecting",
            moved,
        )
    off = {
        r.label: round(r.cx + 0.5 - r.width / 2, 2)
        for r in rasters
        if isinstance(r, Raster) and abs(r.cx + 0.5 - r.width / 2) > 0.25
    }
    if off:
        log.warning(
            "MeshLab project: rasters with the principal point off the image centre in x "
            "(label: px) %s; MeshLab mirrors it when it renders a raster's view and depth "
            "maps (vcglib Camera::GetFrustum), shifting them by twice that: undistort the "
            "images to cx = (width - 1) / 2 for MeshLab's colour projection and overlays",
            off,
        )


def _parse_project(path: Path) -> ET.Element:
    try:
        root = ET.fromstring(path.read_text())
    except FileNotFoundError:
        raise SlscanError(f"{path}: MeshLab project not found") from None
    except (ET.ParseError, UnicodeDecodeError) as exc:
        raise SlscanError(f"{path}: not a MeshLab project ({exc})") from None
    if root.tag != "MeshLabProject":
        raise SlscanError(f"{path}: root element is <{root.tag}>; expected <MeshLabProject>")
    return root


def _numbers(values) -> str:
    return " ".join(repr(float(v)) for v in values)
