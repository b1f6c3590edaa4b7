"""Import any folder of Gray-code captures as a capture session, given the image order.

Other tools project black/white Gray-code stripes in their own order and save the
photographs under their own names. An *order spec* says what each photograph shows, in
the natural sort order of the file names (``img2`` before ``img10``)::

    white,black,cols:10:pairs,rows:10:pairs         3DUNDERWORLD-SLS
    cols:pairs,rows:pairs,white,black               OpenCV GrayCodePattern, kamino410

Grammar (items separated by commas, one item per image or block of images)::

    ITEM   := "white" | "black" | "skip" | CODE
    CODE   := AXIS (":" OPTION)*
    AXIS   := "cols" | "rows"             projector columns (vertical stripes) or rows
    OPTION := BITS                        number of bits; default ceil(log2(projector size))
            | "pairs"                     (pattern, inverse) per bit (default)
            | "split"                     every bit's pattern, then every bit's inverse
            | "plain"                     patterns only, no inverse images
            | "msb" | "lsb"               most significant bit first (default) or last

``skip`` is an image that is there but not imported (e.g. a focus frame). Every order
needs one ``white``, one ``black`` and a ``cols`` block; ``rows`` is optional. The
projector size and how the projector is mounted (rotated by 0, 90, 180 or 270 degrees)
are given beside the order. Named presets (:data:`PRESETS`) hold the layouts of known
tools. Images are copied byte for byte, PNG, JPEG or TIFF as they are (BMP, which a
session does not hold, is converted to PNG without loss); JPEG (and JPEG-compressed TIFF)
sessions are marked lossy. The camera's tone curve (linear or sRGB) is measured from the
captures themselves (:mod:`slscan.capture.response`), not assumed from the file format.

References
----------
.. [1] OpenCV ``structured_light.GrayCodePattern`` (opencv_contrib): ``generate`` gives the
   column (pattern, inverse) pairs, most significant bit first, then the row pairs;
   the capture tutorial appends the white and black images of
   ``getImagesForShadowMasks`` after them.
.. [2] Herakleous, Poullis, "3DUNDERWORLD-SLS: An Open-Source Structured-Light Scanning
   System for Rapid Geometry Acquisition", arXiv:1406.6595, 2014; images ``0000.jpg``
   (white), ``0001.jpg`` (black), then column and row (pattern, inverse) pairs, most
   significant bit first (``GrayCode.cpp``, ``FileReader.cpp`` of
   theICTlab/3DUNDERWORLD-SLS-GPU_CPU).
"""

from __future__ import annotations

import fnmatch
import logging
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.capture.response import (
    ResponseFit,
    describe_response,
    measure_response,
    response_pairs,
)
from slscan.capture.session import (
    IMAGE_FORMATS,
    RESPONSES,
    ROTATIONS,
    ImageRecord,
    Session,
    SessionWriter,
    ViewRecord,
    image_header,
    read_capture,
)
from slscan.errors import SlscanError
from slscan.fsio import decode_image, write_png
from slscan.patterns import PatternImage, flat
from slscan.patterns.graycode import n_bits

logger = logging.getLogger(__name__)

LAYOUTS = ("pairs", "split", "plain")
MISSING_BITS = ("error", "drop")
AXIS_NAMES = {"cols": "columns", "rows": "rows"}
_TAGS = {"columns": "col", "rows": "row"}
_NUMBERED = re.compile(r"^(.*?)(\d+)(\D*)$")
SOURCE_FORMATS = {**IMAGE_FORMATS, ".bmp": "bmp"}
"""Capture file extensions an import reads: the session's own formats, copied byte for
byte, and BMP, converted to PNG (lossless both; a session holds no BMP)."""


# --- the order spec ---------------------------------------------------------------------------


@dataclass(frozen=True)
class CodeBlock:
    """A block of Gray-code images along one projector axis.

    axis : {"columns", "rows"}
    bits : number of bits, or None for ``ceil(log2(projector size))``
    layout : {"pairs", "split", "plain"}
    msb_first : the most significant bit comes first
    """

    axis: str
    bits: int | None = None
    layout: str = "pairs"
    msb_first: bool = True


