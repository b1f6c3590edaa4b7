"""Ray-traced image formation for the virtual rig.

Geometry is traced once per view (:func:`trace_view`, Open3D ``RaycastingScene``): the
surface seen at each camera pixel centre, its shading normal and albedo, where it falls
in the projector (continuous column and row), whether the projector and each light reach
it (shadow rays), and the pixel's footprint in projector pixels. Each projected image is
then only shaded (:func:`shade_pattern`, :func:`shade_light`): the projector image is
box-filtered over the camera pixel's footprint after the projector's own blur, so thin
lines render with the right sub-pixel position and width. Optical blur, noise and
quantisation are the sensor's job (:mod:`slscan.virtual.sensor`).

Radiometry (linear, relative units; ``E`` is 1 on a surface facing the projector at the
working distance, with cos θ and inverse-square falloff elsewhere). Under the default
``Optics.colour_model="physical"``, camera channel ``c`` receives
``albedo_c * sum_k M[c, k] * p_k * E`` from projector primary ``k`` (``M``: colour
crosstalk, the camera bands' response to each primary): the paint acts after the
crosstalk, so the leak of primary ``k`` into band ``c`` is reflected with the paint's
reflectance in band ``c``, as a real surface does. ``colour_model="legacy"`` (the virtual
rig's earlier model, ``sum_k M[c, k] * albedo_k * p_k * E``) filters the primaries by the
paint first, which the decoder's one global crosstalk matrix then undoes exactly: paint
never shifts a decoded line there, as it does on a real rig.

Everything else is the same in both models and already physical. The specular lobe is
white (a dielectric reflects the source's spectrum unfiltered by the paint): projector
light adds ``s * sum_k M[c, k] * p_k``. Ambient light adds ``albedo_c * ambient_c``. The
ring lights are broadband white sources, and their ``intensity`` is what each camera
band reads off a white surface facing them at the reference distance (the light
calibration measures exactly that): camera channel ``c`` sees ``albedo_c * I_c`` diffuse
plus ``s * I_c`` specular. A white light seen through the camera's bands has no
per-primary crosstalk to undo, so the ring-light images, and the albedo recovered from
them, do not depend on the colour model; the projector's full white reads
``albedo_c * sum_k M[c, k]`` (1.12, 1.14, 1.16 times the albedo with the default ``M``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from slscan.errors import SlscanError
from slscan.patterns import PatternImage
from slscan.patterns import profile as pattern_profile
from slscan.rig import PinholeModel, Rig, transform_points
from slscan.virtual.scenes import Scene

SHADOW_EPS = 0.05  # mm offset of shadow-ray origins along the normal
MAX_FOOTPRINT = 64.0  # projector px; grazing surfaces are clamped


@dataclass(frozen=True)
class Optics:
    """Projector and scene light that every image of a view shares.

    projector_blur : Gaussian sigma of the projector lens's point spread at its focus,
        projector px (the projector pixel itself, a box, is rendered apart). The default
        0.4 is an XGA (1024 × 768) DLP projector's lens: a 0.7" DMD of 13.7 µm pitch, so
        f = 1857 px is a 25.4 mm lens, at f/2.4 as data projectors are. In quadrature:
        diffraction (Airy, 550 nm: σ = 0.42 λ N = 0.55 µm = 0.04 px); lens aberrations
        at focus, MTF 0.5 at the panel's Nyquist frequency (36.5 lp/mm) as typical of
        such lenses (a Gaussian with MTF(½ cycle/px) = exp(-π²σ²/2) = 0.5: σ = 0.37 px);
        focus set by eye within Δ = 20 mm of the working distance s = 1300 mm (blur
        circle f² / (N (s − f)) · Δ / (s + Δ) = 3.2 µm = 0.23 px across, σ = diameter / 4
        = 0.06 px): √(0.04² + 0.37² + 0.06²) = 0.38, rounded to 0.4 px. Defocus away from
        the focus distance is an effect of its own. The DMD's fill factor
        (≈ 0.92) and a 3-LCD projector's panel misconvergence are not modelled.
    projector_black : light the projector leaks when showing black, fraction of white
    crosstalk : (3, 3) camera channel (rows) response to projector primaries (columns)
    ambient : (3,) ambient irradiance, fraction of the projector's white
    colour_model : {"physical", "legacy"}: "physical" (default): camera channel c sees
        ``albedo_c * sum_k M[c, k] * p_k`` (each primary's leak into camera band c is
        reflected with the paint's reflectance in band c, as a real surface does);
        "legacy": ``sum_k M[c, k] * albedo_k * p_k`` (the paint filters the projector's
        primaries before the crosstalk, so the decoder's one global crosstalk matrix
        undoes paint exactly). Ring-light and specular terms are the same in both (see
        the module's docstring).
    """

    projector_blur: float = 0.4
    projector_black: float = 0.01
    crosstalk: tuple[tuple[float, float, float], ...] = (
        (1.0, 0.10, 0.02),
        (0.06, 1.0, 0.08),
        (0.02, 0.14, 1.0),
    )
    ambient: tuple[float, float, float] = (0.02, 0.02, 0.02)
    colour_model: str = "physical"

    def __post_init__(self) -> None:
        if self.colour_model not in ("legacy", "physical"):
            raise SlscanError(f"optics.colour_model: expected 'physical' or 'legacy', got {self.colour_model!r}")
        if not self.projector_blur >= 0:
            raise SlscanError(f"optics.projector_blur: expected a blur of 0 px or more, got {self.projector_blur!r}")

    def to_dict(self) -> dict:
        return {
            "projector_blur_px": self.projector_blur, "projector_black": self.projector_black,
            "crosstalk": [list(r) for r in self.crosstalk], "ambient": list(self.ambient),
            "colour_model": self.colour_model,
        }


@dataclass(frozen=True)
class ViewGeometry:
    """What the camera sees in one view, traced once. Arrays are over camera pixels (h, w).

    hit : bool, a surface is seen
    point : (h, w, 3) float64 mm rig frame; normal : (h, w, 3) float32 shading normal
    albedo : (h, w, 3) float32 linear
    proj_uv : (h, w, 2) float64 continuous projector pixel of ``point``
    proj_footprint : (h, w, 2) float32 footprint width of the camera pixel along the
        projector's columns and rows, projector px
    proj_lit : bool, the projector reaches ``point`` (in frustum, facing, unoccluded)
    proj_diffuse, proj_specular : (h, w) float32 geometric factors for projector light
    light_diffuse, light_specular : (n_lights, h, w) float32, the same for ring lights
    """

    hit: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    proj_uv: np.ndarray
    proj_footprint: np.ndarray
    proj_lit: np.ndarray
    proj_diffuse: np.ndarray
    proj_specular: np.ndarray
    light_diffuse: np.ndarray
    light_specular: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.hit.shape


@functools.lru_cache(maxsize=4)
def camera_rays(camera: PinholeModel) -> np.ndarray:
    """Undistorted ray directions (h + 1, w + 1, 3), z = 1, through pixel centres 0..w, 0..h.

    The extra row and column give each pixel its right and lower neighbour's ray.
    """
    xs = np.arange(camera.width + 1, dtype=np.float64)
    ys = np.arange(camera.height + 1, dtype=np.float64)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1)
    rays = camera.rays_local(grid)
    rays.flags.writeable = False
    return rays


def _raycasting_scene(vertices: np.ndarray, triangles: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32))
    )
    return scene


def _occluded(scene, origins: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """True where the segment from ``origins`` to ``targets`` (k, 3) hits the scene."""
    import open3d as o3d

    d = targets - origins
    dist = np.linalg.norm(d, axis=1)
    rays = np.concatenate([origins, d / dist[:, None]], axis=1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return t_hit < dist - 2 * SHADOW_EPS


def _blinn_phong(n, to_light, to_eye, shininess):
    h = to_light + to_eye
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    return np.clip(np.einsum("ij,ij->i", n, h), 0, None) ** shininess


def trace_view(scene: Scene, rig: Rig, rig_from_object: np.ndarray) -> ViewGeometry:
    """Trace the camera, projector and light rays of one view of ``scene`` at ``rig_from_object``."""
    cam = rig.camera
    h, w = cam.height, cam.width
    vertices = transform_points(rig_from_object, scene.vertices)
    rscene = _raycasting_scene(vertices, scene.triangles)
    rays_all = camera_rays(cam)
    rays = rays_all[:h, :w].reshape(-1, 3)
    unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)

    import open3d as o3d

    cast = rscene.cast_rays(
        o3d.core.Tensor(np.concatenate([np.zeros_like(unit), unit], axis=1).astype(np.float32))
    )
    prim = cast["primitive_ids"].numpy().astype(np.int64)
    hit = prim != rscene.INVALID_ID
    idx = np.flatnonzero(hit)
    prim = prim[idx]
    bary = cast["primitive_uvs"].numpy()[idx].astype(np.float64)

    tri = scene.triangles[prim]
    v0, v1, v2 = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    geo_n = np.cross(v1 - v0, v2 - v0)
    geo_n /= np.linalg.norm(geo_n, axis=1, keepdims=True)
    # exact float64 intersection with the hit triangle's plane
    r = rays[idx]
    t = np.einsum("ij,ij->i", geo_n, v0) / np.einsum("ij,ij->i", geo_n, r)
    point = r * t[:, None]
    facing_cam = np.einsum("ij,ij->i", geo_n, r) < 0
    geo_n[~facing_cam] *= -1  # seen from behind (open meshes): shade the side we see

    wts = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], axis=1)
    if scene.normals is not None:
        normals_rig = scene.normals @ rig_from_object[:3, :3].T
        n = np.einsum("kc,kcj->kj", wts, normals_rig[tri])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n[~facing_cam] *= -1
        # keep interpolated normals on the visible side of the face
        back = np.einsum("ij,ij->i", n, geo_n) <= 0.05
        n[back] = geo_n[back]
    else:
        n = geo_n
    p_obj = (point - rig_from_object[:3, 3]) @ rig_from_object[:3, :3]
    albedo = scene.albedo.at(p_obj, prim, bary)

    # projector: coordinates, footprint, visibility
    proj = rig.projector
    uv = proj.project(point)
    uv_neighbours = []
    for neigh in (rays_all[:h, 1 : w + 1].reshape(-1, 3)[idx], rays_all[1 : h + 1, :w].reshape(-1, 3)[idx]):
        denom = np.einsum("ij,ij->i", geo_n, neigh)
        with np.errstate(divide="ignore", invalid="ignore"):
            tn = np.einsum("ij,ij->i", geo_n, point) / denom
        uv_neighbours.append(proj.project(neigh * tn[:, None]) - uv)
    dx, dy = uv_neighbours
    footprint = np.sqrt(dx**2 + dy**2)
    footprint = np.where(np.isfinite(footprint), np.minimum(footprint, MAX_FOOTPRINT), MAX_FOOTPRINT)

    origin_off = point + SHADOW_EPS * geo_n
    to_proj = proj.center - point
    d_proj = np.linalg.norm(to_proj, axis=1)
    l_proj = to_proj / d_proj[:, None]
    to_eye = -point / np.linalg.norm(point, axis=1, keepdims=True)
    pw, ph = proj.lens.width, proj.lens.height
    in_frustum = (uv[:, 0] >= -0.5) & (uv[:, 0] <= pw - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= ph - 0.5)
    facing_proj = np.einsum("ij,ij->i", geo_n, l_proj) > 0
    cand = np.flatnonzero(in_frustum & facing_proj)
    lit = np.zeros(len(idx), bool)
    lit[cand] = ~_occluded(rscene, origin_off[cand], np.broadcast_to(proj.center, (len(cand), 3)))
    d0 = float(np.linalg.norm(proj.center - [0, 0, rig.working_distance]))
    falloff = (d0 / d_proj) ** 2
    cos_p = np.clip(np.einsum("ij,ij->i", n, l_proj), 0, None)
    proj_diffuse = np.where(lit, cos_p * falloff, 0.0)
    proj_spec = np.where(lit, scene.specular * _blinn_phong(n, l_proj, to_eye, scene.shininess) * falloff, 0.0)

    n_lights = len(rig.lights)
    light_diffuse = np.zeros((n_lights, len(idx)))
    light_spec = np.zeros((n_lights, len(idx)))
    for i, light in enumerate(rig.lights):
        lp = np.asarray(light.position, float)
        to_l = lp - point
        d_l = np.linalg.norm(to_l, axis=1)
        l_dir = to_l / d_l[:, None]
        cand = np.flatnonzero(np.einsum("ij,ij->i", geo_n, l_dir) > 0)
        vis = np.zeros(len(idx), bool)
        vis[cand] = ~_occluded(rscene, origin_off[cand], np.broadcast_to(lp, (len(cand), 3)))
        fall = (rig.working_distance / d_l) ** 2
        light_diffuse[i] = np.where(vis, np.clip(np.einsum("ij,ij->i", n, l_dir), 0, None) * fall, 0)
        light_spec[i] = np.where(vis, scene.specular * _blinn_phong(n, l_dir, to_eye, scene.shininess) * fall, 0)

    def full(values, fill, dtype):
        out = np.full((h * w,) + values.shape[1:], fill, dtype=dtype)
        out[idx] = values
        return out.reshape((h, w) + values.shape[1:])

    def full_stack(values):
        out = np.zeros((values.shape[0], h * w), np.float32)
        out[:, idx] = values
        return out.reshape(values.shape[0], h, w)

    return ViewGeometry(
        hit=hit.reshape(h, w),
        point=full(point, np.nan, np.float64),
        normal=full(n.astype(np.float32), np.nan, np.float32),
        albedo=full(albedo, np.nan, np.float32),
        proj_uv=full(uv, np.nan, np.float64),
        proj_footprint=full(footprint.astype(np.float32), 0, np.float32),
        proj_lit=full(lit, False, bool),
        proj_diffuse=full(proj_diffuse.astype(np.float32), 0, np.float32),
        proj_specular=full(proj_spec.astype(np.float32), 0, np.float32),
        light_diffuse=full_stack(light_diffuse),
        light_specular=full_stack(light_spec),
    )


@dataclass(frozen=True)
class _ProfileFilter:
    """Box filtering of a 1-D projector profile after the projector's Gaussian blur."""

    origin: float  # coordinate of the first cumulative sample
    step: float
    cumulative: np.ndarray  # (k, 3) running integral of the blurred profile

    @classmethod
    def build(cls, values: np.ndarray, blur: float, oversample: int = 16) -> _ProfileFilter:
        from scipy.ndimage import gaussian_filter1d

        pad = int(np.ceil(4 * blur)) + 2
        padded = np.concatenate([np.zeros((pad, 3)), values.astype(np.float64), np.zeros((pad, 3))])
        fine = np.repeat(padded, oversample, axis=0)
        if blur > 0:
            fine = gaussian_filter1d(fine, blur * oversample, axis=0, mode="constant")
        step = 1.0 / oversample
        cumulative = np.concatenate([np.zeros((1, 3)), np.cumsum(fine, axis=0) * step])
        return cls(origin=-pad - 0.5, step=step, cumulative=cumulative)

    def sample(self, coord: np.ndarray, width: np.ndarray) -> np.ndarray:
        """Mean of the blurred profile over ``[coord - width/2, coord + width/2]``, (k, 3)."""
        width = np.maximum(width, self.step)
        x = (coord - self.origin) / self.step
        half = 0.5 * width / self.step
        grid = np.arange(len(self.cumulative))
        out = np.empty((len(coord), 3))
        for c in range(3):
            hi = np.interp(x + half, grid, self.cumulative[:, c])
            lo = np.interp(x - half, grid, self.cumulative[:, c])
            out[:, c] = (hi - lo) / width
        return out


@functools.lru_cache(maxsize=64)
def _profile_filter(blur: float, values_bytes: bytes, n: int) -> _ProfileFilter:
    values = np.frombuffer(values_bytes, dtype=np.uint8).reshape(n, 3) / 255.0
    return _ProfileFilter.build(values, blur)


def image_profile(image: np.ndarray) -> tuple[str, np.ndarray]:
    """(axis, values) when projector ``image`` (h, w, 3) uint8 varies along one axis only:
    axis {"none", "columns", "rows"} and its (n, 3) values; ("2d", image) otherwise."""
    if (image == image[:1]).all():
        values = image[0]
        return ("none", values[:1]) if (values == values[:1]).all() else ("columns", values)
    if (image == image[:, :1]).all():
        return "rows", image[:, 0]
    return "2d", image


def projector_light(geom: ViewGeometry, desc: PatternImage | None, optics: Optics) -> np.ndarray:
    """RGB projector emission (k, 3) in [0, 1] reaching each hit pixel, footprint-filtered.

    ``desc`` None means the projector is switched off.
    """
    if desc is None:
        return projector_light_image(geom, None, optics)
    values = pattern_profile(desc)
    return _light_from_profile(geom, desc.axis, values, optics)


def projector_light_image(geom: ViewGeometry, image: np.ndarray | None, optics: Optics) -> np.ndarray:
    """:func:`projector_light` for any projector image (h, w, 3) uint8 (None: switched off).

    Images that vary along one axis (every pattern slscan projects) take the same exact
    footprint filter as :func:`projector_light`, so they render identically; others are
    blurred and sampled bilinearly at each pixel's projector position."""
    hit = geom.hit
    if image is None:
        return np.zeros((int(hit.sum()), 3))
    axis, values = image_profile(image)
    if axis != "2d":
        return _light_from_profile(geom, axis, values, optics)
    import cv2

    plane = image.astype(np.float32) / 255.0
    footprint = float(np.median(geom.proj_footprint[hit])) if hit.any() else 1.0
    sigma = float(np.hypot(optics.projector_blur, footprint / np.sqrt(12.0)))
    if sigma > 0:
        plane = cv2.GaussianBlur(plane, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    uv = geom.proj_uv[hit].astype(np.float32)
    sampled = cv2.remap(plane, uv[:, 0:1], uv[:, 1:2], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    light = sampled.reshape(-1, 3).astype(np.float64)
    black = optics.projector_black
    return black + (1 - black) * light


def _light_from_profile(geom: ViewGeometry, axis: str, values: np.ndarray, optics: Optics) -> np.ndarray:
    hit = geom.hit
    if axis == "none":
        light = np.broadcast_to(values[0] / 255.0, (int(hit.sum()), 3)).astype(np.float64)
    else:
        a = 0 if axis == "columns" else 1
        values = np.ascontiguousarray(values, dtype=np.uint8)
        filt = _profile_filter(optics.projector_blur, values.tobytes(), len(values))
        light = filt.sample(geom.proj_uv[..., a][hit], geom.proj_footprint[..., a][hit].astype(np.float64))
    black = optics.projector_black
    return black + (1 - black) * light


def shade_pattern(geom: ViewGeometry, desc: PatternImage | None, optics: Optics) -> np.ndarray:
    """Linear radiance image (h, w, 3) float32 under projected pattern ``desc`` (None: off)."""
    return _shade(geom, projector_light(geom, desc, optics), optics)


def shade_image(geom: ViewGeometry, image: np.ndarray | None, optics: Optics) -> np.ndarray:
    """Linear radiance image (h, w, 3) float32 under projector image (h, w, 3) uint8
    (None: off); a rendered pattern gives exactly :func:`shade_pattern`'s result."""
    return _shade(geom, projector_light_image(geom, image, optics), optics)


def _shade(geom: ViewGeometry, light: np.ndarray, optics: Optics) -> np.ndarray:
    hit = geom.hit
    m = np.asarray(optics.crosstalk, dtype=np.float64)
    albedo = geom.albedo[hit].astype(np.float64)
    if optics.colour_model == "physical":
        diffuse = albedo * (light @ m.T) * geom.proj_diffuse[hit][:, None]
    else:
        diffuse = (albedo * light) @ m.T * geom.proj_diffuse[hit][:, None]
    specular = light @ m.T * geom.proj_specular[hit][:, None]
    ambient = albedo * np.asarray(optics.ambient)
    out = np.zeros(hit.shape + (3,), np.float32)
    out[hit] = diffuse + specular + ambient
    return out


def shade_light(geom: ViewGeometry, light_index: int, rig: Rig, optics: Optics) -> np.ndarray:
    """Linear radiance image (h, w, 3) float32 under ring light ``light_index``, projector off."""
    out = shade_pattern(geom, None, optics)
    add_light(out, geom, light_index, rig)
    return out


def add_light(radiance: np.ndarray, geom: ViewGeometry, light_index: int, rig: Rig) -> None:
    """Add ring light ``light_index``'s diffuse and specular light to ``radiance`` (h, w, 3)."""
    hit = geom.hit
    intensity = np.asarray(rig.lights[light_index].intensity, dtype=np.float64)
    albedo = geom.albedo[hit].astype(np.float64)
    diffuse = albedo * intensity * geom.light_diffuse[light_index][hit][:, None]
    specular = intensity * geom.light_specular[light_index][hit][:, None]
    radiance[hit] += (diffuse + specular).astype(np.float32)
