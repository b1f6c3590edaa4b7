"""Import the Gray-code captures of kamino410/procam-calibration as a capture session.

That tool (https://github.com/kamino410/procam-calibration, MIT licence) projects the
patterns of OpenCV's ``structured_light.GrayCodePattern`` and saves one folder per
chessboard pose::

    sample_data/
      graycode_pattern/pattern_00.png ...   the projected images (optional here)
      capture_0/graycode_00.png ...         the photographs, one folder per pose
      capture_1/ ...

In each capture folder, for a ``pw`` × ``ph`` projector with ``cb = ceil(log2(pw))``
column bits and ``rb = ceil(log2(ph))`` row bits (10 and 10 for 1024 × 768):

- ``graycode_00`` … ``graycode_{2cb-1}``: column-bit (pattern, inverse) pairs, most
  significant bit first;
- the next ``2 rb`` images: row-bit (pattern, inverse) pairs, most significant first;
- then one all-white and one all-black image (``graycode_40`` and ``graycode_41``).

This is exactly the order of ``graycode.generate(pw, ph, rows=True)`` followed by
``flat.generate(pw, ph)``, so each photograph maps onto one of our pattern descriptions.
The photographs are copied byte for byte; nothing is re-encoded.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slscan.capture.session import ImageRecord, Session, SessionWriter, ViewRecord, png_header
from slscan.errors import SlscanError
from slscan.fsio import read_png
from slscan.patterns import PatternImage, flat, graycode, render

logger = logging.getLogger(__name__)

TOOL = "kamino410/procam-calibration"
DEFAULT_PROJECTOR_SIZE = (1024, 768)
PATTERN_FOLDER = "graycode_pattern"
CAPTURE_RE = re.compile(r"capture_(\d+)")
IMAGE_RE = re.compile(r"graycode_(\d+)\.png")


def capture_sequence(width: int, height: int) -> list[PatternImage]:
    """Descriptions of the images in one capture folder, in the tool's file order.

    width, height : projector pixels

    Returns the ``2 (cb + rb) + 2`` descriptions of ``graycode_00.png`` onwards: the
    column then row Gray-code (pattern, inverse) pairs, most significant bit first, then
    ``white`` and ``black``.
    """
    return graycode.generate(width, height, rows=True) + flat.generate(width, height)


def import_kamino410(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    projector_size: tuple[int, int] | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Session:
    """Turn kamino410/procam-calibration Gray-code captures into an slscan capture session.

    Parameters
    ----------
    src : folder
        Either a ``sample_data``-like folder holding ``capture_0``, ``capture_1``, ...
        (one view each, named after the folder, in numeric order), or one capture folder.
    out : folder
        The session to write; must be absent or empty unless ``overwrite``.
    projector_size : (width, height) px, optional
        Default: the size of ``graycode_pattern/pattern_00.png`` beside the captures
        (in ``src``, or in its parent when ``src`` is one capture folder), else 1024 × 768.
        When that folder exists every ``pattern_XX.png`` in it is checked against our
        rendering of the pattern it is assumed to be.
    overwrite : bool
        Replace an existing non-empty ``out``.
    progress : callable ``(done, total)``, optional
        Called after each image is copied.

    Returns
    -------
    Session
        The written session (``calibration`` None; no poses; one pattern image per file).

    Raises
    ------
    SlscanError
        Naming the file and what was expected: no captures found, a missing or extra
        ``graycode_XX.png``, images of differing size or format, or projected patterns
        that do not match the assumed layout. Nothing is left at ``out`` then.
    """
    src = Path(src).resolve()
    out_path = Path(out)
    if not src.is_dir():
        raise SlscanError(f"{src}: folder not found (expected a kamino410 capture folder)")
    captures = _find_captures(src)
    _refuse_overlap(out_path.resolve(), src, captures)
    pattern_dir = _pattern_folder(src, captures)
    if projector_size is None:
        if pattern_dir is not None:
            w, h, _, _ = png_header(pattern_dir / "pattern_00.png")
            projector_size = (w, h)
        else:
            projector_size = DEFAULT_PROJECTOR_SIZE
    pw, ph = (int(v) for v in projector_size)
    if pw <= 0 or ph <= 0:
        raise SlscanError(f"projector size must be positive, got {pw}x{ph}")
    sequence = capture_sequence(pw, ph)
    if pattern_dir is not None:
        _verify_patterns(pattern_dir, sequence)

    files = {folder: _capture_files(folder, len(sequence), (pw, ph)) for folder in captures}
    camera = _image_format(files)
    logger.info(
        "importing %d kamino410 capture(s) from %s: %d images each, camera %dx%d, projector %dx%d",
        len(captures),
        src,
        len(sequence),
        camera[0],
        camera[1],
        pw,
        ph,
    )

    patterns = flat.generate(pw, ph) + graycode.generate(pw, ph, rows=True)
    total, done = len(captures) * len(sequence), 0
    with SessionWriter(
        out_path,
        camera_size=(camera[0], camera[1]),
        projector_size=(pw, ph),
        channels=3 if camera[2] == 4 else camera[2],
        bit_depth=camera[3],
        patterns=patterns,
        calibration=None,
        device={"kind": "import", "tool": TOOL, "source": str(src)},
        overwrite=overwrite,
    ) as writer:
        for folder in captures:
            view_dir = writer.view_folder(folder.name)
            records = []
            for i, (path, desc) in enumerate(zip(files[folder], sequence)):
                name = f"{i:02d}_{desc.id}.png"
                shutil.copy2(path, view_dir / name)
                records.append(ImageRecord(name, "pattern", pattern=desc.id))
                done += 1
                if progress is not None:
                    progress(done, total)
            writer.add_view(
                ViewRecord(folder.name, tuple(records), rig_from_object=None, exposure={})
            )
        session = writer.session()
    logger.info("wrote capture session %s (%d views)", out_path, len(captures))
    return session


def _refuse_overlap(out: Path, src: Path, captures: list[Path]) -> None:
    """Writing (or overwriting) ``out`` must never touch the source captures."""
    for folder in [src, *captures]:
        if out == folder or out in folder.parents or (folder != src and folder in out.parents):
            raise SlscanError(
                f"{out}: the session must be written outside the source captures {folder}"
            )


def _image_indices(folder: Path) -> dict[int, Path]:
    found = {}
    for path in folder.iterdir():
        m = IMAGE_RE.fullmatch(path.name)
        if m and path.is_file():
            found[int(m.group(1))] = path
    return found


def _find_captures(src: Path) -> list[Path]:
    """The capture folders of ``src``: itself when it holds images, else its ``capture_N``."""
    if _image_indices(src):
        return [src]
    numbered = []
    for path in src.iterdir():
        m = CAPTURE_RE.fullmatch(path.name)
        if m and path.is_dir():
            numbered.append((int(m.group(1)), path))
    if not numbered:
        raise SlscanError(
            f"{src}: no graycode_*.png images and no capture_N folders; expected a kamino410 "
            "capture folder (graycode_00.png, graycode_01.png, ...) or a folder of capture_0, "
            "capture_1, ..."
        )
    return [path for _, path in sorted(numbered)]


def _pattern_folder(src: Path, captures: list[Path]) -> Path | None:
    candidates = [src / PATTERN_FOLDER]
    if captures == [src]:
        candidates.append(src.parent / PATTERN_FOLDER)
    for folder in candidates:
        if folder.is_dir():
            return folder
    return None


def _verify_patterns(folder: Path, sequence: list[PatternImage]) -> None:
    """Check each projected ``pattern_XX.png`` against our rendering of ``sequence[XX]``."""
    for i, desc in enumerate(sequence):
        path = folder / f"pattern_{i:02d}.png"
        if not path.is_file():
            raise SlscanError(
                f"{path}: not found; expected {len(sequence)} projected patterns for a "
                f"{desc.width}x{desc.height} projector"
            )
        image = read_png(path)
        expected = render(desc)
        h, w = image.shape[:2]
        if (w, h) != (desc.width, desc.height):
            raise SlscanError(
                f"{path}: pattern is {w}x{h}, expected the projector size {desc.width}x{desc.height}"
            )
        if image.dtype != np.uint8 or not np.array_equal(
            image, expected[..., 0] if image.ndim == 2 else expected
        ):
            raise SlscanError(
                f"{path}: differs from pattern {desc.id!r} as slscan renders it; expected "
                "column then row Gray-code (pattern, inverse) pairs, most significant bit "
                "first, then white and black (a graycode_step other than 1 is not supported)"
            )
    extra = folder / f"pattern_{len(sequence):02d}.png"
    if extra.exists():
        raise SlscanError(
            f"{extra}: unexpected; a {sequence[0].width}x{sequence[0].height} projector has "
            f"{len(sequence)} patterns (pattern_00.png … pattern_{len(sequence) - 1:02d}.png)"
        )


def _capture_files(folder: Path, n: int, projector_size: tuple[int, int]) -> list[Path]:
    """The ``n`` images ``graycode_00.png`` … of one capture folder, checked present."""
    found = _image_indices(folder)
    expected = (
        f"expected {n} images graycode_00.png … graycode_{n - 1:02d}.png for a "
        f"{projector_size[0]}x{projector_size[1]} projector"
    )
    if not found:
        jpegs = any(folder.glob("graycode_*.jp*g"))
        raise SlscanError(
            f"{folder}: no graycode_*.png images; {expected}"
            + ("; JPEG captures are not supported (lossy), save PNG" if jpegs else "")
        )
    extra = sorted(i for i in found if i >= n)
    if extra:
        raise SlscanError(
            f"{found[extra[0]]}: unexpected image; {expected} "
            "(pass projector_size if the projector differs)"
        )
    paths = []
    for i in range(n):
        path = folder / f"graycode_{i:02d}.png"
        if not path.is_file():
            raise SlscanError(f"{path}: image not found; {expected}")
        paths.append(path)
    return paths


def _image_format(files: dict[Path, list[Path]]) -> tuple[int, int, int, int]:
    """(width, height, channels, bit_depth) shared by every image; raise naming the odd one."""
    first_path = next(iter(files.values()))[0]
    first = png_header(first_path)
    w, h, channels, depth = first
    if channels not in (1, 3, 4) or depth not in (8, 16):
        raise SlscanError(
            f"{first_path}: {channels}-channel {depth}-bit PNG; expected 8- or 16-bit grey or RGB"
        )
    for paths in files.values():
        for path in paths:
            header = png_header(path)
            if header != first:
                hw, hh, hc, hd = header
                raise SlscanError(
                    f"{path}: image is {hw}x{hh}, {hc} channel(s), {hd}-bit; expected "
                    f"{w}x{h}, {channels} channel(s), {depth}-bit like {first_path}"
                )
    return first
