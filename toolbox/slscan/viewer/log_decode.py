"""Loggers for the decode stage: masks, code maps, stripe axes, saturation, range maps, metrics.

Entity tree, continuing :mod:`slscan.viewer.log`::

    world/camera/image/decode/mask         lit-and-decodable pixels    [view]
    world/camera/image/decode/codes        decoded region / column map, colour-mapped  [view]
    world/camera/image/decode/columns      projector column map (Gray code), colour-mapped  [view]
    world/camera/image/decode/rows         projector row map (Gray code), colour-mapped  [view]
    world/camera/image/decode/saturation   saturated pixels (red overlay)  [view]
    world/camera/image/decode/stripes      stripe medial axes / edges as 2D line strips  [view]
    world/camera/image/decode/<map>        a family decoder's further maps (DisplayMap), e.g.
                                           phase/wrapped/columns/period_8  [view]
    world/scans/view_NNN/range_map         Mesh3D of the range map (rig frame, mm)  [view]
    plot/decode/<metric>                   per-view scalars  [view]
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import TYPE_CHECKING

import cv2
import numpy as np
import rerun as rr

from slscan.viewer.log import _colors_u8, _overlay, _png, _set_view
from slscan.viewer.paths import DECODE_PATH, DECODE_PLOT_PATH, scan_path
from slscan.viewer.recording import first_static

if TYPE_CHECKING:
    from slscan.decode.family import DisplayMap
    from slscan.decode.samples import StripeSamples

STRIPE_COLOR = (40, 255, 120)
SATURATION_COLOR = (255, 30, 30, 160)
LABEL_DRAW_ORDER = 15.0
"""Marks of label maps (:class:`~slscan.decode.family.DisplayMap` with labels) over the
capture and the saturation overlay (10), under the stripe axes (20)."""
LABEL_RADIUS_UI = 1.5
"""Radius of a label map's marks, UI points: a single pixel stays visible when the image is
shown at a fraction of its size."""
MARKER_SIZE_UI = 3.0
"""Size of the point drawn for each view of a marked metric (a single view shows)."""
CV_COLORMAPS = {"turbo": cv2.COLORMAP_TURBO, "viridis": cv2.COLORMAP_VIRIDIS, "twilight": cv2.COLORMAP_TWILIGHT}
def colormap(values: np.ndarray, vmax: float) -> np.ndarray:
    """Turbo colours (h, w, 3) uint8 of ``values`` (h, w) over [0, vmax]; negative or NaN black."""
    valid = np.isfinite(values) & (values >= 0)
    scaled = np.zeros(values.shape, np.uint8)
    scaled[valid] = np.clip(values[valid] / max(vmax, 1e-9) * 255, 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)[..., ::-1]
    rgb[~valid] = 0
    return np.ascontiguousarray(rgb)


def colormap_range(values: np.ndarray, value_range: tuple[float, float], name: str = "turbo") -> np.ndarray:
    """Colours (h, w, 3) uint8 of ``values`` (h, w) across ``value_range`` with the colormap
    ``name`` ({"turbo", "viridis", "twilight"}; "twilight" wraps around the range); NaN black."""
    lo, hi = float(value_range[0]), float(value_range[1])
    valid = np.isfinite(values)
    t = (np.asarray(values, np.float64)[valid] - lo) / max(hi - lo, 1e-12)
    t = np.mod(t, 1.0) if name == "twilight" else np.clip(t, 0.0, 1.0)
    scaled = np.zeros(values.shape, np.uint8)
    scaled[valid] = np.minimum(t * 256, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(scaled, CV_COLORMAPS[name])[..., ::-1]
    rgb[~valid] = 0
    return np.ascontiguousarray(rgb)


def log_display_maps(
    rec: rr.RecordingStream | None, maps: Mapping[str, DisplayMap], *, view_index: int
) -> None:
    """A family decoder's further per-pixel maps (``FamilyDecode.maps``) at
    ``world/camera/image/decode/<name>``: colour-mapped PNGs, black where NaN.

    A label map (``labels``; sparse: e.g. the few pixels a decoder corrected) is a mark at
    each labelled pixel's centre, of :data:`LABEL_RADIUS_UI` on screen so that one pixel
    shows when the image is shown small, coloured and named (on hover) by its class under
    the map's annotation context (sent once per recording, static); class 0 is not drawn.
    """
    if rec is None or not maps:
        return
    _set_view(rec, view_index)
    for name, shown in maps.items():
        path = f"{DECODE_PATH}/{name}"
        if shown.labels is not None:
            if first_static(rec, path):
                infos = [rr.AnnotationInfo(id=int(k), label=label, color=color)
                         for k, (label, color) in shown.labels.items()]
                rec.log(path, rr.AnnotationContext(infos), static=True)
            classes = np.asarray(shown.values)
            ys, xs = np.nonzero(classes)
            rec.log(path, rr.Points2D(
                np.stack([xs, ys], axis=1).astype(np.float32) + 0.5,  # pixel centres in Rerun's image space
                class_ids=classes[ys, xs].astype(np.uint16),
                radii=rr.components.Radius.ui_points(LABEL_RADIUS_UI),
                draw_order=LABEL_DRAW_ORDER if shown.draw_order is None else shown.draw_order,
            ))
        else:
            rec.log(path, _png(colormap_range(shown.values, shown.value_range, shown.colormap),
                               draw_order=shown.draw_order))


def stripe_strips(samples: StripeSamples, *, max_gap_rows: int = 1) -> list[np.ndarray]:
    """Polylines (list of (k, 2) float32 [x, row]) joining each stripe's samples row by row."""
    if len(samples) == 0:
        return []
    # one polyline per stripe and search line kind: samples found along camera rows step
    # row by row, those found along camera columns (a turned projector) column by column
    line, _ = samples.lines()
    along = np.zeros(len(samples), bool) if samples.along_columns is None else np.asarray(samples.along_columns)
    order = np.lexsort((line, samples.stripe, along))
    stripe, line, kind = samples.stripe[order], line[order], along[order]
    breaks = np.flatnonzero((np.diff(stripe) != 0) | (np.diff(kind) != 0) | (np.diff(line) > max_gap_rows)) + 1
    points = samples.pixels()[order].astype(np.float32)
    return [p for p in np.split(points, breaks) if len(p) >= 2]


