"""Capture sessions on disk: what a real or virtual rig writes, and all later stages read.

Layout (full description in ``docs/capture-session.md``)::

    SESSION/
      session.json            metadata: devices, calibration, pattern set, views, images
      view_000/
        00_white.png ...      captures, 8 or 16 bit, grey or RGB: PNG, or JPEG/TIFF as
                              imported from another tool (``camera.lossy`` says so)
        ground_truth.npz      virtual rig only: per-pixel truth

Everything downstream reads sessions through :func:`load_session`, never simulator
internals, so real captures drop in.
"""

from __future__ import annotations

import functools
import os
import shutil
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import numpy as np

from slscan import __version__
from slscan.errors import SlscanError, about_file
from slscan.fsio import (
    Prefetched,
    atomic_output_dir,
    read_json,
    read_png,
    write_jpeg,
    write_json,
    write_png,
)
from slscan.patterns import PatternImage
from slscan.rig import Rig, _as_pose

SESSION_FORMAT = "slscan.capture-session"
SESSION_VERSION = 1
SESSION_FILE = "session.json"
IMAGE_KINDS = ("pattern", "lit")
ROTATIONS = (0, 90, 180, 270)
IMAGE_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".tif": "tiff", ".tiff": "tiff"}
"""Capture file extensions (lower case) a session may hold, and their format."""

# ground-truth visibility labels
BACKGROUND, SHADOW, LIT = 0, 1, 2
VISIBILITY_LABELS = {BACKGROUND: "background", SHADOW: "projector shadow", LIT: "lit"}


@dataclass(frozen=True)
class ImageRecord:
    """One captured image of a view.

    file : name inside the view folder
    kind : {"pattern", "lit"}; "pattern" is lit by the projector showing ``pattern``,
        "lit" by ring light ``light`` with the projector dark
    """

    file: str
    kind: str
    pattern: str | None = None
    light: int | None = None

    def to_dict(self) -> dict:
        d: dict[str, Any] = {"file": self.file, "kind": self.kind}
        if self.pattern is not None:
            d["pattern"] = self.pattern
        if self.light is not None:
            d["light"] = self.light
        return d


@dataclass(frozen=True)
class ViewRecord:
    """One range map's worth of images.

    rig_from_object : (4, 4) mm or None, the scanned object's pose in the rig frame
    pose_source : e.g. "ground-truth" (virtual rig), "turntable", or None
    exposure : free-form capture settings (exposure time factor, gain, ...)
    ground_truth : name of the view's ground-truth file, or None
    turntable_deg : the angle a turntable stage was turned to for this view (degrees, the
        controller's own zero), or None (no turntable)
    """

    name: str
    images: tuple[ImageRecord, ...]
    rig_from_object: np.ndarray | None = None
    pose_source: str | None = None
    exposure: dict = field(default_factory=dict)
    ground_truth: str | None = None
    turntable_deg: float | None = None

    def pattern_images(self) -> list[ImageRecord]:
        return [r for r in self.images if r.kind == "pattern"]

    def lit_images(self) -> list[ImageRecord]:
        return sorted((r for r in self.images if r.kind == "lit"), key=lambda r: r.light)

    def image_for(self, pattern_id: str) -> ImageRecord:
        for rec in self.images:
            if rec.pattern == pattern_id:
                return rec
        raise SlscanError(f"view {self.name}: no image of pattern {pattern_id!r}")

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "rig_from_object": None if self.rig_from_object is None else self.rig_from_object.tolist(),
            "pose_source": self.pose_source,
            "exposure": self.exposure,
            "ground_truth": self.ground_truth,
            **({} if self.turntable_deg is None else {"turntable_deg": self.turntable_deg}),
            "images": [r.to_dict() for r in self.images],
        }


