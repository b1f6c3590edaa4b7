"""Global light transport of the virtual rig: subsurface scattering and inter-reflections.

Both act on the **per-primary irradiance** a view's surface receives (projector primary
``k`` at camera pixel ``x``, :func:`slscan.virtual.render._shade`), before the colour step
turns irradiance into camera channels, so every colour model sees them alike.

- **Subsurface scattering** (:func:`spread_subsurface`, effect ``subsurface``): light that
  enters a material with a mean free path ``l`` (``Material.mean_free_path``, mm) leaves it
  spread over the surface with the radial profile ``R(r) ~ exp(-r / l)``: the exponential
  far field of Jensen et al.'s dipole diffusion model (SIGGRAPH 2001, "A practical model
  for subsurface light transport"), with ``l = 1 / sigma_tr``. It is applied in camera
  image space: each pixel's light goes to the pixels within ``SUBSURFACE_EXTENT * l`` (3D
  distance between their surface points, so the kernel's width in pixels follows each
  pixel's mm footprint), of the same material only (no light crosses a material border),
  and never to a surface more than that far away in 3D (depth discontinuities). The
  weights are normalised per source pixel with the receivers' surface areas, so the
  power ``sum E * area`` is conserved exactly.
- **Inter-reflections** (:class:`IndirectPaths`, effect ``interreflection``): one bounce
  of projector light between surfaces. From receivers on a camera-pixel grid (every
  ``Optics.interreflection_stride`` px) ``Optics.interreflection_samples`` cosine-weighted
  rays find the secondary surface points they see (Open3D ``RaycastingScene``); each
  secondary point's projector position, projector visibility (shadow ray), Lambertian
  and Blinn-Phong factors towards the receiver are traced once per view. Each image then
  only samples the projector light actually shown at those projector positions
  (:func:`slscan.virtual.render.projector_light_at`), gathers it at the receivers and
  interpolates it to every pixel, so coarse patterns give structured indirect light and
  fine ones about half of white's (Nayar et al., SIGGRAPH 2006; Gupta et al., CVPR 2011).
  Each path reads the image averaged over the patch its share of the hemisphere covers
  (:func:`path_footprint`, a cone-traced lookup), not at its one point: with point reads,
  which of a few rays happen to land on lit stripes of a fine pattern is binomial noise
  that differs between a pattern and its inverse, and it moved Gray-code edges in the
  ``concave`` corner as much as the inter-reflection itself (mean error 0.051 mm at 128
  rays against 0.040 mm converged at 4096; with the patch reads, 0.040 mm at 128 rays;
  ``benchmarks/transport_cost.py`` table 2, ``benchmarks/light_transport.py``).

Ring-light images get subsurface scattering too; their inter-reflections are not modelled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

SUBSURFACE_EXTENT = 5.0  # the kernel reaches this many mean free paths (96 % of its energy)
SUBSURFACE_MAX_RADIUS = 32  # px; the kernel's reach in the image is capped here
SUBSURFACE_CACHE_BYTES = 256 * 2**20  # per-view kernel weights kept up to this size
INDIRECT_SEED = 18  # the hemisphere samples are the same on every run

LightAt = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""Projector light (k, 3) in [0, 1] of the image shown, at projector (u, v) (k, 2), averaged
over widths (k,) projector px."""


# --- subsurface scattering ------------------------------------------------------------


@dataclass(frozen=True)
class SubsurfaceKernel:
    """The spreading weights of one view, traced once.

    box : (y0, y1, x0, x1) camera pixels the kernel acts in
    offsets : (n, 2) int (dy, dx) pixel offsets of the kernel's support
    mfp : (by, bx) float32 mean free path mm of each pixel in the box (0: none)
    point : (by, bx, 3) float32 mm surface points, relative to their mean; material : (by, bx) int16
    area : (by, bx) float32 mm^2 surface area of each pixel
    norm : (by, bx) float32 ``W(y) = sum_x w(x, y) area(x)`` of each source pixel
    weights : per offset, (by, bx) float32 ``w_d(x) = w(x, x + d)``, or None (recomputed)
    """

    box: tuple[int, int, int, int]
    offsets: np.ndarray
    mfp: np.ndarray
    point: np.ndarray
    material: np.ndarray
    area: np.ndarray
    norm: np.ndarray
    weights: list[np.ndarray] | None


