"""Bake the views' un-shaded colour into a texture atlas, and onto the vertices.

For every texel covered by a chart (its surface point and interpolated normal found by
rasterising the atlas triangles in texture space) and for every registered view:

1. the point is projected through the view's camera (distortion included);
2. it is **visible** when the model's own depth, ray cast from that view, is not nearer
   than the point by more than a tolerance that grows with the pixel footprint and the
   surface slope;
3. its colour is the bilinear sample of the view's linear albedo, weighted by
   ``cos(angle)^p`` (viewing angle), a ramp on the distance to the nearest depth
   discontinuity or unknown albedo, and a ramp on the distance to the image border — so
   the colour of each view fades out before its edges and seams between views blend;
4. the weighted mean over views is the texel's colour.

Texels no view sees take the colour interpolated from the per-vertex bake (which fills
unseen vertices from the nearest seen ones); then the charts are padded into the gutter
so bilinear sampling and mip-mapping do not pull in background across seams. The same
view blending on the vertices gives the per-vertex colour fallback.

The blending follows the weighting of Callieri, Cignoni, Scopigno, "Reconstructing
textured meshes from multiple range+RGB maps" (VMV 2002; the paper's ref. 8) and
Bernardini, Martin, Rushmeier, "High-quality texture reconstruction from multiple scans"
(TVCG 2001): per-pixel weights from view angle, depth-discontinuity and border distance.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.texture.views import TextureView

log = logging.getLogger(__name__)

BYTES_PER_TEXEL = 64
"""Peak working memory per atlas texel (rasterisation, points, normals, accumulators)."""


@dataclass(frozen=True)
class BakeOptions:
    """How views are weighted and blended (lengths in camera pixels unless noted)."""

    max_angle_deg: float = 80.0
    """A view sees a surface point at most this obliquely (angle between normal and ray)."""
    angle_power: float = 2.0
    """Weight ``cos(angle) ** angle_power``."""
    edge_px: float = 12.0
    """Weight ramps from 0 to 1 over this distance from a depth discontinuity or unknown albedo."""
    border_px: float = 24.0
    """Weight ramps from 0 to 1 over this distance from the image border."""
    depth_slack_px: float = 1.5
    """Visibility tolerance: this many pixel footprints plus the slope's depth change."""
    jump_px: float = 12.0
    """Neighbouring depths differing by more than this many pixel footprints are a discontinuity."""
    prior_weight: float = 0.01
    """Texels seen only weakly (total weight about this or less, e.g. one view at more than
    ~75 degrees) are pulled towards the per-vertex colour with this weight."""
    padding: int = 4
    """Texels the charts are extended into the gutter."""
    chunk: int = 2_000_000
    """Texels processed at once."""
    views_per_task: int = 8
    """Views baked by one task (one process at a time: its views' images and depth maps one
    after the other, the texels' points shared); the tasks' sums are added in order, so a
    change of this number changes the atlas by float32 rounding only."""
    cull: bool = True
    """Project a texel only into the views whose frustum holds it and that face it, tested
    on blocks of nearby texels with conservative bounds (:func:`point_blocks`); False:
    every texel into every view (the same result, kept to measure against)."""


@dataclass(frozen=True, eq=False)
class DepthMap:
    """The model as a view sees it: depth z (mm, camera frame) per pixel, inf where empty,
    and the per-pixel distance (px) to a depth discontinuity or unknown albedo."""

    depth: np.ndarray
    edge_distance: np.ndarray


@dataclass(frozen=True, eq=False)
class Blend:
    """Blended colour of a set of surface points.

    color : (k, 3) float32 linear RGB, NaN where no view sees the point
    weight : (k,) float32 summed weight
    views : (k,) uint8 number of views that contributed
    """

    color: np.ndarray
    weight: np.ndarray
    views: np.ndarray


@dataclass(frozen=True, eq=False)
class BakedTexture:
    """The baked atlas.

    linear : (size, size, 3) float32 linear RGB (padded; background = mean colour)
    covered : (size, size) bool, texels inside a chart
    observed : (size, size) bool, texels some view saw (the rest were filled)
    view_count : (size, size) uint8 views blended per texel
    vertex_colors : (n, 3) float32 linear RGB per input vertex (filled, no NaN)
    vertex_observed : (n,) bool
    seconds : wall time per phase
    view_model_share : {view name: share of the view's known-albedo pixels on which the
        model lies} (:func:`model_share`): near 1 where the model is the object the view saw,
        where the view saw it
    """

    linear: np.ndarray
    covered: np.ndarray
    observed: np.ndarray
    view_count: np.ndarray
    vertex_colors: np.ndarray
    vertex_observed: np.ndarray
    seconds: dict = field(default_factory=dict)
    view_model_share: dict = field(default_factory=dict)

    @property
    def size(self) -> int:
        return self.linear.shape[0]