def _turntable_deg(value, where: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise SlscanError(f"{where}: turntable_deg must be a number of degrees, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Session:
    """A capture session read from (or about to be written to) ``root``.

    camera_size, projector_size : (width, height) px
    channels : 1 (grey) or 3 (RGB); bit_depth : 8 or 16
    calibration : the rig's calibration when known (the virtual rig writes its truth)
    lossy : the captures went through lossy compression (JPEG, imported as they were)
    response : the camera's tone curve, ``"linear"`` (RAW-like: values proportional to
        light) or ``"srgb"`` (the sRGB curve most cameras apply before saving JPEG);
        decoders read captures through :meth:`Session.read_image` ``(linear=True)``, which
        undoes it
    response_fit : how ``response`` was found when it was measured from the captures
        (``slscan import``: :class:`slscan.capture.response.ResponseFit` as a dict, plus
        ``source``: "measured" or "given"); empty when the capture recorded it
    projector_rotation : {0, 90, 180, 270} degrees the projector is turned about its axis
        relative to the camera; with 90 or 270 its column stripes appear horizontal in the
        captures (see :meth:`camera_axis`)
    """

    root: Path
    camera_size: tuple[int, int]
    projector_size: tuple[int, int]
    channels: int
    bit_depth: int
    patterns: tuple[PatternImage, ...]
    views: tuple[ViewRecord, ...]
    calibration: Rig | None = None
    calibration_source: str | None = None
    device: dict = field(default_factory=dict)
    lossy: bool = False
    projector_rotation: int = 0
    response: str = "linear"
    response_fit: dict = field(default_factory=dict)

    def camera_axis(self, axis: str) -> str:
        """The camera image axis, ``"x"`` (along rows) or ``"y"`` (along columns), that
        the stripes of patterns varying along projector ``axis`` ("columns" or "rows")
        cross: where to search their edges."""
        if axis not in ("columns", "rows"):
            raise SlscanError(f"pattern axis must be 'columns' or 'rows', got {axis!r}")
        turned = self.projector_rotation in (90, 270)
        return "x" if (axis == "columns") != turned else "y"

    def pattern(self, pattern_id: str) -> PatternImage:
        for p in self.patterns:
            if p.id == pattern_id:
                return p
        raise SlscanError(f"{self.root / SESSION_FILE}: no pattern with id {pattern_id!r}")

    def flat_frame_ids(self, purpose: str = "decoding") -> tuple[str, str]:
        """Ids of the all-white and all-black frames of the pattern set (the first of each)."""
        white = black = None
        for p in self.patterns:
            if p.family == "flat":
                value = list(p.params.get("value", []))
                if value == [255, 255, 255] and white is None:
                    white = p.id
                elif value == [0, 0, 0] and black is None:
                    black = p.id
        if white is None or black is None:
            missing = "white" if white is None else "black"
            raise SlscanError(f"{self.root}: the pattern set has no all-{missing} frame; {purpose} needs one")
        return white, black

    def view(self, name: str) -> ViewRecord:
        for v in self.views:
            if v.name == name:
                return v
        raise SlscanError(f"{self.root}: no view named {name!r}")

    def image_path(self, view: ViewRecord, rec: ImageRecord) -> Path:
        return self.root / view.name / rec.file

    def read_image(self, view: ViewRecord, rec: ImageRecord, *, linear: bool = False) -> np.ndarray:
        """Read one capture, checking it against the session's size, channels and depth.

        linear : undo the camera's tone curve (:attr:`response`) for measuring light: an
            sRGB session's captures come back as float32 fractions of full scale through
            :func:`linearise`; a linear session's as stored (decoders take both)
        """
        path = self.image_path(view, rec)
        image = read_capture(path)
        _check_image(path, image.shape, image.dtype.itemsize * 8, self)
        return linearise(image, self.response) if linear else image

    def prefetch_images(self, view: ViewRecord, records: Sequence[ImageRecord], *,
                        linear: bool = False) -> Prefetched:
        """The captures ``records`` of ``view`` by pattern id, read (and checked like
        :meth:`read_image`, ``linear`` likewise) in that order by a background thread;
        use it in a ``with`` block."""
        by_id = {rec.pattern: rec for rec in records}
        return Prefetched(lambda pid: self.read_image(view, by_id[pid], linear=linear), list(by_id))

    def load_ground_truth(self, view: ViewRecord) -> GroundTruth:
        if view.ground_truth is None:
            raise SlscanError(f"{self.root / view.name}: this view has no ground truth (only the virtual rig writes it)")
        return GroundTruth.load(self.root / view.name / view.ground_truth)

    def to_dict(self) -> dict:
        return {
            "format": SESSION_FORMAT,
            "version": SESSION_VERSION,
            "written_by": f"slscan {__version__}",
            "device": self.device,
            "camera": {
                "width": self.camera_size[0], "height": self.camera_size[1],
                "channels": self.channels, "bit_depth": self.bit_depth, "lossy": self.lossy,
                "response": self.response,
                **({"response_fit": self.response_fit} if self.response_fit else {}),
            },
            "projector": {
                "width": self.projector_size[0], "height": self.projector_size[1],
                "rotation": self.projector_rotation,
            },
            "calibration": None if self.calibration is None else {
                "source": self.calibration_source, **self.calibration.to_dict()
            },
            "patterns": [p.to_dict() for p in self.patterns],
            "views": [v.to_dict() for v in self.views],
        }


@dataclass(frozen=True)
class GroundTruth:
    """Per-pixel truth of one virtual-rig view, all (h, w, ...) over camera pixels.

    point : (h, w, 3) float32 mm, rig frame; NaN on background
    normal : (h, w, 3) float32, unit, rig frame; NaN on background
    albedo : (h, w, 3) float32 linear RGB reflectance in [0, 1]; NaN on background
    projector_uv : (h, w, 2) float32 continuous projector pixel (column, row) of the
        surface point seen at each camera pixel centre; NaN on background
    visibility : (h, w) uint8: 0 background, 1 in projector shadow (or outside its
        frustum, or facing away), 2 lit by the projector
    """

    point: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    projector_uv: np.ndarray
    visibility: np.ndarray

    def column_crossings(
        self, rows: np.ndarray, x: np.ndarray, columns: np.ndarray, reach: int = 3
    ) -> np.ndarray:
        """(k,) camera x where the true projector column, linear between pixel centres,
        rises through ``columns`` (k,) on camera row ``rows`` (k,), searched within
        ``reach`` px of ``x`` (k,) — the true position of a measured stripe sample; NaN
        where it does not cross there."""
        u = self.projector_uv[..., 0].astype(np.float64)
        rows, columns = np.asarray(rows), np.asarray(columns, np.float64)
        true_x = np.full(len(rows), np.nan)
        start = np.round(np.asarray(x)).astype(int) - reach
        for o in range(2 * reach + 1):
            xi = np.clip(start + o, 0, u.shape[1] - 2)
            ua, ub = u[rows, xi], u[rows, xi + 1]
            hit = (ua <= columns) & (columns < ub) & np.isnan(true_x)
            true_x = np.where(hit, xi + (columns - ua) / (ub - ua), true_x)
        return true_x

    def save(self, path: str | os.PathLike) -> None:
        from slscan.fsio import atomic_output_file

        path = Path(path)
        path = path if path.suffix == ".npz" else path.with_name(path.name + ".npz")  # as numpy names it
        with atomic_output_file(path) as tmp:  # flushed and checked; a full disk names the file
            np.savez_compressed(
                tmp, point=self.point, normal=self.normal, albedo=self.albedo,
                projector_uv=self.projector_uv, visibility=self.visibility,
            )

    @classmethod
    def load(cls, path: str | os.PathLike) -> GroundTruth:
        path = Path(path)
        if not path.is_file():
            raise SlscanError(f"{path}: ground-truth file not found")
        try:
            with np.load(path, allow_pickle=False) as data:
                return cls(**{k: data[k] for k in ("point", "normal", "albedo", "projector_uv", "visibility")})
        except KeyError as exc:
            raise SlscanError(f"{path}: ground truth lacks array {exc.args[0]!r}") from None
        except (OSError, ValueError) as exc:
            raise SlscanError(f"{path}: not a readable ground-truth file ({exc})") from None


def png_header(path: Path, *, check_chunks: bool = False) -> tuple[int, int, int, int]:
    """(width, height, channels, bit_depth) from a PNG's IHDR without decoding pixels.

    With ``check_chunks``, also walk the file's chunks and check each one's CRC up to
    ``IEND`` (no decompression): a truncated or corrupted file is refused, naming it.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(29)
            if check_chunks and len(head) == 29:
                _check_png_chunks(path, f)
    except FileNotFoundError:
        raise SlscanError(f"{path}: image not found") from None
    except IsADirectoryError:
        raise SlscanError(f"{path}: is a folder; expected a PNG image") from None
    except OSError as exc:
        raise SlscanError(f"{path}: cannot read the image ({exc.strerror})") from None
    if len(head) < 29 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise SlscanError(f"{path}: not a PNG file")
    width, height, depth, color_type = struct.unpack(">IIBB", head[16:26])
    if width == 0 or height == 0:
        raise SlscanError(f"{path}: PNG header gives a {width}x{height} image")
    channels = {0: 1, 2: 3, 4: 2, 6: 4, 3: 3}.get(color_type, 0)
    return width, height, channels, depth


def image_format(path: Path) -> str:
    """{"png", "jpeg", "tiff"}: a capture's format from its extension; raise naming others."""
    fmt = IMAGE_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise SlscanError(
            f"{path}: not a capture file; expected PNG, JPEG or TIFF "
            f"({', '.join(sorted(IMAGE_FORMATS))})"
        )
    return fmt


def image_header(path: Path, *, check: bool = False) -> tuple[int, int, int, int]:
    """(width, height, channels, bit_depth) of a PNG, JPEG or TIFF capture, from its header
    only (no pixels decoded). With ``check``, a PNG's chunk CRCs are checked and a JPEG
    must end with its end-of-image marker (a truncated file is refused, naming it)."""
    if image_format(path) == "png":
        return png_header(path, check_chunks=check)
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            width, height = im.size
            if im.format == "TIFF":
                samples = int(im.tag_v2.get(277, 1))
                depth = im.tag_v2.get(258, (8,))
                depth = int(depth[0] if isinstance(depth, tuple) else depth)
            else:
                samples = {"L": 1, "RGB": 3, "RGBA": 4}.get(im.mode, 0)
                depth = 8
            if check and im.format == "JPEG":
                _check_jpeg_end(path)
    except FileNotFoundError:
        raise SlscanError(f"{path}: image not found") from None
    except IsADirectoryError:
        raise SlscanError(f"{path}: is a folder; expected an image") from None
    except UnidentifiedImageError:
        raise SlscanError(f"{path}: not a readable {image_format(path).upper()} image") from None
    except OSError as exc:
        if "truncated" in str(exc).lower():
            raise SlscanError(f"{path}: {image_format(path).upper()} file is truncated") from None
        raise SlscanError(f"{path}: cannot read the image ({exc})") from None
    return width, height, samples, depth


def _check_jpeg_end(path: Path) -> None:
    with open(path, "rb") as f:
        f.seek(max(0, os.fstat(f.fileno()).st_size - 1024))
        if b"\xff\xd9" not in f.read():
            raise SlscanError(f"{path}: JPEG file is truncated (no end-of-image marker)")


RESPONSES = ("linear", "srgb")
"""Camera tone curves a session records (``camera.response``)."""


@functools.lru_cache(maxsize=4)
def _srgb_lut(top: int) -> np.ndarray:
    """The inverse sRGB curve (IEC 61966-2-1) of the codes 0..top, float32 fractions of
    full scale; code ``top`` maps to exactly 1.0 (clipping stays detectable)."""
    v = np.arange(top + 1, dtype=np.float64) / top
    lin = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    lin[-1] = 1.0
    return lin.astype(np.float32)


def linearise(image: np.ndarray, response: str) -> np.ndarray:
    """A capture with the camera's tone curve undone: ``"srgb"`` gives float32 fractions
    of full scale in [0, 1] (an integer capture through a lookup table: full scale from
    its dtype); ``"linear"`` returns ``image`` itself."""
    if response == "linear":
        return image
    if response != "srgb":
        raise SlscanError(f"camera response must be one of {', '.join(RESPONSES)}, got {response!r}")
    image = np.asarray(image)
    if image.dtype in (np.uint8, np.uint16):
        return _srgb_lut(int(np.iinfo(image.dtype).max))[image]
    if np.issubdtype(image.dtype, np.floating):
        v = np.clip(image, 0, 1).astype(np.float32)
        return np.where(v <= 0.04045, v / np.float32(12.92),
                        ((v + np.float32(0.055)) / np.float32(1.055)) ** np.float32(2.4)).astype(np.float32)
    raise SlscanError(f"cannot linearise {image.dtype} pixels; expected uint8, uint16 or float in [0, 1]")


def read_capture(path: Path) -> np.ndarray:
    """A capture as stored: (h, w) grey or (h, w, 3) RGB, uint8 or uint16. PNG through
    :func:`~slscan.fsio.read_png`; JPEG and TIFF decoded by OpenCV as they are (EXIF
    orientation ignored, like the header sizes)."""
    if image_format(path) == "png":
        return read_png(path)
    import cv2

    if not Path(path).is_file():
        raise SlscanError(f"{path}: image not found")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SlscanError(f"{path}: not a readable {image_format(path).upper()} image")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return image


def _check_png_chunks(path: Path, f) -> None:
    """Walk the chunks of PNG file ``f`` (positioned anywhere) from the signature to ``IEND``,
    checking lengths and CRCs; raise naming ``path`` when it is truncated or corrupted."""
    size = os.fstat(f.fileno()).st_size
    f.seek(8)
    has_data = False
    while True:
        head = f.read(8)
        if len(head) < 8:
            raise SlscanError(f"{path}: PNG file is truncated (no IEND chunk)")
        length, kind = struct.unpack(">I4s", head)
        if f.tell() + length + 4 > size:  # checked before reading: a damaged length may be huge
            raise SlscanError(f"{path}: PNG file is truncated (in a {kind.decode('latin-1')!r} chunk)")
        body = f.read(length + 4)
        if zlib.crc32(kind + body[:length]) != struct.unpack(">I", body[length:])[0]:
            raise SlscanError(f"{path}: PNG file is corrupted (bad CRC in a {kind.decode('latin-1')!r} chunk)")
        has_data |= kind == b"IDAT"
        if kind == b"IEND":
            break
    if not has_data:
        raise SlscanError(f"{path}: PNG file has no image data (IDAT chunk)")


def _check_image(path: Path, shape: tuple, depth: int, session: Session) -> None:
    h, w = shape[:2]
    channels = 1 if len(shape) == 2 else shape[2]
    if (w, h) != session.camera_size:
        raise SlscanError(
            f"{path}: image is {w}x{h}, the session's camera is {session.camera_size[0]}x{session.camera_size[1]}"
        )
    if channels != session.channels and not (session.channels == 3 and channels == 4):
        raise SlscanError(f"{path}: image has {channels} channel(s), the session says {session.channels}")
    if depth != session.bit_depth:
        raise SlscanError(f"{path}: image is {depth}-bit, the session says {session.bit_depth}-bit")


def validate_session(session: Session) -> None:
    """Check that every image exists and matches the metadata; raise naming the first bad file."""
    pattern_ids = {p.id for p in session.patterns}
    for view in session.views:
        for rec in view.images:
            if rec.kind == "pattern" and rec.pattern not in pattern_ids:
                raise SlscanError(f"{session.root / view.name / rec.file}: unknown pattern {rec.pattern!r}")
            if (rec.kind == "lit" and session.calibration is not None and session.calibration.lights
                    and not 0 <= rec.light < len(session.calibration.lights)):
                raise SlscanError(f"{session.root / view.name / rec.file}: light {rec.light} is not in the rig")
            path = session.image_path(view, rec)
            w, h, channels, depth = image_header(path, check=True)
            shape = (h, w) if channels == 1 else (h, w, channels)
            _check_image(path, shape, depth, session)


def _check_consistent(session: Session, meta_path: Path) -> None:
    """The calibration and pattern sizes must agree with the camera and projector blocks."""
    cal = session.calibration
    if cal is not None:
        if (cal.camera.width, cal.camera.height) != session.camera_size:
            raise SlscanError(
                f"{meta_path}: calibration is for a {cal.camera.width}x{cal.camera.height} camera, "
                f"the images are {session.camera_size[0]}x{session.camera_size[1]}"
            )
        lens = cal.projector.lens
        if (lens.width, lens.height) != session.projector_size:
            raise SlscanError(
                f"{meta_path}: calibration is for a {lens.width}x{lens.height} projector, "
                f"the session's projector is {session.projector_size[0]}x{session.projector_size[1]}"
            )
    for p in session.patterns:
        if (p.width, p.height) != session.projector_size:
            raise SlscanError(
                f"{meta_path}: pattern {p.id!r} is {p.width}x{p.height}, the projector is "
                f"{session.projector_size[0]}x{session.projector_size[1]}"
            )


def _check_unique_names(session: Session, meta_path: Path) -> None:
    """Each view's name must be distinct: every output is named for its view, and a second
    view of one name would silently replace the first's range map, albedo and mesh."""
    seen: dict[str, int] = {}
    for i, view in enumerate(session.views):
        if not isinstance(view.name, str) or not view.name:
            raise SlscanError(f"{meta_path}: views[{i}].name: expected a non-empty string, got {view.name!r}")
        if view.name in seen:
            raise SlscanError(
                f"{meta_path}: views[{i}].name: {view.name!r} is also the name of views[{seen[view.name]}]; "
                "expected distinct view names (each names its folder and its outputs)"
            )
        seen[view.name] = i


def _check_inside(session: Session, meta_path: Path) -> None:
    """Every file the session names must resolve (symlinks followed) inside its folder."""
    root = session.root.resolve()
    outside = []
    for view in session.views:
        names = [rec.file for rec in view.images] + ([view.ground_truth] if view.ground_truth else [])
        for name in names:
            if not (session.root / view.name / name).resolve().is_relative_to(root):
                outside.append(f"{view.name}/{name}")
    if outside:
        shown = ", ".join(outside[:3]) + (f" and {len(outside) - 3} more" if len(outside) > 3 else "")
        raise SlscanError(
            f"{meta_path}: {len(outside)} image file(s) resolve outside the session folder: {shown}; "
            "expected files inside it"
        )


def locate_metadata(path: str | os.PathLike, file_name: str, kind: str) -> tuple[Path, Path]:
    """The folder and its metadata file ``file_name``, given either of them.

    Raises
    ------
    SlscanError
        When the folder does not exist (``kind`` names what it should be).
    """
    root = Path(path)
    meta = root / file_name
    if root.is_file() and root.name == file_name:
        root, meta = root.parent, root
    if not root.is_dir():
        raise SlscanError(f"{root}: {kind} folder not found")
    return root, meta


def load_session(path: str | os.PathLike, *, validate: bool = True) -> Session:
    """Read ``session.json`` in folder ``path`` (and check its images unless ``validate=False``)."""
    root, meta_path = locate_metadata(path, SESSION_FILE, "capture-session")
    with about_file(meta_path, "capture-session metadata (session.json)"):
        session = _read_session(root, meta_path)
    if validate:
        validate_session(session)
    return session


def _read_session(root: Path, meta_path: Path) -> Session:
    d = read_json(meta_path, "capture-session metadata (session.json)")
    if not isinstance(d, dict):
        raise SlscanError(f"{meta_path}: expected a JSON object (an slscan capture session)")
    if d.get("format") != SESSION_FORMAT:
        raise SlscanError(f"{meta_path}: not an slscan capture session (format {d.get('format')!r})")
    if d.get("version") != SESSION_VERSION:
        raise SlscanError(
            f"{meta_path}: session format version {d.get('version')} is not supported (this slscan reads {SESSION_VERSION})"
        )
    try:
        cam, proj = d["camera"], d["projector"]
        calibration = source = None
        if d.get("calibration"):
            calibration = Rig.from_dict(d["calibration"])
            source = d["calibration"].get("source")
        views = []
        for v in d["views"]:
            images = tuple(
                ImageRecord(r["file"], r["kind"], r.get("pattern"), r.get("light")) for r in v["images"]
            )
            for r in images:
                if r.kind not in IMAGE_KINDS:
                    raise SlscanError(f"{meta_path}: view {v['name']}: image {r.file} has unknown kind {r.kind!r}")
                if r.kind == "pattern" and not isinstance(r.pattern, str):
                    raise SlscanError(f"{meta_path}: view {v['name']}: pattern image {r.file} names no pattern")
                if r.kind == "lit" and not isinstance(r.light, int):
                    raise SlscanError(f"{meta_path}: view {v['name']}: lit image {r.file} names no light index")
            pose = v.get("rig_from_object")
            views.append(
                ViewRecord(
                    v["name"], images,
                    None if pose is None else _as_pose(pose, f"{meta_path}: view {v['name']} pose"),
                    v.get("pose_source"), v.get("exposure", {}), v.get("ground_truth"),
                    _turntable_deg(v.get("turntable_deg"), f"{meta_path}: view {v['name']}"),
                )
            )
        session = Session(
            root=root,
            camera_size=(int(cam["width"]), int(cam["height"])),
            projector_size=(int(proj["width"]), int(proj["height"])),
            channels=int(cam.get("channels", 3)),
            bit_depth=int(cam.get("bit_depth", 8)),
            patterns=tuple(PatternImage.from_dict(p) for p in d["patterns"]),
            views=tuple(views),
            calibration=calibration,
            calibration_source=source,
            device=d.get("device", {}),
            lossy=bool(cam.get("lossy", False)),
            projector_rotation=int(proj.get("rotation", 0)),
            response=str(cam.get("response", "linear")),  # sessions older than the field: linear
            response_fit=dict(cam.get("response_fit") or {}),
        )
    except KeyError as exc:
        raise SlscanError(f"{meta_path}: missing field {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise SlscanError(f"{meta_path}: a field has the wrong type ({exc})") from None
    if session.channels not in (1, 3) or session.bit_depth not in (8, 16):
        raise SlscanError(f"{meta_path}: camera must have 1 or 3 channels and 8 or 16 bits")
    if session.response not in RESPONSES:
        raise SlscanError(
            f"{meta_path}: camera.response must be one of {', '.join(RESPONSES)}, got {session.response!r}"
        )
    if session.projector_rotation not in ROTATIONS:
        raise SlscanError(
            f"{meta_path}: projector rotation {session.projector_rotation} is not one of {ROTATIONS} (degrees)"
        )
    _check_consistent(session, meta_path)
    _check_unique_names(session, meta_path)
    _check_inside(session, meta_path)
    return session


def write_capture(path: Path, image: np.ndarray, *, bit_depth: int, jpeg_quality: int | None) -> None:
    """Write one capture as the session stores it: a JPEG when ``path`` is named so (at
    ``jpeg_quality``), else a lossless PNG; its pixels must be of the session's depth."""
    expected_dtype = np.uint8 if bit_depth == 8 else np.uint16
    if image.dtype != expected_dtype:
        raise SlscanError(f"{path.name}: expected {expected_dtype.__name__} pixels, got {image.dtype}")
    if image_format(path) == "jpeg":
        if jpeg_quality is None:
            raise SlscanError(f"{path.name}: a JPEG capture, but the writer has no jpeg_quality")
        write_jpeg(path, image, jpeg_quality)
    else:
        write_png(path, image)


class SessionWriter:
    """Write a capture session view by view.

    By default the whole session is written into a temporary folder, renamed into place
    at the end: if the block raises, nothing is left at ``out``. With ``incremental=True``
    (live scans) ``out`` is created at once and each view is written into a hidden
    ``.view_NNN.partial`` folder, renamed to ``view_NNN`` when complete, and then added to
    ``session.json`` (rewritten atomically): an interrupted scan keeps every finished view,
    and ``resume=True`` reopens such a session (same devices and patterns) to add more::

        with SessionWriter(out, camera_size=..., ...) as writer:
            folder = writer.view_folder("view_000")
            writer.write_image("view_000", record, image)
            writer.add_view(ViewRecord("view_000", ...))

    ``jpeg_quality`` (1–100) saves captures named ``.jpg`` as JPEG at that quality (a
    camera that shoots JPEG) and marks the session lossy; ``response`` records the
    camera's tone curve (``camera.response``: "linear" or "srgb"), ``response_fit`` how
    it was measured (``camera.response_fit``, see :class:`Session`).
    """

    def __init__(
        self,
        out: str | os.PathLike,
        *,
        camera_size: tuple[int, int],
        projector_size: tuple[int, int],
        channels: int,
        bit_depth: int,
        patterns: list[PatternImage],
        calibration: Rig | None = None,
        calibration_source: str | None = None,
        device: dict | None = None,
        overwrite: bool = False,
        incremental: bool = False,
        resume: bool = False,
        lossy: bool = False,
        projector_rotation: int = 0,
        jpeg_quality: int | None = None,
        response: str = "linear",
        response_fit: dict | None = None,
    ) -> None:
        if response not in RESPONSES:
            raise SlscanError(f"camera response must be one of {', '.join(RESPONSES)}, got {response!r}")
        self.out = Path(out)
        self._jpeg_quality = jpeg_quality
        lossy = lossy or jpeg_quality is not None
        self._meta = {
            "camera_size": tuple(camera_size), "projector_size": tuple(projector_size), "channels": channels,
            "bit_depth": bit_depth, "patterns": tuple(patterns), "calibration": calibration,
            "calibration_source": calibration_source, "device": device or {},
            "lossy": bool(lossy), "projector_rotation": int(projector_rotation), "response": response,
            "response_fit": dict(response_fit or {}),
        }
        self._overwrite = overwrite
        self._incremental = incremental or resume
        self._resume = resume
        self._views: list[ViewRecord] = []
        self._ctx = None
        self._created = False  # incremental: this writer made ``out``
        self.tmp: Path | None = None

    @property
    def views(self) -> tuple[ViewRecord, ...]:
        """The views written so far (with ``resume``, those found in the session too)."""
        return tuple(self._views)

    def __enter__(self) -> Self:
        if not self._incremental:
            self._ctx = atomic_output_dir(self.out, overwrite=self._overwrite)
            self.tmp = self._ctx.__enter__()
            return self
        self.tmp = self.out
        meta = self.out / SESSION_FILE
        if self._resume and meta.is_file():
            old = load_session(self.out)
            self._check_resumable(old, meta)
            self._views = list(old.views)
            for left in self.out.glob(".view_*.partial"):  # a view cut off mid-way
                shutil.rmtree(left, ignore_errors=True)
            return self
        if self.out.exists() and not self.out.is_dir():
            raise SlscanError(f"{self.out}: exists and is not a folder")
        if self.out.is_dir() and any(self.out.iterdir()):
            if not self._overwrite:
                hint = "pass --resume to continue it, or --overwrite" if meta.is_file() else "pass --overwrite"
                raise SlscanError(f"{self.out}: folder exists and is not empty ({hint})")
            shutil.rmtree(self.out)
        try:
            self.out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SlscanError(f"{self.out}: cannot write here ({exc.strerror})") from None
        self._created = True
        write_json(meta, self.session().to_dict())
        return self

    def _check_resumable(self, old: Session, meta: Path) -> None:
        new = self.session()
        for what, a, b in (
            ("camera size", old.camera_size, new.camera_size),
            ("projector size", old.projector_size, new.projector_size),
            ("channels", old.channels, new.channels), ("bit depth", old.bit_depth, new.bit_depth),
            ("pattern set", [p.id for p in old.patterns], [p.id for p in new.patterns]),
        ):
            if a != b:
                raise SlscanError(f"{meta}: cannot resume: its {what} is {a}, this scan's is {b}")

    def _folder_name(self, name: str) -> str:
        return f".{name}.partial" if self._incremental else name

    def view_folder(self, name: str) -> Path:
        folder = self.tmp / self._folder_name(name)
        folder.mkdir(exist_ok=True)
        return folder

    def write_image(self, view_name: str, rec: ImageRecord, image: np.ndarray) -> None:
        write_capture(self.view_folder(view_name) / rec.file, image, bit_depth=self._meta["bit_depth"],
                      jpeg_quality=self._jpeg_quality)

    def discard_view(self, name: str) -> None:
        """Remove what was written of an unfinished view."""
        shutil.rmtree(self.tmp / self._folder_name(name), ignore_errors=True)

    def add_view(self, view: ViewRecord) -> None:
        """Register a view whose images were written with :meth:`write_image`; when
        incremental, the view is then complete on disk and listed in ``session.json``."""
        if any(v.name == view.name for v in self._views):
            raise SlscanError(f"{self.out}: view {view.name} is already in the session")
        if self._incremental:
            folder = self.view_folder(view.name)
            target = self.out / view.name
            if target.exists():
                shutil.rmtree(target)
            folder.rename(target)
            self._views.append(view)
            write_json(self.out / SESSION_FILE, self.session().to_dict())
        else:
            self._views.append(view)

    def session(self) -> Session:
        return Session(root=self.out, views=tuple(self._views), **self._meta)

    def __exit__(self, exc_type, exc, tb) -> bool:
        if self._incremental:
            for left in self.out.glob(".view_*.partial"):
                shutil.rmtree(left, ignore_errors=True)
            if exc_type is not None and self._created and not self._views:
                shutil.rmtree(self.out, ignore_errors=True)  # nothing finished: leave nothing
            return False
        if exc_type is None:
            write_json(self.tmp / SESSION_FILE, self.session().to_dict())
        return bool(self._ctx.__exit__(exc_type, exc, tb))
