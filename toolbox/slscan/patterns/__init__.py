"""Projected patterns: descriptions that decoding can use alone, and their images.

A pattern set is a list of :class:`PatternImage` descriptions. Each family module
(:mod:`.hybrid`, :mod:`.graycode`, :mod:`.phase`, :mod:`.flat`) has a ``generate`` that
returns descriptions, and a ``profile`` that turns one description back into its pixels,
and registers itself with a ``FAMILY`` (:class:`Family`): the CLI, the capture driver, the
importers, calibration, decoding and the virtual rig ask the registry (:func:`family`,
:func:`families_in`, :func:`standard_set`) instead of switching on family names. A
description carries everything decoding needs (line positions and indices, band colours,
code bits, fringe periods and phase shifts), so decoding never depends on state kept from
generation.

All patterns here vary along one projector axis (``"columns"``, ``"rows"``) or not at all
(``"none"``); :func:`profile` returns the (n, 3) RGB values along that axis.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import os
import pkgutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from slscan.errors import SlscanError, about_file
from slscan.fsio import atomic_output_dir, read_json, write_json, write_png

AXES = ("columns", "rows", "none")
PATTERN_SET_FORMAT = "slscan.pattern-set"
PATTERN_SET_VERSION = 1


@dataclass(frozen=True)
class PatternImage:
    """Description of one projected image.

    id : unique name within a set, e.g. ``"hybrid-03"``
    family : a registered family (:func:`families`): "flat", "hybrid", "gray", "phase"
    width, height : projector pixels
    axis : {"columns", "rows", "none"}, the coordinate the image varies along
    params : family-specific fields, JSON types only (documented in each family module)
    """

    id: str
    family: str
    width: int
    height: int
    axis: str
    params: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.family not in _registry():
            raise SlscanError(
                f"pattern {self.id!r}: unknown family {self.family!r}, expected one of {', '.join(sorted(_registry()))}"
            )
        if self.axis not in AXES:
            raise SlscanError(f"pattern {self.id!r}: unknown axis {self.axis!r}, expected one of {AXES}")

    def to_dict(self) -> dict:
        return {
            "id": self.id, "family": self.family, "width": self.width, "height": self.height,
            "axis": self.axis, **self.params,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PatternImage:
        base = ("id", "family", "width", "height", "axis")
        missing = [k for k in base if k not in d]
        if missing:
            raise SlscanError(f"pattern description {d.get('id', '?')!r}: missing {', '.join(missing)}")
        params = {k: v for k, v in d.items() if k not in base and k != "file"}
        return cls(str(d["id"]), str(d["family"]), int(d["width"]), int(d["height"]), str(d["axis"]), params)


def profile(desc: PatternImage) -> np.ndarray:
    """RGB values (n, 3) uint8 along ``desc.axis`` (n = width, height, or 1 for "none")."""
    return family(desc.family).profile(desc)


def render(desc: PatternImage) -> np.ndarray:
    """The projector image (height, width, 3) uint8 of ``desc``."""
    values = profile(desc)
    if desc.axis == "columns":
        return np.ascontiguousarray(np.broadcast_to(values[None, :, :], (desc.height, desc.width, 3)))
    if desc.axis == "rows":
        return np.ascontiguousarray(np.broadcast_to(values[:, None, :], (desc.height, desc.width, 3)))
    return np.ascontiguousarray(np.broadcast_to(values[0], (desc.height, desc.width, 3)))


def standard_set(
    family: str = "hybrid",
    *,
    width: int = 1024,
    height: int = 768,
    levels: int = 9,
    rows: bool = False,
    **options: Any,
) -> list[PatternImage]:
    """White, black, then the family's patterns: the sequence projected for one range map.

    family : a set name of :func:`set_names`: "hybrid", "gray", "xor" (Gupta's XOR-04
        codes, Gray code XOR-ed with its 4-px bit so every image is high-frequency;
        described as family "gray" with ``code: "xor"``), "phase", or several joined by
        "+" ("hybrid+phase"); "both" is "hybrid+gray"
    levels : hybrid subdivision levels (``2**levels - 1`` green lines)
    rows : Gray code and phase shifting: also code the projector rows
    options : other keyword options of the families' ``generate`` (e.g. phase shifting's
        ``periods``, ``steps``, ``unwrap``); each goes to the families that take it, and one
        that no selected family takes is an error
    """
    from slscan.patterns import flat

    images = flat.generate(width, height)
    given = {"levels": levels, "rows": rows, **options}
    used = set()
    for fam, preset in _selected(family):
        takes = inspect.signature(fam.generate).parameters
        chosen = {k: v for k, v in given.items() if k in takes and k not in preset}
        used |= chosen.keys()
        images += fam.generate(width, height, **preset, **chosen)
    unused = sorted(set(options) - used)
    if unused:
        raise SlscanError(f"pattern option(s) {', '.join(unused)} do not apply to the {family!r} patterns")
    return images


def file_name(index: int, desc: PatternImage) -> str:
    return f"{index:02d}_{desc.id}.png"


def write_pattern_set(out: str | os.PathLike, images: list[PatternImage], *, overwrite: bool = False) -> Path:
    """Write PNGs a projector can show full-screen, and ``patterns.json`` describing them."""
    if not images:
        raise SlscanError("empty pattern set")
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        entries = []
        for i, desc in enumerate(images):
            name = file_name(i, desc)
            write_png(tmp / name, render(desc))
            entries.append({"file": name, **desc.to_dict()})
        write_json(
            tmp / "patterns.json",
            {
                "format": PATTERN_SET_FORMAT,
                "version": PATTERN_SET_VERSION,
                "projector": {"width": images[0].width, "height": images[0].height},
                "images": entries,
            },
        )
    return Path(out)


def read_pattern_set(path: str | os.PathLike) -> list[PatternImage]:
    """Read the descriptions of a folder written by :func:`write_pattern_set`."""
    path = Path(path)
    meta_path = path / "patterns.json" if path.is_dir() else path
    data = read_json(meta_path, "pattern-set description")
    with about_file(meta_path, "pattern-set description (patterns.json)"):
        if not isinstance(data, dict) or data.get("format") != PATTERN_SET_FORMAT:
            found = data.get("format") if isinstance(data, dict) else type(data).__name__
            raise SlscanError(f"{meta_path}: not an slscan pattern set (format {found!r})")
        if data.get("version") != PATTERN_SET_VERSION:
            raise SlscanError(f"{meta_path}: pattern-set version {data.get('version')} is not supported")
        images = [PatternImage.from_dict(e) for e in data["images"]]
        if not images:
            raise SlscanError(f"{meta_path}: the pattern set lists no images")
        return images


# --- the family registry -------------------------------------------------------------------


@dataclass(frozen=True)
class Option:
    """A pattern-set option a family's ``generate`` takes, as the CLI offers it.

    name : the keyword of ``generate`` (and of :func:`standard_set`)
    parse : turns the command-line text into the value (e.g. ``int``)
    default : the value when not given
    help : one line for ``--help``
    flag : the command-line flag, default ``--FAMILY-NAME`` (``--phase-periods``)
    """

    name: str
    parse: Callable[[str], Any]
    default: Any
    help: str
    flag: str = ""


@dataclass(frozen=True)
class Family:
    """One pattern family: what it projects, and which module decodes it.

    Each family is a pair of modules: ``slscan.patterns.<module>`` (``generate`` the
    descriptions, ``profile`` one of them) holding a ``FAMILY`` of this type, and the
    decoder named by ``decoder`` (``slscan.decode.<module>``). Everything else (the CLI's
    choices, the capture driver, the importers, calibration, the virtual rig) asks the
    registry (:func:`family`, :func:`families`, :func:`standard_set`), so a new family is
    one new pair of modules.

    name : the ``PatternImage.family`` of its images
    summary : one line for ``--help``
    generate : ``generate(width, height, **options) -> list[PatternImage]``
    profile : ``profile(desc) -> (n, 3) uint8`` values along ``desc.axis``
    decoder : the decoding module's dotted name, or None (flat frames decode nothing);
        it provides the functions of :class:`FamilyDecoder`
    sets : the set names that select the family (``--patterns``), each with the keyword
        arguments its ``generate`` gets: Gray code's ``{"gray": {}, "xor": {"code": "xor"}}``
    options : the keyword options of ``generate`` the CLI offers (see :class:`Option`)
    priority : "auto" decoding takes the family present with the highest priority
    lossy : decodes lossy (JPEG, 4:2:0 chroma) captures well; "auto" passes over a family
        that does not when another one is present
    rows : can code projector rows as well as columns (the inverse-camera calibration and
        two-camera matching need both)
    finest : ``finest(patterns) -> PatternImage | None``, the image with the finest detail
        of this family in a set (exposure and focus checks look at it)
    """

    name: str
    summary: str
    generate: Callable[..., list[PatternImage]]
    profile: Callable[[PatternImage], np.ndarray]
    decoder: str | None = None
    sets: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    options: tuple[Option, ...] = ()
    priority: int = 0
    lossy: bool = True
    rows: bool = False
    finest: Callable[[Sequence[PatternImage]], PatternImage | None] | None = None

    def decode_module(self) -> ModuleType:
        """The decoder module (imported on first use: it loads OpenCV)."""
        if self.decoder is None:
            raise SlscanError(f"pattern family {self.name!r} has no decoder")
        return importlib.import_module(self.decoder)


SET_ALIASES = {"both": ("hybrid", "gray")}
"""Set names that stand for several families' sets: "both" is the hybrid pattern and Gray code."""