def _shifted(a: np.ndarray, dy: int, dx: int, fill) -> np.ndarray:
    """``a[y + dy, x + dx]`` over ``a``'s own grid, ``fill`` outside."""
    out = np.full_like(a, fill)
    dst, src = _slices(a.shape[:2], dy, dx)
    out[dst] = a[src]
    return out


def _slices(shape: tuple[int, int], dy: int, dx: int):
    """(dst, src) index pairs with ``dst`` pixel ``x`` and ``src`` pixel ``x + d``."""
    h, w = shape
    src = (slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0)))
    dst = (slice(max(-dy, 0), h + min(-dy, 0)), slice(max(-dx, 0), w + min(-dx, 0)))
    return dst, src


def _pixel_area(point: np.ndarray) -> np.ndarray:
    """Surface area (h, w) mm^2 of each pixel from the neighbouring surface points: the
    shorter one-sided difference along each axis, so a depth discontinuity next to a pixel
    does not count as its surface (NaN where a pixel has no neighbour along an axis)."""
    def step(axis):
        fwd = np.diff(point, axis=axis, append=np.nan)
        bwd = np.diff(point, axis=axis, prepend=np.nan)
        nf = np.nan_to_num(np.linalg.norm(fwd, axis=-1), nan=np.inf)
        nb = np.nan_to_num(np.linalg.norm(bwd, axis=-1), nan=np.inf)
        return np.where((nf <= nb)[..., None], fwd, bwd)

    return np.linalg.norm(np.cross(step(1), step(0)), axis=-1)


def subsurface_kernel(point: np.ndarray, material: np.ndarray, mean_free_paths: np.ndarray,
                      *, extent: float = SUBSURFACE_EXTENT) -> SubsurfaceKernel | None:
    """The subsurface weights of a view.

    point : (h, w, 3) mm surface point per camera pixel (NaN: background)
    material : (h, w) int material index (-1: background)
    mean_free_paths : (n_materials,) mm, 0 for materials without subsurface scattering
    Returns None when no pixel shows a scattering material.
    """
    mfp_of = np.asarray(mean_free_paths, np.float64)
    valid = material >= 0
    mfp = np.where(valid, mfp_of[np.maximum(material, 0)], 0.0)
    sss = mfp > 0
    if not sss.any():
        return None
    area_full = _pixel_area(point)
    good = sss & np.isfinite(area_full) & (area_full > 0)
    typical = float(np.median(area_full[good])) if good.any() else 1.0
    area_full = np.where(good, area_full, typical)  # isolated pixels: a typical area
    foot = np.sqrt(area_full[sss])
    reach = extent * float(mfp[sss].max())
    radius = int(min(SUBSURFACE_MAX_RADIUS, np.ceil(reach / max(float(np.percentile(foot, 5)), 1e-6))))
    ys, xs = np.nonzero(sss)
    h, w = material.shape
    box = (max(0, ys.min() - radius), min(h, ys.max() + radius + 1),
           max(0, xs.min() - radius), min(w, xs.max() + radius + 1))
    y0, y1, x0, x1 = box
    sub_point = point[y0:y1, x0:x1].astype(np.float64)
    sub_point = (sub_point - np.nanmean(sub_point[sss[y0:y1, x0:x1]], axis=0)).astype(np.float32)  # local, exact enough
    sub_mat = np.where(sss, material, -1)[y0:y1, x0:x1].astype(np.int16)
    sub_mfp = mfp[y0:y1, x0:x1].astype(np.float32)
    area = np.where(sub_mat >= 0, area_full[y0:y1, x0:x1], 0).astype(np.float32)
    # half the disc: w(x, x - d) is w_d(x - d), so each weight image serves d and -d
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    keep = (dy**2 + dx**2 <= radius**2) & ((dy > 0) | ((dy == 0) & (dx > 0)))
    offsets = np.stack([dy[keep], dx[keep]], axis=1)
    budget = len(offsets) * sub_mat.size * 4 <= SUBSURFACE_CACHE_BYTES
    kernel = SubsurfaceKernel(box, offsets, sub_mfp, sub_point, sub_mat, area, np.zeros_like(area), None)
    weights = []
    norm = np.where(sub_mat >= 0, area, 0).astype(np.float64)  # d = 0: w = 1
    for d in offsets:
        wd = _offset_weight(kernel, int(d[0]), int(d[1]), extent)
        dst, src = _slices(area.shape, int(d[0]), int(d[1]))
        cv2.accumulateProduct(wd[dst], area[src], norm[dst])  # y = x, receiver x + d
        cv2.accumulateProduct(wd[dst], area[dst], norm[src])  # y = x + d, receiver x
        if budget:
            weights.append(wd)
    return SubsurfaceKernel(box, offsets, sub_mfp, sub_point, sub_mat, area, norm.astype(np.float32),
                            weights if budget else None)


