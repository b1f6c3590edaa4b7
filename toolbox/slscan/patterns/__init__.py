"""Projected patterns: descriptions that decoding can use alone, and their images.

A pattern set is a list of :class:`PatternImage` descriptions. Each family module
(:mod:`.hybrid`, :mod:`.graycode`, :mod:`.flat`) has a ``generate`` that returns
descriptions, and a ``profile`` that turns one description back into its pixels. A
description carries everything decoding needs (line positions and indices, band
colours, code bits), so decoding never depends on state kept from generation.

All patterns here vary along one projector axis (``"columns"``, ``"rows"``) or not at all
(``"none"``); :func:`profile` returns the (n, 3) RGB values along that axis.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir, read_json, write_json, write_png

FAMILIES = ("flat", "hybrid", "gray")
AXES = ("columns", "rows", "none")
SET_FAMILIES = ("hybrid", "gray", "both", "xor")
"""What :func:`standard_set` projects after white and black."""
PATTERN_SET_FORMAT = "slscan.pattern-set"
PATTERN_SET_VERSION = 1


@dataclass(frozen=True)
class PatternImage:
    """Description of one projected image.

    id : unique name within a set, e.g. ``"hybrid-03"``
    family : {"flat", "hybrid", "gray"}
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
        if self.family not in FAMILIES:
            raise SlscanError(f"pattern {self.id!r}: unknown family {self.family!r}, expected one of {FAMILIES}")
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
    from slscan.patterns import flat, graycode, hybrid

    module = {"flat": flat, "hybrid": hybrid, "gray": graycode}[desc.family]
    return module.profile(desc)


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
) -> list[PatternImage]:
    """White, black, then the family's patterns: the sequence projected for one range map.

    family : {"hybrid", "gray", "both", "xor"}; ``"xor"``: Gupta's XOR-04 codes, Gray
        code XOR-ed with its 4-px bit so every image is high-frequency
        (:mod:`.graycode`; described as family ``"gray"`` with ``code: "xor"``)
    levels : hybrid subdivision levels (``2**levels - 1`` green lines)
    rows : Gray (XOR) code only: also project row codes
    """
    from slscan.patterns import flat, graycode, hybrid

    if family not in SET_FAMILIES:
        raise SlscanError(f"unknown pattern family {family!r}: expected one of {', '.join(SET_FAMILIES)}")
    images = flat.generate(width, height)
    if family in ("hybrid", "both"):
        images += hybrid.generate(width, height, levels=levels)
    if family in ("gray", "both"):
        images += graycode.generate(width, height, rows=rows)
    if family == "xor":
        images += graycode.generate(width, height, rows=rows, code="xor")
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
    if data.get("format") != PATTERN_SET_FORMAT:
        raise SlscanError(f"{meta_path}: not an slscan pattern set (format {data.get('format')!r})")
    if data.get("version") != PATTERN_SET_VERSION:
        raise SlscanError(f"{meta_path}: pattern-set version {data.get('version')} is not supported")
    return [PatternImage.from_dict(e) for e in data["images"]]