@functools.cache
def _registry() -> dict[str, Family]:
    """Every family, found as the ``FAMILY`` of the modules of this package."""
    found = {}
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{__name__}.{info.name}")
        fam = getattr(module, "FAMILY", None)
        if isinstance(fam, Family):
            if fam.name in found:
                raise SlscanError(f"two pattern families named {fam.name!r}")
            found[fam.name] = fam
    return found


def families() -> tuple[Family, ...]:
    """Every registered family, the highest "auto" priority first."""
    return tuple(sorted(_registry().values(), key=lambda f: (-f.priority, f.name)))


def family(name: str) -> Family:
    """The family named ``name``; an error listing the known ones otherwise."""
    reg = _registry()
    if name not in reg:
        raise SlscanError(f"unknown pattern family {name!r}: expected one of {', '.join(sorted(reg))}")
    return reg[name]


def decodable() -> tuple[str, ...]:
    """Names of the families with a decoder, the highest "auto" priority first."""
    return tuple(f.name for f in families() if f.decoder is not None)


def set_names() -> tuple[str, ...]:
    """Every name :func:`standard_set` (and ``--patterns``) accepts."""
    names = [s for f in families() for s in f.sets]
    return tuple(sorted(names)) + tuple(SET_ALIASES)


def set_families(name: str) -> tuple[str, ...]:
    """Names of the families a set name (:func:`standard_set`'s ``family``) selects."""
    return tuple(dict.fromkeys(f.name for f, _ in _selected(name)))