def _offset_weight(kernel: SubsurfaceKernel, dy: int, dx: int, extent: float = SUBSURFACE_EXTENT) -> np.ndarray:
    """``w(x, x + d) = exp(-|P(x + d) - P(x)| / l)`` between pixels of the same scattering
    material within ``extent * l`` of each other, else 0; (by, bx) float32."""
    mat = kernel.material
    out = np.zeros(mat.shape, np.float32)
    dst, src = _slices(mat.shape, dy, dx)
    here = mat[dst]
    same = (here >= 0) & (mat[src] == here)
    if not same.any():
        return out
    diff = kernel.point[src] - kernel.point[dst]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    mfp = np.where(same, kernel.mfp[dst], 1.0)
    with np.errstate(invalid="ignore"):
        ok = same & (dist <= extent * mfp)
    out[dst] = np.where(ok, np.exp(-np.where(ok, dist, 0) / mfp), 0)
    return out


def spread_subsurface(irradiance: np.ndarray, kernel: SubsurfaceKernel) -> np.ndarray:
    """Irradiance (h, w, k) after subsurface transport: pixel ``x`` receives
    ``sum_y w(x, y) E(y) area(y) / W(y)``; pixels without a scattering material keep theirs."""
    y0, y1, x0, x1 = kernel.box
    out = irradiance.astype(np.float64, copy=True)
    sub = out[y0:y1, x0:x1]
    scatter = kernel.material >= 0
    with np.errstate(invalid="ignore", divide="ignore"):
        source = np.where(scatter[..., None], sub * (kernel.area / kernel.norm)[..., None], 0.0)
    # channel planes: OpenCV's in-place multiply-accumulate on strided views is ~25x numpy's
    source = np.ascontiguousarray(np.moveaxis(np.nan_to_num(source), -1, 0), dtype=np.float32)
    gathered = source.copy()  # d = 0
    for i, d in enumerate(kernel.offsets):
        dy, dx = int(d[0]), int(d[1])
        wd = kernel.weights[i] if kernel.weights is not None else _offset_weight(kernel, dy, dx)
        dst, src = _slices(wd.shape, dy, dx)
        w_pair = wd[dst]
        for c in range(len(source)):
            cv2.accumulateProduct(source[c][src], w_pair, gathered[c][dst])  # x receives from x + d
            cv2.accumulateProduct(source[c][dst], w_pair, gathered[c][src])  # x + d receives from x
    sub[scatter] = np.moveaxis(gathered, 0, -1)[scatter]
    return out


# --- inter-reflections ----------------------------------------------------------------


@dataclass(frozen=True)
class IndirectPaths:
    """One-bounce paths of a view, traced once; each image then only gathers.

    shape : (h, w) camera image; stride : px between receivers; grid : (gh, gw) receivers
    receiver_cell : (r,) int flat index into the receiver grid of each receiver (a hit pixel)
    entry_receiver : (e,) int32 receiver of each lit secondary point
    uv : (e, 2) float64 projector (u, v) of each lit secondary point
    weight : (e, 3) float32 what the secondary point sends to its receiver per unit
        projector light: ``(albedo * cos + specular) * falloff / samples``
    footprint : (e,) float32 projector px: the width of the projector image that the
        path's share of the receiver's hemisphere sees on the secondary surface
        (:func:`path_footprint`); each image's light there is averaged over it
    """

    shape: tuple[int, int]
    stride: int
    grid: tuple[int, int]
    receiver_cell: np.ndarray
    entry_receiver: np.ndarray
    uv: np.ndarray
    weight: np.ndarray
    footprint: np.ndarray