@dataclass(frozen=True)
class Slot:
    """What one image of the order shows: a flat frame, a skipped image, or one Gray-code bit.

    kind : {"white", "black", "skip", "gray"}
    axis, bit, bits, inverse : for "gray": ``bit`` 0 is the most significant of ``bits``
    """

    kind: str
    axis: str | None = None
    bit: int | None = None
    bits: int | None = None
    inverse: bool = False

    @property
    def pattern_id(self) -> str | None:
        if self.kind in ("white", "black"):
            return self.kind
        if self.kind == "gray":
            return f"gray-{_TAGS[self.axis]}-{self.bit:02d}{'-inv' if self.inverse else ''}"
        return None

    def describe(self) -> str:
        if self.kind != "gray":
            return f"the {self.kind} image" if self.kind != "skip" else "a skipped image"
        which = "inverse of " if self.inverse else ""
        return f"the {which}{self.axis[:-1]} bit {self.bit} (0 = most significant of {self.bits})"


@dataclass(frozen=True)
class GrayOrder:
    """A parsed order spec: what each image shows, in file order (:func:`parse_order`)."""

    text: str
    items: tuple[str | CodeBlock, ...]

    def slots(self, projector_size: tuple[int, int]) -> list[Slot]:
        """One :class:`Slot` per image for a ``(width, height)`` projector."""
        out: list[Slot] = []
        for item in self.items:
            if isinstance(item, str):
                out.append(Slot(item))
                continue
            size = projector_size[0] if item.axis == "columns" else projector_size[1]
            bits = item.bits if item.bits is not None else n_bits(size)
            if bits < n_bits(size):
                raise SlscanError(
                    f"order {self.text!r}: {bits} {item.axis[:-1]} bits cannot code {size} projector "
                    f"{item.axis}; expected at least {n_bits(size)} (or give --projector)"
                )
            order = range(bits) if item.msb_first else range(bits - 1, -1, -1)
            if item.layout == "pairs":
                out += [Slot("gray", item.axis, b, bits, inv) for b in order for inv in (False, True)]
            elif item.layout == "split":
                out += [Slot("gray", item.axis, b, bits, inv) for inv in (False, True) for b in order]
            else:
                out += [Slot("gray", item.axis, b, bits, False) for b in order]
        return out

    def summary(self, projector_size: tuple[int, int]) -> str:
        """E.g. ``"white, black, 20 column, 20 row"`` images."""
        parts = []
        for item in self.items:
            if isinstance(item, str):
                parts.append(item)
            else:
                n = len(GrayOrder(self.text, (item,)).slots(projector_size))
                parts.append(f"{n} {item.axis[:-1]}")
        return ", ".join(parts)


def order_items(text: str) -> list[tuple[str, str, list[str]]]:
    """The items of an order spec: (as written, head, options) of each, lower case."""
    out = []
    for raw in text.split(","):
        head, *options = raw.strip().lower().split(":")
        out.append((raw.strip(), head, options))
    return out


def flat_item(text: str, head: str, options: list[str], seen: set[str]) -> bool:
    """Whether an order item is ``white``, ``black`` or ``skip`` (recorded in ``seen``);
    raise when white or black comes twice."""
    if head not in ("white", "black", "skip") or options:
        return False
    if head in seen and head != "skip":
        raise SlscanError(f"order {text!r}: {head!r} appears twice; expected one {head} image")
    seen.add(head)
    return True