# --- rasterising the atlas ----------------------------------------------------------------------


def rasterise_uv(uv_px: np.ndarray, faces: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texels whose centre lies in a triangle of the atlas.

    uv_px : (m, 2) texture coordinates in texels (x = column, y = row; texel centres at
        integers)
    faces : (n, 3) indices into ``uv_px``
    Returns ``(texel, face, bary)``: flat texel index ``row * size + col`` (k,), the face
    covering it (k,), and barycentric coordinates (k, 3) float32 — one entry per texel
    (on a shared edge the lower face index wins).
    """
    tri = np.asarray(uv_px, np.float64)[np.asarray(faces)]
    a = tri[:, 0]
    e1 = tri[:, 1] - a
    e2 = tri[:, 2] - a
    det = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    lo = np.ceil(tri.min(axis=1) - 1e-9).astype(np.int64)
    hi = np.floor(tri.max(axis=1) + 1e-9).astype(np.int64)
    lo = np.clip(lo, 0, size - 1)
    hi = np.clip(hi, -1, size - 1)
    extent = np.maximum(hi - lo + 1, 0)
    span = extent.max(axis=1)
    ok = (np.abs(det) > 1e-12) & (extent.min(axis=1) > 0)
    out_texel, out_face, out_bary = [], [], []
    bounds = [0, 1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256]
    while bounds[-1] < span.max(initial=0):
        bounds.append(bounds[-1] * 2)
    for lo_s, hi_s in itertools.pairwise(bounds):
        ids = np.nonzero(ok & (span > lo_s) & (span <= hi_s))[0]
        if len(ids) == 0:
            continue
        s = hi_s
        dy, dx = np.divmod(np.arange(s * s), s)
        per_chunk = max(1, 4_000_000 // (s * s))
        for start in range(0, len(ids), per_chunk):
            f = ids[start:start + per_chunk]
            px = lo[f, 0:1] + dx[None, :]
            py = lo[f, 1:2] + dy[None, :]
            vx = px - a[f, 0:1]
            vy = py - a[f, 1:2]
            d = det[f, None]
            b1 = (vx * e2[f, 1:2] - e2[f, 0:1] * vy) / d
            b2 = (e1[f, 0:1] * vy - vx * e1[f, 1:2]) / d
            b0 = 1.0 - b1 - b2
            inside = (b0 >= -1e-9) & (b1 >= -1e-9) & (b2 >= -1e-9)
            inside &= (px <= hi[f, 0:1]) & (py <= hi[f, 1:2])
            r, c = np.nonzero(inside)
            out_texel.append(py[r, c] * size + px[r, c])
            out_face.append(f[r])
            out_bary.append(np.stack([b0[r, c], b1[r, c], b2[r, c]], axis=1).astype(np.float32))
    if not out_texel:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    texel = np.concatenate(out_texel)
    face = np.concatenate(out_face)
    bary = np.concatenate(out_bary)
    order = np.lexsort((face, texel))
    texel, face, bary = texel[order], face[order], bary[order]
    first = np.ones(len(texel), bool)
    first[1:] = texel[1:] != texel[:-1]
    return texel[first], face[first], np.clip(bary[first], 0.0, 1.0)


# --- what each view sees ------------------------------------------------------------------------


def _raycasting_scene(vertices: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)),
    )
    return scene


def model_share(depth: DepthMap, view: TextureView) -> float:
    """Share of ``view``'s pixels of known albedo (the object it saw) on which the model
    lies (finite ``depth``); NaN for a view with no known albedo. The right model, where the
    views saw it, covers nearly all of them (silhouette pixels aside); another object, or
    the model moved or turned, leaves many uncovered (``benchmarks/texture_seen.py``)."""
    known = np.all(np.isfinite(view.albedo), axis=2)
    n = int(known.sum())
    return float((known & np.isfinite(depth.depth)).sum() / n) if n else float("nan")


def depth_map(scene, view: TextureView, options: BakeOptions) -> DepthMap:
    """Ray cast the model from ``view`` and find where its colour must fade out."""
    import cv2
    import open3d as o3d

    from slscan.rig import pixel_rays

    cam = view.camera
    rays_cam = pixel_rays(cam)  # (h, w, 3) unit, camera frame
    m = np.asarray(view.world_from_camera, float)
    dirs = rays_cam.reshape(-1, 3) @ m[:3, :3].T
    origins = np.broadcast_to(m[:3, 3], dirs.shape)
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().reshape(cam.height, cam.width)
    depth = (t * rays_cam[..., 2]).astype(np.float32)  # inf stays inf
    footprint = np.where(np.isfinite(depth), depth, 0.0) / cam.fx
    usable = np.isfinite(depth) & np.all(np.isfinite(view.albedo), axis=2)
    limit = options.jump_px * footprint
    finite = np.where(np.isfinite(depth), depth, 0.0)
    jump = np.zeros_like(usable)
    dx = np.abs(np.diff(finite, axis=1)) > np.maximum(limit[:, 1:], limit[:, :-1])
    dy = np.abs(np.diff(finite, axis=0)) > np.maximum(limit[1:], limit[:-1])
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    jump[1:] |= dy
    jump[:-1] |= dy
    usable &= ~jump
    edge = cv2.distanceTransform(usable.astype(np.uint8), cv2.DIST_L2, 5).astype(np.float32)
    return DepthMap(depth, edge)


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (k, c) of ``image`` (h, w, c) at pixel centres ``x, y``; NaN if a
    neighbour is NaN. Coordinates must lie within [0, w-1] x [0, h-1]."""
    h, w = image.shape[:2]
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2) if w > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(np.floor(y).astype(np.int64), h - 2) if h > 1 else np.zeros(len(y), np.int64)
    fx = (x - x0).astype(np.float32)[:, None]
    fy = (y - y0).astype(np.float32)[:, None]
    step_x = np.minimum(x0 + 1, w - 1) - x0
    step_y = (np.minimum(y0 + 1, h - 1) - y0) * w
    flat = image.reshape(h * w, -1)  # one flat gather per corner: cheaper than image[y, x]
    i00 = y0 * w + x0
    top = flat.take(i00, axis=0) * (1 - fx) + flat.take(i00 + step_x, axis=0) * fx
    i10 = i00 + step_y
    bottom = flat.take(i10, axis=0) * (1 - fx) + flat.take(i10 + step_x, axis=0) * fx
    return top * (1 - fy) + bottom * fy


