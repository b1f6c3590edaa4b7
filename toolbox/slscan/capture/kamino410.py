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
The photographs are copied byte for byte; nothing is re-encoded. The import itself is
:func:`slscan.capture.graycode_import.import_graycode` with the ``kamino410`` preset; this
module adds the projector size read from, and the check of, ``graycode_pattern``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slscan.capture.graycode_import import PRESETS, find_views, import_graycode
from slscan.capture.session import Session, png_header
from slscan.errors import SlscanError
from slscan.fsio import read_png
from slscan.patterns import PatternImage, flat, graycode, render

TOOL = "kamino410/procam-calibration"
DEFAULT_PROJECTOR_SIZE = (1024, 768)
PATTERN_FOLDER = "graycode_pattern"


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
    response: str | None = None,
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
    response : {"auto", "linear", "srgb"}, optional
        The camera's tone curve (default: measured from the captures, see
        :func:`~slscan.capture.graycode_import.import_graycode`).

    Returns
    -------
    Session
        The written session (``calibration`` None; no poses; one pattern image per file).

    Raises
    ------
    SlscanError
        Naming the file and what was expected: no captures found, a missing or extra
        ``graycode_XX`` image, images of differing size or format, or projected patterns
        that do not match the assumed layout. Nothing is left at ``out`` then.
    """
    src = Path(src).resolve()
    if not src.is_dir():
        raise SlscanError(f"{src}: folder not found (expected a kamino410 capture folder)")
    layout = PRESETS["kamino410"]
    captures = list(find_views(src, pattern=layout.pattern, views=layout.views))
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
    if pattern_dir is not None:
        _verify_patterns(pattern_dir, capture_sequence(pw, ph))
    return import_graycode(
        src, out, preset="kamino410", projector_size=(pw, ph), overwrite=overwrite,
        progress=progress, tool=TOOL, response=response,
    )


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