def path_footprint(samples: int, cos_receiver: np.ndarray, distance: np.ndarray, cos_secondary: np.ndarray,
                   cos_projector: np.ndarray, projector_distance: np.ndarray, projector_focal_px: float) -> np.ndarray:
    """Width (projector px) of the patch each one-bounce path stands for, (e,) float32.

    A receiver's ``samples`` cosine-weighted rays split its hemisphere into cells of solid
    angle ``pi / (samples * cos_receiver)`` (one over the sample density). A cell meets the
    secondary surface at ``distance`` mm in a patch of area ``distance**2 * solid_angle /
    cos_secondary``, which the projector sees foreshortened by ``cos_projector`` at
    ``projector_distance`` mm, ``projector_distance / projector_focal_px`` mm per projector
    px; the width is the side of that area's square. Averaging the projector image over
    it (a cone-traced lookup, as ray differentials filter textures) instead of reading it
    at one point gives each cell the light its whole patch receives: patterns finer than a
    patch, which light half of it, then no longer add the binomial noise of which points
    a few rays happen to hit (:mod:`slscan.virtual.transport` notes the measured effect).
    Grazing angles are bounded (cosines at least 0.05) so a patch stays finite."""
    solid = np.pi / (samples * np.maximum(cos_receiver, 0.05))
    area = distance**2 * solid / np.maximum(cos_secondary, 0.05) * np.clip(cos_projector, 0.0, 1.0)
    return (np.sqrt(area) * projector_focal_px / projector_distance).astype(np.float32)


def _hemisphere(n_receivers: int, samples: int, rng: np.random.Generator) -> np.ndarray:
    """Cosine-weighted directions (r, s, 3) about +z, stratified over a sqrt(s) x sqrt(s) grid."""
    k = int(np.sqrt(samples))
    strata = k * k
    a, b = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    base = np.stack([a.ravel(), b.ravel()], 1).astype(np.float64)
    u = np.empty((n_receivers, samples, 2))
    u[:, :strata] = (base[None] + rng.random((n_receivers, strata, 2))) / k
    u[:, strata:] = rng.random((n_receivers, samples - strata, 2))
    r, phi = np.sqrt(u[..., 0]), 2 * np.pi * u[..., 1]
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - u[..., 0]))], -1)