@dataclass(frozen=True, eq=False)
class Blocks:
    """Surface points grouped for culling: ``members`` (b, size) indices into the points
    (``-1`` pads the last block), spatially coherent and of similar normal; every point of
    block ``i`` lies within ``radius[i]`` of ``centre[i]`` and its normal within
    ``spread[i]`` radians of the unit ``axis[i]`` (``spread`` = pi: unbounded)."""

    members: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    axis: np.ndarray
    spread: np.ndarray


CULL_BLOCK = 256
"""Points per culling block."""
CULL_MARGIN_RAD = 1e-3
"""Angles are culled only this far beyond their bound (float rounding)."""


def point_blocks(points: np.ndarray, normals: np.ndarray, size: int = CULL_BLOCK) -> Blocks:
    """Group ``points`` (k, 3) with unit ``normals`` into blocks of ``size`` for culling:
    sorted by the normal's dominant axis (6 classes), then by a grid cell holding about
    ``size`` points of the surface, then cut into consecutive runs."""
    k = len(points)
    p = np.asarray(points)
    n = np.asarray(normals)
    lo = p.min(axis=0).astype(np.float64)
    hi = p.max(axis=0).astype(np.float64)
    diagonal = float(np.linalg.norm(hi - lo)) or 1.0
    cell = diagonal * math.sqrt(size / max(k, 1))  # a surface of ~k points: ~k / size cells
    dims = np.floor((hi - lo) / cell).astype(np.int64) + 2
    major = np.abs(n).argmax(axis=1)
    key = 2 * major + (np.take_along_axis(n, major[:, None], axis=1)[:, 0] < 0)
    del major
    for i in range(3):  # column by column: a few bytes per point at a time
        cells = np.clip(np.floor((p[:, i] - lo[i]) / cell), 0, dims[i] - 1).astype(np.int64)
        key = key * dims[i] + cells
    del cells
    order = np.argsort(key)
    del key
    b = -(-k // size)
    members = np.full(b * size, -1, np.int64)
    members[:k] = order
    del order
    members = members.reshape(b, size)
    # bounds, coordinate by coordinate on (b, size) arrays; pads repeat their block's first point
    filled = np.where(members >= 0, members, members[:, :1])
    columns = [p[:, i].take(filled).astype(np.float64) for i in range(3)]
    centre = np.stack([0.5 * (c.min(axis=1) + c.max(axis=1)) for c in columns], axis=1)
    del columns
    d2 = np.zeros(filled.shape)
    for i in range(3):
        d2 += (p[:, i].take(filled) - centre[:, i:i + 1]) ** 2
    radius = np.sqrt(d2.max(axis=1))
    del d2
    # points may be float32: allow for their rounding at the model's scale
    radius = radius * (1 + 1e-6) + 1e-5 * (1.0 + float(np.abs(p).max(initial=0.0)))
    axis = np.stack([n[:, i].take(filled).sum(axis=1, dtype=np.float64) for i in range(3)], axis=1)
    length = np.linalg.norm(axis, axis=1)
    axis /= np.maximum(length, 1e-12)[:, None]
    dot = np.zeros(filled.shape)
    norm2 = np.zeros(filled.shape)
    for i in range(3):
        c = n[:, i].take(filled).astype(np.float64)
        dot += c * axis[:, i:i + 1]
        norm2 += c * c
    cos = (dot / np.maximum(np.sqrt(norm2), 1e-12)).min(axis=1)
    spread = np.where(length > 1e-6, np.arccos(np.clip(cos, -1.0, 1.0)), np.pi)
    return Blocks(members, centre, radius, axis, spread)


def _view_frustum(cam) -> np.ndarray:
    """(4, 3) unit inward normals of the planes through the camera centre bounding the
    rays of the image (undistorted from a dense walk round its border, widened by 1 %)."""
    w, h = cam.width, cam.height
    xs = np.linspace(-0.5, w - 0.5, max(2, w // 4))
    ys = np.linspace(-0.5, h - 0.5, max(2, h // 4))
    border = np.concatenate([
        np.stack([xs, np.full_like(xs, -0.5)], 1), np.stack([xs, np.full_like(xs, h - 0.5)], 1),
        np.stack([np.full_like(ys, -0.5), ys], 1), np.stack([np.full_like(ys, w - 0.5), ys], 1),
    ])
    rays = cam.rays_local(border)
    x0, x1 = rays[:, 0].min(), rays[:, 0].max()
    y0, y1 = rays[:, 1].min(), rays[:, 1].max()
    pad_x, pad_y = 0.01 * (x1 - x0) + 1e-6, 0.01 * (y1 - y0) + 1e-6
    x0, x1, y0, y1 = x0 - pad_x, x1 + pad_x, y0 - pad_y, y1 + pad_y
    planes = np.array([[1.0, 0.0, -x0], [-1.0, 0.0, x1], [0.0, 1.0, -y0], [0.0, -1.0, y1]])
    return planes / np.linalg.norm(planes, axis=1, keepdims=True)


def blocks_in_view(blocks: Blocks, view: TextureView, max_angle_deg: float) -> np.ndarray:
    """Indices of the blocks some point of which may be in front of ``view``, inside its
    image and facing it at most ``max_angle_deg`` obliquely (the rest cannot be)."""
    m = view.camera_from_world
    c = blocks.centre @ m[:3, :3].T + m[:3, 3]
    r = blocks.radius
    keep = c[:, 2] + r > 0
    for plane in _view_frustum(view.camera):
        keep &= c @ plane + r >= 0
    dist = np.linalg.norm(c, axis=1)
    toward = -c / np.maximum(dist, 1e-12)[:, None]
    axis = blocks.axis @ m[:3, :3].T
    angle = np.arccos(np.clip(np.einsum("ij,ij->i", axis, toward), -1.0, 1.0))
    # the rays to the block's points deviate from the ray to its centre by at most this
    ray_spread = np.where(dist > r, np.arcsin(np.clip(r / np.maximum(dist, 1e-12), 0.0, 1.0)), np.pi)
    keep &= angle - blocks.spread - ray_spread <= math.radians(max_angle_deg) + CULL_MARGIN_RAD
    return np.nonzero(keep)[0]


@dataclass(frozen=True, eq=False)
class Targets:
    """Surface points laid out for blending (:func:`blend_targets`): coordinates and unit
    normals in columns ``pts``, ``nms`` (3, rows, width) float32 (a row is a culling block,
    or ``chunk`` points in their order without culling), ``target_of`` (rows, width) the
    point each entry is (``k`` for padding), ``blocks`` the rows' culling bounds (their
    ``members`` may be empty: ``target_of`` has them), ``k`` the number of points."""

    pts: np.ndarray
    nms: np.ndarray
    target_of: np.ndarray
    blocks: Blocks | None
    k: int


@dataclass(frozen=True, eq=False)
class Sums:
    """Weighted colour sums of the points some views saw, sparse: ``index`` (m,) int64 the
    points (ascending), ``acc`` (m, 3) float32 the sum of colour x weight, ``weight`` (m,)
    float32 the sum of weights, ``views`` (m,) uint8 the views that contributed."""

    index: np.ndarray
    acc: np.ndarray
    weight: np.ndarray
    views: np.ndarray


def blend_targets(points: np.ndarray, normals: np.ndarray, options: BakeOptions) -> Targets:
    """Lay ``points`` (k, 3) with unit ``normals`` out for :func:`accumulate_view`: in
    culling blocks (:func:`point_blocks`) with ``options.cull``, else in rows of
    ``options.chunk`` points."""
    k = len(points)
    blocks = point_blocks(points, normals) if options.cull and k else None
    if blocks is None:  # rows of ``chunk`` points in their order
        width = max(1, min(options.chunk, k))
        members = np.full(-(-k // width) * width, -1, np.int64)
        members[:k] = np.arange(k)
        members = members.reshape(-1, width)
    else:
        members = blocks.members
    # coordinates in columns (3, rows, width): a view gathers its blocks as contiguous runs
    ordered = np.where(members >= 0, members, 0)
    pts = np.asarray(points, np.float32)[ordered].transpose(2, 0, 1)
    nms = np.asarray(normals, np.float32)[ordered].transpose(2, 0, 1)
    del ordered
    target_of = np.where(members >= 0, members, k).astype(np.int32 if k < 2**31 - 1 else np.int64)
    if blocks is not None:
        blocks = Blocks(np.zeros((0, 0), np.int64), blocks.centre, blocks.radius, blocks.axis, blocks.spread)
    return Targets(np.ascontiguousarray(pts), np.ascontiguousarray(nms), target_of, blocks, k)


def accumulate_view(
    targets: Targets,
    view: TextureView,
    dm: DepthMap,
    options: BakeOptions,
    acc: np.ndarray,
    wsum: np.ndarray,
    count: np.ndarray,
) -> None:
    """Add ``view``'s weighted colour at the ``targets`` it sees to ``acc`` (k + 1, 3),
    ``wsum`` (k + 1,) float32 and ``count`` (k + 1,) uint8 (the last row takes padding)."""
    cam = view.camera
    m = view.camera_from_world
    centre = np.asarray(view.world_from_camera, float)[:3, 3]
    axis = m[2, :3]  # the optical axis in the world frame
    cos_min = math.cos(math.radians(options.max_angle_deg))
    target_of = targets.target_of
    chunk_rows = max(1, options.chunk // target_of.shape[1])
    blocks = targets.blocks
    rows = np.arange(len(target_of)) if blocks is None else blocks_in_view(blocks, view, options.max_angle_deg)
    depth_flat = dm.depth.ravel()
    edge_flat = dm.edge_distance.ravel()
    for start in range(0, len(rows), chunk_rows):
        sel = rows[start:start + chunk_rows]
        p = targets.pts[:, sel].reshape(3, -1).astype(np.float64)
        nrm = targets.nms[:, sel].reshape(3, -1)
        # the tests in the world frame, column by column (no (k, 3) matrix products):
        # the ray to the camera centre, its length and depth are those of the camera frame
        ray = [centre[i] - p[i] for i in range(3)]
        del p
        dist = np.sqrt(ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2])
        cos = (nrm[0] * ray[0] + nrm[1] * ray[1] + nrm[2] * ray[2]) / np.maximum(dist, 1e-12)
        depth = -(axis[0] * ray[0] + axis[1] * ray[1] + axis[2] * ray[2])
        idx = np.nonzero((cos > cos_min) & (depth > 0))[0]
        del dist, depth, nrm
        if len(idx) == 0:
            continue
        sub = [ray[0][idx], ray[1][idx], ray[2][idx]]
        del ray
        pc = np.stack([-(r[0] * sub[0] + r[1] * sub[1] + r[2] * sub[2]) for r in m[:3, :3]], axis=1)
        del sub
        pix = cam.project_local(pc)
        x, y = pix[:, 0], pix[:, 1]
        inside = (x >= 0) & (y >= 0) & (x <= cam.width - 1) & (y <= cam.height - 1)
        idx, x, y = idx[inside], x[inside], y[inside]
        z = pc[inside, 2]
        del pc, pix
        xi, yi = np.rint(x).astype(np.int64), np.rint(y).astype(np.int64)
        c = cos[idx]
        del cos
        tan = np.sqrt(np.maximum(1.0 - c * c, 0.0)) / c
        slack = (z / cam.fx) * (options.depth_slack_px + tan)
        pixel = yi * cam.width + xi
        visible = z <= depth_flat.take(pixel) + slack
        idx, x, y, pixel, c = idx[visible], x[visible], y[visible], pixel[visible], c[visible]
        edge = np.clip(edge_flat.take(pixel) / options.edge_px, 0.0, 1.0)
        border = np.minimum.reduce([x, y, cam.width - 1 - x, cam.height - 1 - y])
        w = (c ** options.angle_power) * edge * np.clip(border / options.border_px, 0.0, 1.0)
        color = _bilinear(view.albedo, x, y)
        good = (w > 0) & np.all(np.isfinite(color), axis=1)
        target = target_of[sel].ravel()[idx[good]]
        acc[target] += (color[good] * w[good, None]).astype(np.float32)
        wsum[target] += w[good].astype(np.float32)
        count[target] += 1


def _accumulators(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zeroed ``acc`` (k + 1, 3), ``wsum`` (k + 1,) float32 and ``count`` (k + 1,) uint8."""
    return np.zeros((k + 1, 3), np.float32), np.zeros(k + 1, np.float32), np.zeros(k + 1, np.uint8)


def _finish(acc: np.ndarray, wsum: np.ndarray, count: np.ndarray, k: int) -> Blend:
    acc, wsum, count = acc[:k], wsum[:k], count[:k]
    with np.errstate(invalid="ignore", divide="ignore"):
        color = np.where(wsum[:, None] > 0, acc / wsum[:, None], np.nan).astype(np.float32)
    return Blend(color, wsum, count)


def blend_views(
    points: np.ndarray,
    normals: np.ndarray,
    views: Sequence[TextureView],
    depths: Sequence[DepthMap],
    options: BakeOptions,
) -> Blend:
    """The views' weighted mean colour at surface ``points`` (k, 3) with unit ``normals``.

    With ``options.cull`` the points are grouped in blocks (:func:`point_blocks`) and each
    view takes only the blocks :func:`blocks_in_view` keeps: the same result (the bounds
    are conservative; every point's arithmetic is the same), at a cost that follows the
    views that can see a point rather than all views.
    """
    k = len(points)
    targets = blend_targets(points, normals, options)
    acc, wsum, count = _accumulators(k)
    for view, dm in zip(views, depths):
        accumulate_view(targets, view, dm, options, acc, wsum, count)
    return _finish(acc, wsum, count, k)


# --- the whole bake -----------------------------------------------------------------------------


def check_texture_memory(size: int, *, available: int | None = None) -> None:
    """Raise when baking a ``size`` × ``size`` atlas would not fit in memory."""
    if size < 16 or size > 16384:
        raise SlscanError(f"texture size {size}: expected 16 to 16384 texels")
    need = size * size * BYTES_PER_TEXEL
    if available is None:
        available = _available_memory()
    if available and need > available:
        raise SlscanError(
            f"texture size {size}: baking needs about {need / 2**30:.1f} GiB of memory, "
            f"{available / 2**30:.1f} GiB are available; choose a smaller --size"
        )


def _available_memory() -> int:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def _fill_vertices(vertices: np.ndarray, color: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unseen vertices (NaN) take the colour of the nearest seen one."""
    from scipy.spatial import cKDTree

    seen = np.all(np.isfinite(color), axis=1)
    out = color.copy()
    if not seen.any():
        out[:] = 0.5
        return out, seen
    if not seen.all():
        _, nearest = cKDTree(vertices[seen]).query(vertices[~seen])
        out[~seen] = color[seen][nearest]
    return out, seen


def pad_charts(image: np.ndarray, covered: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow the charts' colours ``iterations`` texels into the uncovered gutter (each new
    texel takes the mean of its covered 8-neighbours)."""
    import cv2

    image = image.copy()
    mask = covered.astype(np.float32)
    for _ in range(iterations):
        weight = cv2.boxFilter(mask, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        grow = (weight > 0) & (mask == 0)
        if not grow.any():
            break
        total = cv2.boxFilter(image * mask[..., None], -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        image[grow] = total[grow] / weight[grow][:, None]
        mask[grow] = 1.0
    return image, mask > 0


@dataclass(frozen=True, eq=False)
class _Shared:
    """What every bake task needs besides its views: the model (``vertices`` (n, 3)
    float32 mm, ``faces`` (f, 3)) for ray casting, and the vertices' and texels'
    :class:`Targets`."""

    vertices: np.ndarray
    faces: np.ndarray
    vertex_targets: Targets
    texel_targets: Targets

    _ARRAYS = ("pts", "nms", "target_of")
    _BOUNDS = ("centre", "radius", "axis", "spread")

    def save(self, folder: Path) -> None:
        """Write the arrays as ``.npy`` files into ``folder`` (for tasks in other processes)."""
        np.save(folder / "vertices.npy", self.vertices)
        np.save(folder / "faces.npy", self.faces)
        for name, t in (("vertex", self.vertex_targets), ("texel", self.texel_targets)):
            for a in self._ARRAYS:
                np.save(folder / f"{name}_{a}.npy", getattr(t, a))
            if t.blocks is not None:
                for a in self._BOUNDS:
                    np.save(folder / f"{name}_{a}.npy", getattr(t.blocks, a))
        (folder / "counts.txt").write_text(f"{self.vertex_targets.k} {self.texel_targets.k}\n")

    @classmethod
    def load(cls, folder: str) -> _Shared:
        """The arrays :meth:`save` wrote, memory-mapped (the processes of one machine share
        their pages)."""
        path = Path(folder)
        if not (path / "counts.txt").is_file():
            raise SlscanError(f"{path}: the bake's shared arrays are not there (a worker needs the output's "
                              "folder at the same path as the caller)")
        counts = [int(c) for c in (path / "counts.txt").read_text().split()]

        def load(name: str) -> np.ndarray:
            return np.load(path / f"{name}.npy", mmap_mode="r")

        targets = []
        for name, k in zip(("vertex", "texel"), counts):
            blocks = None
            if (path / f"{name}_centre.npy").is_file():
                bounds = (np.asarray(load(f"{name}_{a}")) for a in cls._BOUNDS)
                blocks = Blocks(np.zeros((0, 0), np.int64), *bounds)
            targets.append(Targets(*(load(f"{name}_{a}") for a in cls._ARRAYS), blocks, k))
        return cls(np.asarray(load("vertices")), np.asarray(load("faces")), *targets)


@dataclass(frozen=True, eq=False)
class _BakeTask:
    """A group of views to bake: ``shared`` in memory, or the folder it was saved in."""

    shared: _Shared | str
    views: tuple
    options: BakeOptions


@dataclass(frozen=True, eq=False)
class _GroupSums:
    """A task's result: its views' sums on the texels and on the vertices, and each
    view's :func:`model_share`."""

    texels: Sums
    vertices: Sums
    shares: dict


def _sparse(acc: np.ndarray, wsum: np.ndarray, count: np.ndarray, k: int) -> Sums:
    index = np.flatnonzero(count[:k])
    return Sums(index, acc[index], wsum[index], count[index])


def _bake_views(task: _BakeTask) -> _GroupSums:
    """Bake a group of views (a task on the executor): each view is read, ray cast and
    blended in turn, so the task holds one view's images at a time; it returns the sums of
    the texels and vertices its views saw (sparse)."""
    shared = _Shared.load(task.shared) if isinstance(task.shared, str) else task.shared
    scene = _raycasting_scene(shared.vertices, shared.faces)
    vt, tt = shared.vertex_targets, shared.texel_targets
    vsum, tsum = _accumulators(vt.k), _accumulators(tt.k)
    shares = {}
    for item in task.views:
        view = item.load()
        dm = depth_map(scene, view, task.options)
        shares[view.name] = model_share(dm, view)
        accumulate_view(vt, view, dm, task.options, *vsum)
        accumulate_view(tt, view, dm, task.options, *tsum)
        del view, dm
    return _GroupSums(_sparse(*tsum, tt.k), _sparse(*vsum, vt.k), shares)


def _add(total: tuple[np.ndarray, np.ndarray, np.ndarray], sums: Sums) -> None:
    acc, wsum, count = total
    acc[sums.index] += sums.acc
    wsum[sums.index] += sums.weight
    count[sums.index] += sums.views


def bake(
    vertices: np.ndarray,
    faces: np.ndarray,
    atlas,
    views: Sequence,
    options: BakeOptions | None = None,
    *,
    normals: np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
    executor=None,
    scratch: str | os.PathLike | None = None,
    scratch_prefix: str = ".bake.partial-",
) -> BakedTexture:
    """Bake ``views`` into ``atlas`` (a :class:`slscan.texture.atlas.Atlas` of the mesh
    ``vertices``, ``faces``: same faces in the same order) and onto the vertices.

    views : :class:`TextureView` (albedo in memory) or :class:`~slscan.texture.views.ViewFile`
        (read where its task runs); split into groups of ``options.views_per_task``, each a
        task that reads, ray casts and blends its views one at a time and returns its sums
        on the texels and vertices it saw. The sums are added in the groups' order, so the
        result does not depend on where the tasks ran (the rounding of float32 sums does
        depend on the group size).
    normals : (n, 3) unit vertex normals when the caller has them (default: computed)
    executor : :class:`slscan.executor.Executor` the tasks run on (default: this process)
    scratch : folder in which the arrays the tasks share are written for other processes,
        in a temporary folder named ``scratch_prefix`` + random letters and removed at the
        end (default: the system's temporary folder; for Dask, one every worker sees at
        the same path). At 4096 texels about 35 bytes per covered texel (0.4 GB).
    """
    import shutil
    import tempfile
    import time

    from slscan.meshes import vertex_normals

    options = options or BakeOptions()
    progress = progress or (lambda label: None)
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        raise SlscanError("bake: the model has no faces")
    if not views:
        raise SlscanError("bake: no views to take colour from")
    if len(atlas.faces) != len(faces):
        raise SlscanError(f"bake: the atlas has {len(atlas.faces)} faces, the model {len(faces)}")
    if options.views_per_task < 1:
        raise SlscanError(f"bake: views_per_task must be at least 1, got {options.views_per_task}")
    size = int(atlas.size)
    check_texture_memory(size)
    seconds = {}
    t0 = time.perf_counter()
    normals = (vertex_normals(vertices, faces) if normals is None else np.asarray(normals)).astype(np.float32)
    uv_px = np.asarray(atlas.uvs, np.float64) * size - 0.5
    texel, face, bary = rasterise_uv(uv_px, atlas.faces, size)
    del uv_px
    seconds["rasterise"] = time.perf_counter() - t0
    progress("rasterised")

    t0 = time.perf_counter()
    points = np.einsum("kj,kjc->kc", bary, vertices.astype(np.float32)[faces[face]])
    tnormals = np.einsum("kj,kjc->kc", bary, normals[faces[face]])
    tnormals /= np.maximum(np.linalg.norm(tnormals, axis=1, keepdims=True), 1e-12)
    texel_targets = blend_targets(points, tnormals, options)
    del points, tnormals
    vertex_targets = blend_targets(vertices.astype(np.float32), normals, options)
    shared = _Shared(vertices.astype(np.float32), faces, vertex_targets, texel_targets)
    del vertex_targets, texel_targets
    step = options.views_per_task
    groups = [tuple(views[i:i + step]) for i in range(0, len(views), step)]
    folder = None
    if executor is not None and executor.parallel(len(groups)):
        folder = Path(tempfile.mkdtemp(prefix=scratch_prefix, dir=scratch))
        shared.save(folder)
        shared = str(folder)  # the caller no longer holds the texels' points
    seconds["targets"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    tsum, vsum = _accumulators(len(texel)), _accumulators(len(vertices))
    shares: dict = {}
    tasks = [_BakeTask(shared, group, options) for group in groups]
    try:
        results = executor.map(_bake_views, tasks) if executor is not None else map(_bake_views, tasks)
        done = 0
        for result in results:  # in the groups' order, wherever they ran
            _add(tsum, result.texels)
            _add(vsum, result.vertices)
            shares.update(result.shares)
            done += len(result.shares)
            del result
            progress(f"views {done}/{len(views)}")
    finally:
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)
    del shared, tasks
    tblend = _finish(*tsum, len(texel))
    vblend = _finish(*vsum, len(vertices))
    del tsum, vsum
    vertex_colors, vertex_seen = _fill_vertices(vertices, vblend.color)
    seconds["views"] = time.perf_counter() - t0
    progress("blended")

    t0 = time.perf_counter()
    # texels no view sees take the per-vertex colours; weakly seen ones (grazing, near an
    # edge) are pulled towards them: a prior of weight ``prior_weight``
    fill = np.einsum("kj,kjc->kc", bary, vertex_colors[faces[face]])
    del face, bary
    unseen = ~np.all(np.isfinite(tblend.color), axis=1)
    w = tblend.weight[:, None]
    seen_color = np.nan_to_num(tblend.color)
    color = ((seen_color * w + fill * options.prior_weight) / (w + options.prior_weight)).astype(np.float32)
    color[unseen] = fill[unseen]
    del fill, seen_color, w
    image = np.zeros((size * size, 3), np.float32)
    image[texel] = color
    del color
    covered = np.zeros(size * size, bool)
    covered[texel] = True
    observed = np.zeros(size * size, bool)
    observed[texel[~unseen]] = True
    view_count = np.zeros(size * size, np.uint8)
    view_count[texel] = tblend.views
    del tblend, texel, unseen
    image = image.reshape(size, size, 3)
    covered = covered.reshape(size, size)
    padded, filled = pad_charts(image, covered, options.padding)
    if covered.any():
        padded[~filled] = image[covered].mean(axis=0)
    seconds["fill_pad"] = time.perf_counter() - t0
    progress("padded")
    return BakedTexture(
        padded, covered, observed.reshape(size, size), view_count.reshape(size, size),
        vertex_colors, vertex_seen, seconds, {view.name: shares[view.name] for view in views},
    )