def parse_order(text: str) -> GrayOrder:
    """Parse an order spec (grammar in the module docstring); raise naming the bad item."""
    items: list[str | CodeBlock] = []
    seen: set[str] = set()
    for raw, head, options in order_items(text):
        if flat_item(text, head, options, seen):
            items.append(head)
            continue
        if head not in AXIS_NAMES:
            raise SlscanError(
                f"order {text!r}: unknown item {raw!r}; expected white, black, skip, "
                "cols[:BITS][:pairs|split|plain][:msb|lsb] or rows[...]"
            )
        if head in seen:
            raise SlscanError(f"order {text!r}: {head!r} appears twice")
        seen.add(head)
        bits, layout, msb = None, None, None
        for opt in options:
            if opt.isdigit() and bits is None and int(opt) > 0:
                bits = int(opt)
            elif opt in LAYOUTS and layout is None:
                layout = opt
            elif opt in ("msb", "lsb") and msb is None:
                msb = opt == "msb"
            else:
                raise SlscanError(
                    f"order {text!r}: bad or repeated option {opt!r} of {head!r}; expected a bit "
                    f"count, one of {', '.join(LAYOUTS)}, and msb or lsb"
                )
        items.append(CodeBlock(AXIS_NAMES[head], bits, layout or "pairs", True if msb is None else msb))
    for needed in ("white", "black", "cols"):
        if needed not in seen:
            raise SlscanError(
                f"order {text!r}: no {needed!r}; decoding needs a white and a black image and "
                "the column codes"
            )
    return GrayOrder(text, tuple(items))


# --- presets ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Preset:
    """The capture layout of a known tool.

    order : the order spec
    projector_size : (width, height) px the tool projects by default
    rotation : degrees the projector is mounted turned (see ``Session.projector_rotation``)
    pattern : glob of the capture file names in a folder
    views : glob of the sub-folders holding one view each
    first : number of the first image when the names are numbered (None: the lowest found)
    tool : what ``device.tool`` of the session says
    """

    order: str
    projector_size: tuple[int, int] = (1024, 768)
    rotation: int = 0
    pattern: str = "*"
    views: str = "*"
    first: int | None = None
    tool: str = "graycode"


PRESETS: dict[str, Preset] = {
    "opencv": Preset("cols:pairs,rows:pairs,white,black", tool="OpenCV structured_light.GrayCodePattern"),
    "kamino410": Preset(
        "cols:pairs,rows:pairs,white,black", pattern="graycode_*", views="capture_*", first=0,
        tool="kamino410/procam-calibration",
    ),
    "3dunderworld": Preset(
        "white,black,cols:pairs,rows:pairs", rotation=90, pattern="[0-9]*", first=0,
        tool="3DUNDERWORLD-SLS",
    ),
}
"""Named layouts. ``opencv``: ``GrayCodePattern.generate`` then white and black, as the
OpenCV capture tutorial projects them; ``kamino410``: the same order, as
procam-calibration saves it (``capture_N/graycode_XX.png``); ``3dunderworld``:
``0000.jpg`` white, ``0001.jpg`` black, then column and row pairs, projector mounted
turned by 90 degrees (as in the tool's two-camera bust data set)."""


def get_preset(name: str) -> Preset:
    """The preset called ``name``; raise listing the presets."""
    try:
        return PRESETS[name]
    except KeyError:
        raise SlscanError(
            f"unknown Gray-code preset {name!r}; expected one of {', '.join(PRESETS)} "
            "(or give the order with --order)"
        ) from None


# --- finding the captures ---------------------------------------------------------------------