def trace_indirect(scene, rig, rig_from_object: np.ndarray, vertices: np.ndarray, rscene,
                   point: np.ndarray, normal: np.ndarray, hit: np.ndarray, *,
                   samples: int, stride: int) -> IndirectPaths:
    """Trace the one-bounce paths of a view (see :class:`IndirectPaths`).

    vertices : (n, 3) mm the scene's vertices in the rig frame; rscene : their Open3D scene
    point, normal, hit : the view's (h, w, 3), (h, w, 3) and (h, w) camera-pixel surface
    """
    import open3d as o3d

    from slscan.virtual.render import SHADOW_EPS, _blinn_phong, _occluded
    from slscan.virtual.scenes import shading_normals

    h, w = hit.shape
    off = stride // 2
    gy, gx = np.arange(off, h, stride), np.arange(off, w, stride)
    grid = (len(gy), len(gx))
    cells = np.flatnonzero(hit[np.ix_(gy, gx)])
    cy, cx = gy[cells // grid[1]], gx[cells % grid[1]]
    p_recv = point[cy, cx].astype(np.float64)
    n_recv = normal[cy, cx].astype(np.float64)
    rng = np.random.default_rng(INDIRECT_SEED)
    local = _hemisphere(len(cells), samples, rng)
    # tangent frame per receiver
    helper = np.where(np.abs(n_recv[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(n_recv, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n_recv, t1)
    dirs = local[..., :1] * t1[:, None] + local[..., 1:2] * t2[:, None] + local[..., 2:] * n_recv[:, None]
    dirs = dirs.reshape(-1, 3)
    cos_receiver = local[..., 2].reshape(-1)
    receiver = np.repeat(np.arange(len(cells), dtype=np.int32), samples)
    origins = p_recv[receiver] + 2 * SHADOW_EPS * n_recv[receiver]
    cast = rscene.cast_rays(o3d.core.Tensor(np.concatenate([origins, dirs], 1).astype(np.float32)))
    t_hit = cast["t_hit"].numpy().astype(np.float64)
    prim = cast["primitive_ids"].numpy().astype(np.int64)
    got = np.flatnonzero(np.isfinite(t_hit) & (prim != rscene.INVALID_ID))
    receiver, prim, dirs, cos_receiver, t_hit = receiver[got], prim[got], dirs[got], cos_receiver[got], t_hit[got]
    bary = cast["primitive_uvs"].numpy()[got].astype(np.float64)
    q = origins[got] + t_hit[:, None] * dirs

    tri = scene.triangles[prim]
    v0, v1, v2 = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    geo_n = np.cross(v1 - v0, v2 - v0)
    geo_n /= np.linalg.norm(geo_n, axis=1, keepdims=True)
    along = np.einsum("ij,ij->i", geo_n, dirs)
    cos_secondary = np.abs(along)
    facing = along < 0
    geo_n[~facing] *= -1  # the side the receiver sees
    wts = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], axis=1)
    n = shading_normals(scene, rig_from_object[:3, :3], tri, wts, geo_n, facing)

    proj = rig.projector
    uv = proj.project(q)
    to_proj = proj.center - q
    d_proj = np.linalg.norm(to_proj, axis=1)
    l_proj = to_proj / d_proj[:, None]
    pw, ph = proj.lens.width, proj.lens.height
    in_frustum = (uv[:, 0] >= -0.5) & (uv[:, 0] <= pw - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= ph - 0.5)
    cand = np.flatnonzero(in_frustum & (np.einsum("ij,ij->i", geo_n, l_proj) > 0))
    lit = np.zeros(len(q), bool)
    lit[cand] = ~_occluded(rscene, q[cand] + SHADOW_EPS * geo_n[cand], np.broadcast_to(proj.center, (len(cand), 3)))
    keep = np.flatnonzero(lit)
    receiver, prim, q, n, l_proj, d_proj, uv, dirs, cos_receiver, t_hit, cos_secondary = (
        a[keep] for a in (receiver, prim, q, n, l_proj, d_proj, uv, dirs, cos_receiver, t_hit, cos_secondary))
    bary = bary[keep]

    d0 = float(np.linalg.norm(proj.center - [0, 0, rig.working_distance]))
    falloff = (d0 / d_proj) ** 2
    cos_p = np.clip(np.einsum("ij,ij->i", n, l_proj), 0, None)
    p_obj = (q - rig_from_object[:3, 3]) @ rig_from_object[:3, :3]
    albedo = scene.albedo.at(p_obj, prim, bary).astype(np.float64)
    weight = albedo * cos_p[:, None]
    mat = scene.material_of(prim)
    for k, m in enumerate(scene.materials):
        sel = np.flatnonzero(mat == k)
        if m.specular > 0 and len(sel):
            lobe = m.specular * _blinn_phong(n[sel], l_proj[sel], -dirs[sel], m.shininess)
            weight[sel] += lobe[:, None] * np.asarray(m.specular_colour)[None]
    weight *= (falloff / samples)[:, None]
    footprint = path_footprint(samples, cos_receiver, t_hit, cos_secondary, cos_p, d_proj, proj.lens.fx)
    nonzero = weight.max(axis=1) > 0
    return IndirectPaths(
        shape=(h, w), stride=stride, grid=grid, receiver_cell=cells,
        entry_receiver=receiver[nonzero].astype(np.int32), uv=uv[nonzero],
        weight=weight[nonzero].astype(np.float32), footprint=footprint[nonzero],
    )


def gather_indirect(paths: IndirectPaths, light_at: LightAt) -> np.ndarray:
    """Indirect irradiance (r, 3) per primary at each receiver, for the projector light
    ``light_at`` (relative units: a white Lambertian surface facing the projector at the
    working distance under full white receives 1)."""
    r = len(paths.receiver_cell)
    if len(paths.uv) == 0:
        return np.zeros((r, 3))
    contrib = light_at(paths.uv, paths.footprint) * paths.weight
    return np.stack([np.bincount(paths.entry_receiver, weights=contrib[:, c], minlength=r) for c in range(3)], 1)


def interpolate_receivers(paths: IndirectPaths, values: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Receiver values (r, k) interpolated to every hit pixel: (n_hit, k) float64.

    Bilinear between the receivers around each pixel, weighted by which receivers exist
    (normalised convolution), so the background does not darken the object's edges."""
    import cv2

    gh, gw = paths.grid
    k = values.shape[1]
    grid = np.zeros((gh * gw, k), np.float32)
    mask = np.zeros(gh * gw, np.float32)
    grid[paths.receiver_cell] = values
    mask[paths.receiver_cell] = 1
    grid, mask = grid.reshape(gh, gw, k), mask.reshape(gh, gw)
    # cells without a receiver take their receiving neighbours' mean (for pixels between)
    blur_v = cv2.GaussianBlur(grid * mask[..., None], (0, 0), 1.0, borderType=cv2.BORDER_CONSTANT).reshape(gh, gw, k)
    blur_m = cv2.GaussianBlur(mask, (0, 0), 1.0, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        filled = np.where(mask[..., None] > 0, grid, blur_v / blur_m[..., None])
    filled = np.nan_to_num(filled)
    ys, xs = np.nonzero(hit)
    off = paths.stride // 2
    gx = np.clip((xs - off) / paths.stride, 0, gw - 1)
    gy = np.clip((ys - off) / paths.stride, 0, gh - 1)
    x0, y0 = np.minimum(gx.astype(int), max(gw - 2, 0)), np.minimum(gy.astype(int), max(gh - 2, 0))
    x1, y1 = np.minimum(x0 + 1, gw - 1), np.minimum(y0 + 1, gh - 1)
    fx, fy = (gx - x0)[:, None], (gy - y0)[:, None]
    top = filled[y0, x0] * (1 - fx) + filled[y0, x1] * fx
    bottom = filled[y1, x0] * (1 - fx) + filled[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


# --- both, per view -------------------------------------------------------------------


@dataclass(frozen=True)
class Transport:
    """What a view needs for global light transport, traced once (None: effect off)."""

    subsurface: SubsurfaceKernel | None = None
    indirect: IndirectPaths | None = None
    subsurface_on: bool = False
    interreflection_on: bool = False
    samples: int = 0

    def matches(self, optics) -> bool:
        """True when this was traced for ``optics``' transport settings."""
        return (self.subsurface_on == optics.subsurface and self.interreflection_on == optics.interreflection
                and (self.indirect is None or (self.indirect.stride == optics.interreflection_stride
                                               and self.samples == optics.interreflection_samples)))


def active(optics) -> bool:
    """True when ``optics`` switches on any global light transport."""
    return bool(getattr(optics, "subsurface", False) or getattr(optics, "interreflection", False))


def prepare(scene, rig, rig_from_object: np.ndarray, vertices: np.ndarray, rscene, point: np.ndarray,
            normal: np.ndarray, hit: np.ndarray, material: np.ndarray, optics) -> Transport | None:
    """The per-view :class:`Transport` of ``optics`` (None when it switches nothing on)."""
    if not active(optics):
        return None
    kernel = None
    if optics.subsurface:
        kernel = subsurface_kernel(point, material, np.array([m.mean_free_path for m in scene.materials]))
    paths = None
    if optics.interreflection:
        paths = trace_indirect(scene, rig, rig_from_object, vertices, rscene, point, normal, hit,
                               samples=optics.interreflection_samples, stride=optics.interreflection_stride)
    return Transport(kernel, paths, bool(optics.subsurface), bool(optics.interreflection),
                     optics.interreflection_samples if optics.interreflection else 0)


def diffuse_irradiance(transport: Transport, hit: np.ndarray, light: np.ndarray, cos_falloff: np.ndarray,
                       light_at: LightAt | None) -> np.ndarray:
    """Per-primary irradiance (n_hit, 3) at the hit pixels: the direct ``light`` (n_hit, 3)
    times its ``cos_falloff`` (n_hit,), plus the inter-reflected light of ``light_at``
    (None: projector off), spread under the surface."""
    irradiance = light * cos_falloff[:, None]
    if transport.indirect is not None and light_at is not None:
        at_receivers = gather_indirect(transport.indirect, light_at)
        irradiance = irradiance + interpolate_receivers(transport.indirect, at_receivers, hit)
    if transport.subsurface is not None:
        irradiance = spread_hit(transport.subsurface, hit, irradiance)
    return irradiance


def spread_hit(kernel: SubsurfaceKernel, hit: np.ndarray, values: np.ndarray) -> np.ndarray:
    """:func:`spread_subsurface` of values (n_hit, k) given at the hit pixels."""
    image = np.zeros(hit.shape + values.shape[1:])
    image[hit] = values
    return spread_subsurface(image, kernel)[hit]
