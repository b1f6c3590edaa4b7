"""What every pattern family's decoder gives: the plug-in interface of ``slscan.decode.<family>``.

A family (:class:`slscan.patterns.Family`) names its decoding module; the decode stage,
the scan command's live preview, calibration and the two-camera matcher call these
functions of it, never a family-specific one:

``decode(session, view, config) -> FamilyDecode`` (required)
    one view's captures to the samples the range map is triangulated from, with the
    masks and maps shown to the user; ``config`` is the decode stage's
    :class:`~slscan.decode.pipeline.DecodeConfig`, of which each decoder reads its own fields.
``projector_codes(session, view, config=None) -> ProjectorCodes`` (optional)
    the projector column (and row) at every decoded camera pixel: ``slscan decode --codes``,
    the inverse-camera calibration's pixel correspondences, two-camera matching.
``projector_constraints(session, view) -> ProjectorConstraints`` (optional)
    camera points whose projector column or row is known, for mapping board corners into
    the projector (the inverse-camera calibration); families that code rows.

A module that lacks an optional function does not offer it; :func:`decoder_function`
says so in one line naming the family.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from slscan.decode.samples import StripeSamples
from slscan.errors import SlscanError

COLORMAPS = ("turbo", "viridis", "twilight")
"""Colormaps a :class:`DisplayMap` may ask for; "twilight" is cyclic (its two ends meet)."""


@dataclass(frozen=True)
class DisplayMap:
    """A per-pixel map a family's decoder shows in the viewer, and how to colour it.

    values : (h, w) float, NaN where there is nothing to show (drawn black); with
        ``labels``, (h, w) int class ids
    colormap : {"turbo", "viridis", "twilight"} across ``value_range``; "twilight" is
        cyclic, for angles (a wrapped phase)
    value_range : (lo, hi), the values the colormap spans (clipped outside; cyclic: wrapped)
    labels : class id -> (name, (r, g, b, a)) for a sparse label map (a few marked
        pixels): the viewer draws a mark of fixed on-screen size at each pixel of a class
        other than 0, coloured and named (on hover) by its class
    draw_order : where several maps share a view, higher is drawn on top; None: the viewer's
    """

    values: np.ndarray
    colormap: str = "turbo"
    value_range: tuple[float, float] = (0.0, 1.0)
    labels: Mapping[int, tuple[str, tuple[int, int, int, int]]] | None = None
    draw_order: float | None = None

    def __post_init__(self) -> None:
        if self.colormap not in COLORMAPS:
            raise SlscanError(f"unknown colormap {self.colormap!r}: expected one of {', '.join(COLORMAPS)}")
        if np.ndim(self.values) != 2:
            raise SlscanError(f"a display map is (h, w), got shape {np.shape(self.values)}")


@dataclass(frozen=True)
class FamilyDecode:
    """One view decoded by a family's decoder, ready to triangulate and mesh.

    samples : the measured features (green-line axes, stripe edges, or every decoded pixel)
    mask : (h, w) bool decodable pixels
    codes : (h, w) display map of the decoded code (-1 or NaN where invalid), up to ``code_max``
    saturated : (h, w) bool pixels clipped in some image the samples use
    white : the white-frame capture as read (the range map's colours)
    max_gap_columns : the mesh's bridge across missing features, projector columns, when
        the family's features are spaced otherwise than the config assumes (Gray code
        with dropped bits); None: the config's
    projector_codes : :class:`~slscan.decode.codes.ProjectorCodes`, when decoding gave them
    valid_share : :class:`~slscan.decode.codes.ValidShare`, what limited the decoded share
    features : the samples are features the viewer draws as stripe axes (green lines,
        stripe edges); False: a sample at every decoded pixel (phase shifting), shown as maps
    maps : further per-pixel maps to stream to the viewer (:class:`DisplayMap`), by entity
        path under ``world/camera/image/decode`` (e.g. ``phase/wrapped/columns/period_8``)
    stats : further per-view numbers for ``range_maps.json`` and the viewer's plots, by
        name; a name may be a path (``phase/columns/order_corrected_share``), plotted under
        ``plot/decode/``
    """

    samples: StripeSamples
    mask: np.ndarray
    codes: np.ndarray
    code_max: int
    saturated: np.ndarray
    white: np.ndarray
    max_gap_columns: float | None = None
    features: bool = True
    projector_codes: Any = None
    valid_share: Any = None
    maps: Mapping[str, DisplayMap] = field(default_factory=dict)
    stats: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class ProjectorConstraints:
    """Camera points whose projector column or row is known (one coordinate each).

    x, y : (k,) float64 camera px (OpenCV pixel centres)
    value : (k,) float64 the projector column (``is_row`` False) or row (True), px
    is_row : (k,) bool
    """

    x: np.ndarray
    y: np.ndarray
    value: np.ndarray
    is_row: np.ndarray

    def __len__(self) -> int:
        return len(self.x)


def decoder_function(family, name: str, purpose: str) -> Callable:
    """The function ``name`` of ``family``'s decoder, or an error saying the family does
    not offer ``purpose``."""
    fn = getattr(family.decode_module(), name, None) if family.decoder else None
    if fn is None:
        raise SlscanError(f"the {family.name} patterns do not give {purpose}")
    return fn