def natural_key(name: str) -> list:
    """Sort key putting ``img2`` before ``img10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _images(folder: Path, pattern: str) -> list[Path]:
    found = [
        p for p in folder.iterdir()
        if p.suffix.lower() in SOURCE_FORMATS and fnmatch.fnmatch(p.name, pattern) and p.is_file()
    ]
    return sorted(found, key=lambda p: natural_key(p.name))


def find_views(src: Path, *, pattern: str = "*", views: str = "*") -> dict[Path, list[Path]]:
    """The capture files of each candidate view: ``src`` itself when it holds images
    matching ``pattern``, else each of its sub-folders matching ``views`` that does (the
    import then keeps those whose images fit the order: :func:`place_views`)."""
    if not src.is_dir():
        raise SlscanError(f"{src}: folder not found (expected a folder of Gray-code captures)")
    own = _images(src, pattern)
    if own:
        return {src: own}
    found = {}
    candidates = sorted((p for p in src.iterdir() if p.is_dir() and fnmatch.fnmatch(p.name, views)),
                        key=lambda p: natural_key(p.name))
    for folder in candidates:
        files = _images(folder, pattern)
        if files:
            found[folder] = files
    kinds = "/".join(sorted({f.upper() for f in SOURCE_FORMATS.values()}))
    if not found and candidates:
        raise SlscanError(
            f"{candidates[0]}: no {pattern} images ({kinds}), nor in {src} or its other "
            f"{views} sub-folders; expected one folder of captures or one sub-folder per view"
        )
    if not found:
        raise SlscanError(
            f"{src}: no {pattern} images ({kinds}) and no {views} sub-folders holding any; "
            "expected one folder of captures or one sub-folder per view"
        )
    return found


def _numbering(files: list[Path]) -> tuple[str, str, int, list[int]] | None:
    """(prefix, suffix, digits, numbers) when every name is PREFIX + number + SUFFIX."""
    parts = [_NUMBERED.match(p.name) for p in files]
    if not all(parts):
        return None
    prefixes = {m.group(1) for m in parts}
    suffixes = {m.group(3).lower() for m in parts}
    if len(prefixes) != 1 or len(suffixes) != 1:
        return None
    widths = {len(m.group(2)) for m in parts}
    digits = widths.pop() if len(widths) == 1 else 0
    return prefixes.pop(), parts[0].group(3), digits, [int(m.group(2)) for m in parts]


def _place(
    folder: Path, files: list[Path], n: int, first: int | None, order_text: str, needs: str, drop: bool
) -> dict[int, Path]:
    """Map each file to its position in the order (0 … n-1). Missing positions are an
    error naming them, unless ``drop`` (then they are absent from the result)."""
    numbering = _numbering(files)
    what = f"the order {order_text!r} needs {n} images ({needs})"
    hint = "; pass --missing-bits drop to import the bits present" if not drop else ""
    if numbering is None:
        if len(files) != n:
            raise SlscanError(
                f"{folder}: found {len(files)} images, {what}"
                + ("; the file names carry no common numbering, so the missing ones cannot be "
                   "told" if len(files) < n else "; give --pattern to select the captures")
            )
        return dict(enumerate(files))
    prefix, suffix, digits, numbers = numbering

    def name(k: int) -> str:
        return f"{prefix}{k:0{digits}d}{suffix}"

    if len(set(numbers)) != len(numbers):
        seen: dict[int, Path] = {}
        for k, path in zip(numbers, files):
            if k in seen:
                raise SlscanError(f"{path}: same number as {seen[k].name}; expected one image per number")
            seen[k] = path
    start = first if first is not None else min(numbers)
    by_number = dict(zip(numbers, files))
    extra = sorted(k for k in numbers if not start <= k < start + n)
    expected = f"expected {n} images {name(start)} … {name(start + n - 1)}: {what}"
    if extra:
        raise SlscanError(f"{by_number[extra[0]]}: unexpected image (found {len(files)}); {expected}")
    missing = [k for k in range(start, start + n) if k not in by_number]
    if missing and not drop:
        shown = ", ".join(name(k) for k in missing[:6]) + (" …" if len(missing) > 6 else "")
        raise SlscanError(
            f"{folder / name(missing[0])}: image not found ({len(missing)} missing: {shown}; "
            f"found {len(files)}); {expected}{hint}"
        )
    return {k - start: path for k, path in by_number.items()}


def place_views(
    src: Path, found: dict[Path, list[Path]], n: int, first: int | None, order_text: str, needs: str,
    drop: bool,
) -> dict[Path, dict[int, Path]]:
    """Each view's files by position in the order (:func:`_place`). ``src`` itself as the
    one view must fit the order (else the error names what is wrong); of its sub-folders,
    those whose images do not fit (a ``calib/`` folder of board images, notes, another
    capture) are not views: they are skipped, named with the reason in one log line. With
    ``drop`` a sub-folder must still hold at least three quarters of the images the order
    needs (a folder of a dozen board images numbered from 0 fits an order with gaps).

    Raises
    ------
    SlscanError
        ``src`` does not fit, or no sub-folder does (the first one's reason).
    """
    if list(found) == [src]:
        return {src: _place(src, found[src], n, first, order_text, needs, drop)}
    placed: dict[Path, dict[int, Path]] = {}
    skipped: list[tuple[Path, int, SlscanError]] = []
    for folder, files in found.items():
        try:
            if drop and 4 * len(files) < 3 * n:
                raise SlscanError(
                    f"{folder}: found {len(files)} images, fewer than three quarters of the {n} "
                    f"the order {order_text!r} needs ({needs})"
                )
            placed[folder] = _place(folder, files, n, first, order_text, needs, drop)
        except SlscanError as exc:
            skipped.append((folder, len(files), exc))
    if not placed:
        raise skipped[0][2]
    if skipped:
        logger.warning(
            "%s: %d sub-folder(s) skipped, not views of the order %r (%d images a view): %s", src,
            len(skipped), order_text, n,
            "; ".join(f"{folder.name}/ ({k} images{'' if k != n else ': ' + _short(exc, folder)})"
                      for folder, k, exc in skipped),
        )
    return placed


def _short(exc: SlscanError, folder: Path) -> str:
    """An error's message about ``folder`` without the path and the order's description."""
    text = str(exc)
    if text.startswith(str(folder)):
        text = text[len(str(folder)):].lstrip("/: ")
    for cut in ("; expected", ", the order", "; the order", "; pass --missing-bits"):
        text = text.split(cut)[0]
    return re.sub(r"order '[^']*'(: )?", "", text)  # an order named at the start (phase import)


# --- the import -------------------------------------------------------------------------------


def import_graycode(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    preset: str | None = None,
    order: str | None = None,
    projector_size: tuple[int, int] | None = None,
    rotation: int | None = None,
    pattern: str | None = None,
    missing_bits: str = "error",
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    tool: str | None = None,
    response: str | None = None,
) -> Session:
    """Turn a folder of Gray-code captures into an slscan capture session.

    Parameters
    ----------
    src : folder
        One folder of captures (one view, named after the folder), or a folder of
        sub-folders, one view each (in natural order of their names).
    out : folder
        The session to write; must be absent or empty unless ``overwrite``.
    preset : {"opencv", "kamino410", "3dunderworld"}, optional
        A named layout (:data:`PRESETS`); its order, projector size, rotation and file
        globs are the defaults of the options below.
    order : str, optional
        The order spec (module docstring), instead of a preset's.
    projector_size : (width, height) px, optional
        Default: the preset's, else 1024 × 768.
    rotation : {0, 90, 180, 270}, optional
        Degrees the projector is mounted turned relative to the camera; with 90 or 270 the
        projector's column stripes appear horizontal in the captures. Default: the
        preset's, else 0.
    pattern : glob, optional
        Which files of a folder are captures (default: the preset's, else every PNG, JPEG
        and TIFF file), taken in natural sort order.
    missing_bits : {"error", "drop"}
        A view with images missing (found by gaps in the numbered file names) is an error
        naming them; with "drop", the Gray-code bits those images belong to are left out,
        with every less significant bit of the same axis (they cannot be decoded without
        it), in all views. The descriptions keep ``bits`` (the full count) and the ``bit``
        index of each bit kept; ``device.missing_bits`` records what was dropped.
    overwrite : bool
        Replace an existing non-empty ``out``.
    progress : callable ``(done, total)``, optional
        Called after each image is copied.
    tool : str, optional
        What ``device.tool`` says (default: the preset's, else "graycode").
    response : {"auto", "linear", "srgb"}, optional
        The camera's tone curve (``camera.response``; decoding undoes "srgb"). Default
        ("auto" or None): measured from the captures (:mod:`slscan.capture.response`: the
        finest column pairs of the first views, against white and black), linear when
        they do not tell; a curve given here is recorded as given, beside what the
        captures measure (``camera.response_fit``).

    Returns
    -------
    Session
        The written session: ``calibration`` None, no poses, one pattern image per file
        named ``NN_<pattern id>.<ext>`` (NN its position in the order), ``lossy`` True for
        JPEG captures, ``response`` and ``response_fit`` as above, ``projector_rotation``
        as given. Sub-folders of ``src`` whose images do not fit the order (a ``calib/``
        folder) are not views: skipped, and named in a log line (:func:`place_views`).

    Raises
    ------
    SlscanError
        One line naming the file or folder and what was expected: an unknown preset, a bad
        order, a view whose image count does not match the order, a missing image, images
        of different sizes, a folder mixing formats. Nothing is left at ``out`` then.
    """
    if (preset is None) == (order is None):
        raise SlscanError("give either a Gray-code preset or an order spec (not both, not neither)")
    chosen = get_preset(preset) if preset is not None else Preset(order)
    spec = parse_order(chosen.order)
    pw, ph = (int(v) for v in (projector_size or chosen.projector_size))
    if pw <= 0 or ph <= 0:
        raise SlscanError(f"projector size must be positive, got {pw}x{ph}")
    rotation = chosen.rotation if rotation is None else int(rotation)
    if rotation not in ROTATIONS:
        raise SlscanError(f"projector rotation {rotation} is not one of {ROTATIONS} (degrees)")
    if response == "auto":
        response = None
    if response is not None and response not in RESPONSES:
        raise SlscanError(f"camera response must be auto or one of {', '.join(RESPONSES)}, got {response!r}")
    if missing_bits not in MISSING_BITS:
        raise SlscanError(f"missing_bits must be one of {MISSING_BITS}, got {missing_bits!r}")
    pattern = pattern or chosen.pattern

    src = Path(src).resolve()
    out_path = Path(out)
    found = find_views(src, pattern=pattern, views=chosen.views)
    _refuse_overlap(out_path.resolve(), src, list(found))
    slots = spec.slots((pw, ph))
    needs = spec.summary((pw, ph))
    placed = place_views(src, found, len(slots), chosen.first, spec.text, needs, missing_bits == "drop")
    keep, dropped = _bits_kept(placed, slots)
    fmt, (cw, ch, channels, depth), lossy = _image_format(placed)
    response, response_fit = choose_response(src, response, _measure_response(placed, slots, keep))

    patterns = flat.generate(pw, ph) + [
        PatternImage(s.pattern_id, "gray", pw, ph, s.axis,
                     {"bit": s.bit, "bits": s.bits, "inverse": s.inverse, "code": "reflected-binary"})
        for s in _canonical(slots) if s.bit < keep[s.axis]
    ]
    device = {"kind": "import", "tool": tool or chosen.tool, "source": str(src)}
    if preset is None:
        device["order"] = spec.text
    if dropped:
        device["missing_bits"] = dropped
    logger.info(
        "importing %d view(s) of Gray-code captures from %s: order %r, %s (%s camera response), camera %dx%d, "
        "projector %dx%d turned %d degrees", len(placed), src, spec.text, fmt.upper(), response, cw, ch, pw, ph,
        rotation,
    )
    with SessionWriter(
        out_path,
        camera_size=(cw, ch),
        projector_size=(pw, ph),
        channels=3 if channels == 4 else channels,
        bit_depth=depth,
        patterns=patterns,
        calibration=None,
        device=device,
        overwrite=overwrite,
        lossy=lossy,
        projector_rotation=rotation,
        response=response,
        response_fit=response_fit,
    ) as writer:
        copy_views(writer, placed, [s.pattern_id if _kept(s, keep) else None for s in slots], progress)
        session = writer.session()
    logger.info("wrote capture session %s (%d views)", out_path, len(placed))
    return session


def _measure_response(placed: dict[Path, dict[int, Path]], slots: list[Slot],
                      keep: dict[str, int]) -> ResponseFit:
    """The camera's tone curve measured on the captures as they are (:mod:`slscan.capture.response`):
    the finest column pairs kept, against white and black, of the first views."""
    at = {slot.pattern_id: i for i, slot in enumerate(slots) if slot.pattern_id is not None}
    bits = sorted({s.bit for s in slots if s.kind == "gray" and s.axis == "columns" and s.bit < keep["columns"]})
    pairs = [(at[f"gray-col-{b:02d}"], at[f"gray-col-{b:02d}-inv"]) for b in bits]
    return measure_placed_response(placed, at["white"], at["black"], pairs)


def measure_placed_response(placed: dict[Path, dict[int, Path]], white: int, black: int,
                            pairs: list[tuple[int, int]]) -> ResponseFit:
    """The tone curve measured on the files ``placed`` (per view, position -> file): the
    finest of the (pattern, inverse) ``pairs`` of positions (most significant first),
    against the ``white`` and ``black`` positions, of the first views holding them all."""
    views = {folder.name: files for folder, files in placed.items()}
    usable = [name for name, files in views.items()
              if all(i in files for pair in response_pairs(pairs) for i in pair)]

    def read(view: str, index: int) -> np.ndarray:
        path = views[view][index]
        image = _read_bmp(path) if path.suffix.lower() == ".bmp" else read_capture(path)
        return image[..., :3] if image.ndim == 3 else image

    return measure_response(read, usable, white, black, response_pairs(pairs))


def choose_response(src: Path, response: str | None, fit: ResponseFit) -> tuple[str, dict]:
    """The camera response to record and its ``response_fit``: the measured one when none
    was given (None), else the one given beside what was measured; logged (a warning when
    it had to be assumed)."""
    response_fit = {**fit.to_dict(), "source": "measured" if response is None else "given"}
    if response is None:
        response = fit.response
    level = logging.WARNING if not fit.measured and response_fit["source"] == "measured" else logging.INFO
    logger.log(level, "%s: camera response %s", src, describe_response(response, response_fit))
    return response, response_fit


def copy_views(
    writer: SessionWriter, placed: dict[Path, dict[int, Path]], pattern_ids: list[str | None],
    progress: Callable[[int, int], None] | None = None,
) -> None:
    """Copy each view's captures into the session ``writer`` writes, one view per folder of
    ``placed`` (position in the order -> file), as ``NN_<pattern id>.<ext>`` with ``NN`` the
    position; positions whose ``pattern_ids`` entry is None are left out. Files are copied
    byte for byte; BMP is converted to PNG (lossless). ``progress(done, total)`` after each."""
    total = sum(1 for files in placed.values() for i in files if pattern_ids[i] is not None)
    done = 0
    for folder, files in placed.items():
        view_dir = writer.view_folder(folder.name)
        records = []
        for i in sorted(files):
            if pattern_ids[i] is None:
                continue
            path = files[i]
            ext = path.suffix.lower()
            name = f"{i:02d}_{pattern_ids[i]}{'.png' if ext == '.bmp' else ext}"
            if ext == ".bmp":
                write_png(view_dir / name, _read_bmp(path))
            else:
                shutil.copy2(path, view_dir / name)
            records.append(ImageRecord(name, "pattern", pattern=pattern_ids[i]))
            done += 1
            if progress is not None:
                progress(done, total)
        writer.add_view(ViewRecord(folder.name, tuple(records), rig_from_object=None, exposure={}))


def _read_bmp(path: Path) -> np.ndarray:
    """A BMP capture's pixels: (h, w) grey or (h, w, 3) RGB uint8 (a grey palette reads grey)."""
    try:
        return decode_image(path.read_bytes())
    except SlscanError:
        raise SlscanError(f"{path}: not a readable BMP image") from None


def _header(path: Path) -> tuple[int, int, int, int]:
    """(width, height, channels, bit depth) of a capture to import (BMP decoded: it is small
    work and tells the channels exactly as the conversion will write them)."""
    if path.suffix.lower() != ".bmp":
        return image_header(path)
    image = _read_bmp(path)
    return image.shape[1], image.shape[0], 1 if image.ndim == 2 else image.shape[2], 8


def _kept(slot: Slot, keep: dict[str, int]) -> bool:
    return slot.kind in ("white", "black") or (slot.kind == "gray" and slot.bit < keep[slot.axis])


def _canonical(slots: list[Slot]) -> list[Slot]:
    """The Gray-code slots in slscan's pattern-set order: columns then rows, most
    significant bit first, each pattern before its inverse (as ``graycode.generate``)."""
    gray = [s for s in slots if s.kind == "gray"]
    return sorted(gray, key=lambda s: (s.axis != "columns", s.bit, s.inverse))


def _bits_kept(placed: dict[Path, dict[int, Path]], slots: list[Slot]) -> tuple[dict[str, int], dict]:
    """Per axis, how many bits (from the most significant) every view has complete, and a
    record of what was dropped; raise when a white or black image or every column bit
    is missing."""
    full = {"columns": 0, "rows": 0}
    for s in slots:
        if s.kind == "gray":
            full[s.axis] = s.bits
    keep = dict(full)
    lost: dict[str, set[int]] = {"columns": set(), "rows": set()}
    for folder, files in placed.items():
        for i, slot in enumerate(slots):
            if i in files:
                continue
            if slot.kind in ("white", "black"):
                raise SlscanError(
                    f"{folder}: {slot.describe()} (position {i} of the order) is missing; "
                    "decoding needs it"
                )
            if slot.kind == "gray":
                keep[slot.axis] = min(keep[slot.axis], slot.bit)
                lost[slot.axis].add(slot.bit)
                logger.warning("%s: image %d of the order (%s) is missing", folder, i, slot.describe())
    if keep["columns"] == 0:
        raise SlscanError(
            f"{next(iter(placed))}: the most significant column bit is missing; nothing left to decode"
        )
    dropped = {}
    for axis, n in keep.items():
        if n < full[axis]:
            dropped[axis] = {"bits": full[axis], "kept": n, "missing": sorted(lost[axis])}
            kept = f"importing bits 0-{n - 1} only" if n else f"importing no {axis[:-1]} codes"
            logger.warning(
                "Gray-code %s: bits %s (0 = most significant of %d) are missing in some view; %s, "
                "in every view", axis, sorted(lost[axis]), full[axis], kept,
            )
    return keep, dropped


def _image_format(placed: dict[Path, dict[int, Path]]) -> tuple[str, tuple[int, int, int, int], bool]:
    """(format, (width, height, channels, bit depth), lossy) shared by every capture;
    raise naming the odd file (another format, size, channel count or depth)."""
    first_path = None
    first = fmt = None
    lossy = False
    for files in placed.values():
        for path in files.values():
            this = SOURCE_FORMATS[path.suffix.lower()]
            if first_path is None:
                first_path, fmt = path, this
                first = _header(path)
                w, h, c, d = first
                if c not in (1, 3, 4) or d not in (8, 16):
                    raise SlscanError(
                        f"{path}: {c}-channel {d}-bit image; expected 8- or 16-bit grey or RGB"
                    )
                lossy = fmt == "jpeg" or (fmt == "tiff" and _tiff_lossy(path))
                continue
            if this != fmt:
                raise SlscanError(
                    f"{path.parent}: mixes {fmt.upper()} ({first_path.name}) and {this.upper()} "
                    f"({path.name}) captures; expected one format"
                )
            header = _header(path)
            if header != first:
                hw, hh, hc, hd = header
                w, h, c, d = first
                raise SlscanError(
                    f"{path}: image is {hw}x{hh}, {hc} channel(s), {hd}-bit; expected "
                    f"{w}x{h}, {c} channel(s), {d}-bit like {first_path}"
                )
            if fmt == "tiff" and not lossy and _tiff_lossy(path):
                lossy = True
    return fmt, first, lossy


def _tiff_lossy(path: Path) -> bool:
    from PIL import Image

    with Image.open(path) as im:
        return "jpeg" in str(im.info.get("compression", "")).lower()


def _refuse_overlap(out: Path, src: Path, views: list[Path]) -> None:
    """Writing (or overwriting) ``out`` must never touch the source captures."""
    for folder in [src, *views]:
        if out == folder or out in folder.parents or (folder != src and folder in out.parents):
            raise SlscanError(
                f"{out}: the session must be written outside the source captures {folder}"
            )