def log_decode_maps(
    rec: rr.RecordingStream | None,
    *,
    view_index: int,
    mask: np.ndarray,
    codes: np.ndarray,
    code_max: float,
    saturated: np.ndarray | None = None,
) -> None:
    """The validity mask, the decoded code map, and a red overlay of saturated pixels."""
    if rec is None:
        return
    _set_view(rec, view_index)
    rec.log(f"{DECODE_PATH}/mask", _png(mask.astype(np.uint8) * 255))
    rec.log(f"{DECODE_PATH}/codes", _png(colormap(codes.astype(np.float64), code_max)))
    if saturated is not None:
        rec.log(f"{DECODE_PATH}/saturation", _overlay(saturated, SATURATION_COLOR))


def log_projector_codes(
    rec: rr.RecordingStream | None,
    *,
    view_index: int,
    column: np.ndarray,
    row: np.ndarray | None,
    projector_size: tuple[int, int],
) -> None:
    """The projector column and row maps (int, -1 where not decoded), turbo over the
    projector's width and height; undecoded pixels black."""
    if rec is None:
        return
    _set_view(rec, view_index)
    rec.log(f"{DECODE_PATH}/columns", _png(colormap(column.astype(np.float32), projector_size[0] - 1)))
    if row is not None:
        rec.log(f"{DECODE_PATH}/rows", _png(colormap(row.astype(np.float32), projector_size[1] - 1)))


def log_stripes(rec: rr.RecordingStream | None, samples: StripeSamples, *, view_index: int) -> None:
    """Stripe axes as 2D line strips over the camera image."""
    if rec is None:
        return
    _set_view(rec, view_index)
    strips = stripe_strips(samples)
    rec.log(f"{DECODE_PATH}/stripes", rr.LineStrips2D(strips, colors=STRIPE_COLOR, radii=0.3, draw_order=20.0))


def log_range_map(
    rec: rr.RecordingStream | None,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None,
    colors: np.ndarray | None,
    *,
    view_index: int,
) -> None:
    """A view's range map as a mesh in the rig frame (mm)."""
    if rec is None:
        return
    _set_view(rec, view_index)
    rec.log(
        f"{scan_path(view_index)}/range_map",
        rr.Mesh3D(
            vertex_positions=vertices.astype(np.float32),
            triangle_indices=faces.astype(np.uint32),
            vertex_normals=None if normals is None else normals.astype(np.float32),
            vertex_colors=None if colors is None else _colors_u8(colors),
        ),
    )


def log_metrics(
    rec: rr.RecordingStream | None, metrics: Mapping[str, float], *, view_index: int, marked: Collection[str] = ()
) -> None:
    """Per-view scalars under ``plot/decode/`` (a name may be a path: ``phase/rows/x``).

    marked : names drawn with a point per view besides the line (styled once, static), so
        that a decode of one view shows them: a family decoder's ``stats``
    """
    if rec is None:
        return
    _set_view(rec, view_index)
    for name, value in metrics.items():
        if value is not None and np.isfinite(value):
            path = f"{DECODE_PLOT_PATH}/{name}"
            if name in marked and first_static(rec, path):
                rec.log(path, rr.SeriesLines(), rr.SeriesPoints(marker_sizes=MARKER_SIZE_UI), static=True)
            rec.log(path, rr.Scalars(float(value)))