def with_rows(name: str) -> str:
    """A set name that codes the projector rows: ``name`` itself when one of its families
    can (Gray code, phase shifting), else ``name`` plus Gray code ("hybrid" -> "hybrid+gray"):
    what the inverse-camera calibration and two-camera matching need."""
    return name if any(family(f).rows for f in set_families(name)) else f"{name}+gray"


def families_in(patterns: Sequence[PatternImage]) -> tuple[Family, ...]:
    """The decodable families a pattern set holds, the highest "auto" priority first."""
    present = {p.family for p in patterns}
    return tuple(f for f in families() if f.name in present and f.decoder is not None)


def _selected(name: str) -> list[tuple[Family, dict]]:
    """(family, generate keywords) of every set a set name selects (``"a+b"`` for several)."""
    parts = [p.strip() for p in name.split("+")]
    parts = [q for p in parts for q in SET_ALIASES.get(p, (p,))]
    out = []
    for part in parts:
        fam = next((f for f in families() if part in f.sets), None)
        if fam is None:
            raise SlscanError(f"unknown pattern family {part!r}: expected one of {', '.join(set_names())}")
        out.append((fam, dict(fam.sets[part])))
    return out


# --- the command line -----------------------------------------------------------------------


def pattern_set_name(text: str) -> str:
    """``argparse`` type of a set name: one of :func:`set_names`, or several joined by "+"."""
    import argparse

    try:
        _selected(text)
    except SlscanError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def _flag(fam: Family, opt: Option) -> str:
    return opt.flag or f"--{fam.name}-{opt.name.replace('_', '-')}"


def add_pattern_arguments(parser, *, flag: str = "--patterns", default: str = "hybrid") -> None:
    """Add the pattern-set choice (``flag``) and every family's options (:class:`Option`)
    to an ``argparse`` parser; :func:`pattern_options` reads the options back."""
    summaries = "; ".join(f"{fam.name}: {fam.summary}" for fam in families())
    parser.add_argument(
        flag, type=pattern_set_name, default=default, metavar="SET",
        help=f"coded patterns after white and black (default: {default}): {', '.join(set_names())}, or "
             f"several joined by + ({summaries}; both: hybrid+gray)",
    )
    for fam in families():
        for opt in fam.options:
            parser.add_argument(_flag(fam, opt), dest=f"pattern_option_{opt.name}", type=opt.parse,
                                default=None, help=f"{fam.name} patterns: {opt.help} (default {opt.default})")


def pattern_options(args) -> dict[str, Any]:
    """The family options given on the command line (those left out take their defaults)."""
    return {opt.name: value for fam in families() for opt in fam.options
            if (value := getattr(args, f"pattern_option_{opt.name}", None)) is not None}
