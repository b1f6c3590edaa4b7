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
white (a dielectric reflects the source's spectrum unfiltered by the paint; a metal's
material tints it): projector light adds ``s * sum_k M[c, k] * p_k``. Ambient light adds ``albedo_c * ambient_c``. The
ring lights are broadband white sources, and their ``intensity`` is what each camera
band reads off a white surface facing them at the reference distance (the light
calibration measures exactly that): camera channel ``c`` sees ``albedo_c * I_c`` diffuse
plus ``s * I_c`` specular. A white light seen through the camera's bands has no
per-primary crosstalk to undo, so the ring-light images, and the albedo recovered from
them, do not depend on the colour model; the projector's full white reads
``albedo_c * sum_k M[c, k]`` (1.12, 1.14, 1.16 times the albedo with the default ``M``).

Global light transport (subsurface scattering, inter-reflections:
:mod:`slscan.virtual.transport`) acts on the per-primary irradiance ``p_k * E`` before the
colour step when switched on.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slscan.errors import SlscanError
from slscan.patterns import PatternImage
from slscan.patterns import profile as pattern_profile
from slscan.rig import PinholeModel, Rig, transform_points
from slscan.virtual import transport
from slscan.virtual.effects import Effect, register
from slscan.virtual.scenes import Scene, shading_normals

SHADOW_EPS = 0.05  # mm offset of shadow-ray origins along the normal
MAX_FOOTPRINT = 64.0  # projector px; grazing surfaces are clamped
# 0.7" XGA DMD (13.68 um pitch) behind the default rig's 1857 px projector focal length
PROJECTOR_FOCAL_MM = 25.4
COC_PER_SIGMA = 2.4  # a circle of confusion of diameter c blurs like a Gaussian of sigma c / 2.4
DOF_FIRST_LEVEL = 0.1  # projector px: finest defocus blur level above none
DOF_LEVEL_RATIO = 1.25  # neighbouring defocus blur levels differ by this factor
REMAP_ROW = 4096  # points per row when sampling a 2-D projector image with cv2.remap
IN_FOCUS = 1e-6  # projector px: a defocus below this is none (points at the focus distance)


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
    projector_fnumber : f-number N of the projector lens; 0: a pinhole (infinite depth of
        field, no defocus). Above 0 the projector is sharp only at ``projector_focus_mm``
        (effect ``dof``: f/2)
    projector_focus_mm : focus distance, mm along the projector axis (effect ``dof``: the
        rig's working distance)
    projector_focal_mm : the projector lens's focal length, mm (default 25.4: the default
        rig's 1857 px focal length on a 0.7" XGA DMD of 13.68 um pitch); its aperture
        diameter is ``projector_focal_mm / projector_fnumber``
    projector_gamma : the projector's tone curve: pattern value v emits ``(v / 255) **
        gamma``; 1: linear (a calibrated projector), effect ``tone``: 2.2 (uncalibrated)
    subsurface : spread the light entering materials with a mean free path under their
        surface (effect ``subsurface``, :mod:`slscan.virtual.transport`)
    interreflection : add one diffuse (and specular) bounce of projector light between
        surfaces (effect ``interreflection``, :mod:`slscan.virtual.transport`)
    interreflection_samples : hemisphere rays per receiver (stratified, cosine-weighted).
        The indirect term's noise, as the std over receivers of its error against a
        4096-sample reference relative to its mean (``concave`` scene under white, scale 0.5,
        ``benchmarks/transport_cost.py``): 16 samples 21.7 %, 64: 8.2 %, 128: 5.6 %, 256:
        3.0 %, 1024: 1.1 %; where the indirect light is a quarter of the direct, 128 samples
        leave about 1.4 % of the image in smooth blotches a receiver step wide. Under fine
        patterns each ray reads the pattern over its patch (:func:`slscan.virtual.transport.
        path_footprint`), which makes 128 rays as good as about 400 point reads there (finest Gray bit, ``benchmarks/transport_cost.py``)
    interreflection_stride : camera px between receivers (the indirect light is smooth, so
        it is gathered on this grid and interpolated)
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
    projector_fnumber: float = 0.0
    projector_focus_mm: float = 0.0
    projector_focal_mm: float = PROJECTOR_FOCAL_MM
    projector_gamma: float = 1.0
    subsurface: bool = False
    interreflection: bool = False
    interreflection_samples: int = 128
    interreflection_stride: int = 6

    def __post_init__(self) -> None:
        if self.colour_model not in ("legacy", "physical"):
            raise SlscanError(f"optics.colour_model: expected 'physical' or 'legacy', got {self.colour_model!r}")
        _check_number("optics.projector_blur", self.projector_blur, low=0.0)
        _check_number("optics.projector_fnumber", self.projector_fnumber, low=0.0,
                      expected="an f-number > 0 (0: a pinhole, no defocus)")
        _check_number("optics.projector_focal_mm", self.projector_focal_mm, low=0.0, strict=True)
        _check_number("optics.projector_gamma", self.projector_gamma, low=0.0, strict=True)
        if self.projector_fnumber > 0:
            _check_number("optics.projector_focus_mm", self.projector_focus_mm, low=self.projector_focal_mm,
                          strict=True, expected=f"a focus distance in front of the projector, beyond its "
                          f"focal length ({self.projector_focal_mm:g} mm)")
        for key in ("subsurface", "interreflection"):
            if not isinstance(getattr(self, key), bool):
                raise SlscanError(f"optics.{key}: expected true or false, got {getattr(self, key)!r}")
        for key in ("interreflection_samples", "interreflection_stride"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise SlscanError(f"optics.{key}: expected an integer >= 1, got {value!r}")

    @property
    def defocus(self) -> bool:
        """The projector has a finite depth of field (``projector_fnumber`` > 0)."""
        return self.projector_fnumber > 0


    def to_dict(self) -> dict:
        return {
            "projector_blur_px": self.projector_blur, "projector_black": self.projector_black,
            "crosstalk": [list(r) for r in self.crosstalk], "ambient": list(self.ambient),
            "colour_model": self.colour_model, "projector_fnumber": self.projector_fnumber,
            "projector_focus_mm": self.projector_focus_mm, "projector_focal_mm": self.projector_focal_mm,
            "projector_gamma": self.projector_gamma, "subsurface": self.subsurface,
            "interreflection": self.interreflection, "interreflection_samples": self.interreflection_samples,
            "interreflection_stride": self.interreflection_stride,
        }


def _check_number(key: str, value, *, low: float, strict: bool = False, high: float | None = None,
                  expected: str | None = None) -> None:
    """Raise naming ``key`` unless ``value`` is a finite number above ``low`` (``strict``) or
    at least ``low``, and at most ``high``."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > low if strict else value >= low) and (high is None or value <= high)
    if not ok:
        if expected is None:
            bound = f"> {low:g}" if strict else f">= {low:g}"
            expected = f"a number {bound}" + ("" if high is None else f" and <= {high:g}")
        raise SlscanError(f"{key}: expected {expected}, got {value!r}")


def _switch_on(key: str):
    def apply(optics: Optics, sensor, working_distance: float):
        return dataclasses.replace(optics, **{key: True}), sensor

    return apply


register(Effect(
    "subsurface",
    "light entering marble-like materials leaves the surface spread over their mean free path",
    "Jensen et al. 2001 (dipole diffusion; its exponential far field); Nayar et al. 2006",
    _switch_on("subsurface"),
))
register(Effect(
    "interreflection",
    "one bounce of projector light between surfaces (concave folds light themselves)",
    "Nayar et al. 2006; Gupta et al. 2011 (global illumination breaks structured light)",
    _switch_on("interreflection"),
))


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
    proj_depth : (h, w) float64 depth of ``point`` along the projector axis, mm (nan: no hit)
    proj_focal_px : the projector's focal length, projector px
    material : (h, w) int16 index into ``materials`` (-1: background); None: all the first
    materials : the scene's materials (:class:`slscan.virtual.scenes.Material`)
    transport : global light transport traced for the view (:mod:`slscan.virtual.transport`);
        None: direct light only
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
    proj_depth: np.ndarray | None = None
    proj_focal_px: float = 0.0
    material: np.ndarray | None = None
    materials: tuple = ()
    transport: transport.Transport | None = None

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


def _specular_factor(scene: Scene, mat: np.ndarray, n, to_light, to_eye) -> np.ndarray:
    """Each point's material's ``specular * (n . h)**shininess`` (k,)."""
    if len(scene.materials) == 1:
        m = scene.materials[0]
        return m.specular * _blinn_phong(n, to_light, to_eye, m.shininess)
    out = np.zeros(len(n))
    for k, m in enumerate(scene.materials):
        sel = np.flatnonzero(mat == k)
        if len(sel) and m.specular > 0:
            out[sel] = m.specular * _blinn_phong(n[sel], to_light[sel], to_eye[sel], m.shininess)
    return out


def trace_view(scene: Scene, rig: Rig, rig_from_object: np.ndarray, optics: Optics | None = None) -> ViewGeometry:
    """Trace the camera, projector and light rays of one view of ``scene`` at ``rig_from_object``.

    ``optics`` that switch on global light transport (subsurface, inter-reflection) also
    trace what it needs (:mod:`slscan.virtual.transport`), once for all the view's images."""
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
    n = shading_normals(scene, rig_from_object[:3, :3], tri, wts, geo_n, facing_cam)
    p_obj = (point - rig_from_object[:3, 3]) @ rig_from_object[:3, :3]
    albedo = scene.albedo.at(p_obj, prim, bary)
    mat = scene.material_of(prim)

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
    proj_spec = np.where(lit, _specular_factor(scene, mat, n, l_proj, to_eye) * falloff, 0.0)

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
        light_spec[i] = np.where(vis, _specular_factor(scene, mat, n, l_dir, to_eye) * fall, 0)

    def full(values, fill, dtype):
        out = np.full((h * w,) + values.shape[1:], fill, dtype=dtype)
        out[idx] = values
        return out.reshape((h, w) + values.shape[1:])

    def full_stack(values):
        out = np.zeros((values.shape[0], h * w), np.float32)
        out[:, idx] = values
        return out.reshape(values.shape[0], h, w)

    point_img = full(point, np.nan, np.float64)
    normal_img = full(n.astype(np.float32), np.nan, np.float32)
    material_img = full(mat, -1, np.int16)
    per_view = None
    if optics is not None:
        per_view = transport.prepare(scene, rig, rig_from_object, vertices, rscene, point_img, normal_img,
                                     hit.reshape(h, w), material_img, optics)
    return ViewGeometry(
        hit=hit.reshape(h, w),
        point=point_img,
        normal=normal_img,
        albedo=full(albedo, np.nan, np.float32),
        proj_uv=full(uv, np.nan, np.float64),
        proj_footprint=full(footprint.astype(np.float32), 0, np.float32),
        proj_lit=full(lit, False, bool),
        proj_diffuse=full(proj_diffuse.astype(np.float32), 0, np.float32),
        proj_specular=full(proj_spec.astype(np.float32), 0, np.float32),
        light_diffuse=full_stack(light_diffuse),
        light_specular=full_stack(light_spec),
        proj_depth=full((point - proj.center) @ proj.axis, np.nan, np.float64),
        proj_focal_px=float(proj.lens.fx),
        material=material_img,
        materials=tuple(scene.materials),
        transport=per_view,
    )


def needs_trace(geom: ViewGeometry, optics: Optics) -> bool:
    """True when ``geom`` lacks the global light transport ``optics`` switches on (trace
    the view again with :func:`trace_view`'s ``optics``)."""
    if not transport.active(optics):
        return False
    return geom.transport is None or not geom.transport.matches(optics)


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
def _profile_filter(blur: float, values_bytes: bytes, n: int, gamma: float = 1.0) -> _ProfileFilter:
    """The filter of an (n, 3) uint8 projector profile blurred by ``blur`` projector px,
    emitted through the projector's tone curve ``(v / 255) ** gamma``."""
    values = emitted(np.frombuffer(values_bytes, dtype=np.uint8).reshape(n, 3), gamma)
    return _ProfileFilter.build(values, blur)


def emitted(values: np.ndarray, gamma: float = 1.0) -> np.ndarray:
    """Relative light the projector emits, float64 in [0, 1], for pattern ``values`` uint8
    through its tone curve ``(v / 255) ** gamma``."""
    light = values / 255.0
    return light if gamma == 1.0 else light**gamma


def image_profile(image: np.ndarray) -> tuple[str, np.ndarray]:
    """(axis, values) when projector ``image`` (h, w, 3) uint8 varies along one axis only:
    axis {"none", "columns", "rows"} and its (n, 3) values; ("2d", image) otherwise."""
    if (image == image[:1]).all():
        values = image[0]
        return ("none", values[:1]) if (values == values[:1]).all() else ("columns", values)
    if (image == image[:, :1]).all():
        return "rows", image[:, 0]
    return "2d", image


def defocus_sigma(geom: ViewGeometry, optics: Optics) -> np.ndarray:
    """Gaussian sigma (k,) of the projector's thin-lens defocus at each hit pixel, projector px.

    The circle of confusion of a point at depth ``d`` along the projector axis, focus
    ``d_f``, focal length ``f`` and aperture diameter ``A = f / N`` has diameter
    ``c = A f |d - d_f| / (d (d_f - f))`` on the DMD (mm), ``c * fx / f`` projector px;
    its blur is taken as a Gaussian of sigma ``c / 2.4``. Zeros when the lens is a pinhole
    and at the focus distance (below :data:`IN_FOCUS`: rounding of the traced depth).
    """
    d = geom.proj_depth[geom.hit] if geom.proj_depth is not None else None
    if not optics.defocus or d is None:
        return np.zeros(int(geom.hit.sum()))
    f, d_f = optics.projector_focal_mm, optics.projector_focus_mm
    aperture = f / optics.projector_fnumber
    coc_px = geom.proj_focal_px * aperture * np.abs(d - d_f) / (np.maximum(d, f) * (d_f - f))
    sigma = coc_px / COC_PER_SIGMA
    sigma[sigma < IN_FOCUS] = 0.0
    return sigma


def defocus_levels(sigma: np.ndarray) -> list[tuple[float, float, np.ndarray, np.ndarray]]:
    """Pixels grouped by defocus: ``[(sigma_lo, sigma_hi, index, weight), ...]``.

    Defocus ``sigma`` (k,) px falls between two levels of a fixed ladder (0, then 0.1 px
    growing by 1.25); a pixel's light is ``(1 - weight) * light(sigma_lo) + weight *
    light(sigma_hi)`` with the weight linear in variance, so the blend has exactly the
    variance of the pixel's own blur. Pixels with no defocus get weight 0 at level 0."""
    ladder = [0.0, DOF_FIRST_LEVEL]
    top = float(sigma.max()) if len(sigma) else 0.0
    while ladder[-1] < top:
        ladder.append(ladder[-1] * DOF_LEVEL_RATIO)
    levels = np.asarray(ladder)
    k = np.clip(np.searchsorted(levels, sigma, side="right") - 1, 0, len(levels) - 2)
    out = []
    for j in np.unique(k):
        index = np.flatnonzero(k == j)
        lo, hi = levels[j], levels[j + 1]
        weight = np.clip((sigma[index] ** 2 - lo**2) / (hi**2 - lo**2), 0.0, 1.0)
        out.append((float(lo), float(hi), index, weight))
    return out


def _blend_defocus(sigma: np.ndarray, sample: Callable[[float, np.ndarray], np.ndarray]) -> np.ndarray:
    """Light (k, 3) of pixels with defocus ``sigma`` (k,), from ``sample(level, index)``: the
    light of pixels ``index`` under defocus ``level`` px (see :func:`defocus_levels`)."""
    light = np.empty((len(sigma), 3))
    for lo, hi, index, weight in defocus_levels(sigma):
        part = sample(lo, index)
        blend = weight > 0
        if blend.any():
            sub = index[blend]
            part[blend] += weight[blend, None] * (sample(hi, sub) - part[blend])
        light[index] = part
    return light


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

    gamma = optics.projector_gamma
    plane = image.astype(np.float32) / 255.0 if gamma == 1.0 else emitted(image, gamma).astype(np.float32)
    footprint = float(np.median(geom.proj_footprint[hit])) if hit.any() else 1.0
    uv = geom.proj_uv[hit].astype(np.float32)

    def sample(defocus: float, index: np.ndarray) -> np.ndarray:
        sigma = float(np.hypot(np.hypot(optics.projector_blur, defocus), footprint / np.sqrt(12.0)))
        blurred = cv2.GaussianBlur(plane, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT) if sigma > 0 else plane
        return _remap_points(blurred, uv[index])

    light = _blend_defocus(defocus_sigma(geom, optics), sample) if optics.defocus else sample(0.0, slice(None))
    black = optics.projector_black
    return black + (1 - black) * light


def _light_from_profile(geom: ViewGeometry, axis: str, values: np.ndarray, optics: Optics) -> np.ndarray:
    hit = geom.hit
    gamma = optics.projector_gamma
    if axis == "none":
        light = np.broadcast_to(emitted(values[0], gamma), (int(hit.sum()), 3)).astype(np.float64)
    else:
        a = 0 if axis == "columns" else 1
        values = np.ascontiguousarray(values, dtype=np.uint8)
        coord = geom.proj_uv[..., a][hit]
        width = geom.proj_footprint[..., a][hit].astype(np.float64)

        def sample(defocus: float, index) -> np.ndarray:
            blur = float(np.hypot(optics.projector_blur, defocus))
            return _profile_filter(blur, values.tobytes(), len(values), gamma).sample(coord[index], width[index])

        light = _blend_defocus(defocus_sigma(geom, optics), sample) if optics.defocus else sample(0.0, slice(None))
    black = optics.projector_black
    return black + (1 - black) * light


def _remap_points(plane: np.ndarray, at: np.ndarray) -> np.ndarray:
    """``plane`` (h, w, 3) float32 sampled bilinearly at projector positions ``at`` (k, 2), (k, 3)
    float64. remap's maps must stay under 32767 rows and columns: the points go in rows."""
    import cv2

    k = len(at)
    cols = REMAP_ROW
    padded = np.zeros((-(-k // cols) * cols, 2), np.float32)
    padded[:k] = at
    grid = padded.reshape(-1, cols, 2)
    sampled = cv2.remap(plane, grid[..., 0], grid[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return sampled.reshape(-1, 3)[:k].astype(np.float64)


def projector_light_at(uv: np.ndarray, shown: PatternImage | np.ndarray | None, optics: Optics,
                       width: float | np.ndarray = 1.0) -> np.ndarray:
    """RGB projector emission (k, 3) in [0, 1] at arbitrary projector positions ``uv`` (k, 2)
    (continuous column, row), for a pattern description or a projector image (h, w, 3)
    uint8 (None: switched off): the projector's blurred image box-filtered over ``width``
    projector px (one for all, or (k,) per position; an image that varies in 2-D is
    filtered with their median), as :func:`projector_light` does at the camera pixels."""
    uv = np.asarray(uv, dtype=np.float64)
    width = np.broadcast_to(np.asarray(width, dtype=np.float64), (len(uv),))
    if shown is None:
        return np.zeros((len(uv), 3))
    if isinstance(shown, PatternImage):
        axis, values = shown.axis, pattern_profile(shown)
    else:
        axis, values = image_profile(shown)
    gamma = optics.projector_gamma
    if axis == "none":
        light = np.broadcast_to(emitted(values[0], gamma), (len(uv), 3)).astype(np.float64)
    elif axis in ("columns", "rows"):
        a = 0 if axis == "columns" else 1
        values = np.ascontiguousarray(values, dtype=np.uint8)
        filt = _profile_filter(optics.projector_blur, values.tobytes(), len(values), gamma)
        light = filt.sample(uv[:, a], width)
    else:
        import cv2

        plane = emitted(values, gamma).astype(np.float32)
        sigma = float(np.hypot(optics.projector_blur, (np.median(width) if len(width) else 1.0) / np.sqrt(12.0)))
        plane = cv2.GaussianBlur(plane, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        light = _remap_points(plane, uv)
    black = optics.projector_black
    return black + (1 - black) * light


def shade_pattern(geom: ViewGeometry, desc: PatternImage | None, optics: Optics) -> np.ndarray:
    """Linear radiance image (h, w, 3) float32 under projected pattern ``desc`` (None: off)."""
    return _shade(geom, projector_light(geom, desc, optics), optics, desc)


def shade_image(geom: ViewGeometry, image: np.ndarray | None, optics: Optics) -> np.ndarray:
    """Linear radiance image (h, w, 3) float32 under projector image (h, w, 3) uint8
    (None: off); a rendered pattern gives exactly :func:`shade_pattern`'s result."""
    return _shade(geom, projector_light_image(geom, image, optics), optics, image)


def _check_transport(geom: ViewGeometry, optics: Optics) -> None:
    if needs_trace(geom, optics):
        raise SlscanError("optics switch on subsurface scattering or inter-reflections, but the view was traced "
                          "without them: trace it with trace_view(scene, rig, pose, optics)")


def _diffuse_irradiance(geom: ViewGeometry, light: np.ndarray, optics: Optics,
                        shown: PatternImage | np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(per-primary light, geometric factor) at the hit pixels, whose product is the
    diffuse irradiance; with global light transport on, the light already includes it."""
    hit = geom.hit
    if not transport.active(optics):
        return light, geom.proj_diffuse[hit]
    _check_transport(geom, optics)
    light_at = None if shown is None else (lambda uv, width: projector_light_at(uv, shown, optics, width))
    irradiance = transport.diffuse_irradiance(geom.transport, hit, light, geom.proj_diffuse[hit].astype(np.float64),
                                              light_at)
    return irradiance, np.ones(len(irradiance))


def _specular_tint(geom: ViewGeometry) -> np.ndarray | None:
    """(n_hit, 3) specular colour of each hit pixel's material; None when all are white."""
    if geom.material is None or all(m.white_specular for m in geom.materials):
        return None
    colours = np.asarray([m.specular_colour for m in geom.materials], dtype=np.float64)
    return colours[geom.material[geom.hit]]


def _shade(geom: ViewGeometry, light: np.ndarray, optics: Optics,
           shown: PatternImage | np.ndarray | None = None) -> np.ndarray:
    hit = geom.hit
    m = np.asarray(optics.crosstalk, dtype=np.float64)
    albedo = geom.albedo[hit].astype(np.float64)
    light_d, geometric = _diffuse_irradiance(geom, light, optics, shown)
    if optics.colour_model == "physical":
        diffuse = albedo * (light_d @ m.T) * geometric[:, None]
    else:
        diffuse = (albedo * light_d) @ m.T * geometric[:, None]
    specular = light @ m.T * geom.proj_specular[hit][:, None]
    tint = _specular_tint(geom)
    if tint is not None:
        specular = specular * tint
    ambient = albedo * np.asarray(optics.ambient)
    out = np.zeros(hit.shape + (3,), np.float32)
    out[hit] = diffuse + specular + ambient
    return out


def shade_light(geom: ViewGeometry, light_index: int, rig: Rig, optics: Optics) -> np.ndarray:
    """Linear radiance image (h, w, 3) float32 under ring light ``light_index``, projector off."""
    out = shade_pattern(geom, None, optics)
    add_light(out, geom, light_index, rig, optics)
    return out


def add_light(radiance: np.ndarray, geom: ViewGeometry, light_index: int, rig: Rig,
              optics: Optics | None = None) -> None:
    """Add ring light ``light_index``'s diffuse and specular light to ``radiance`` (h, w, 3).

    With ``optics.subsurface`` on, the light is spread under scattering materials (ring
    lights are not inter-reflected)."""
    hit = geom.hit
    intensity = np.asarray(rig.lights[light_index].intensity, dtype=np.float64)
    albedo = geom.albedo[hit].astype(np.float64)
    if optics is not None and optics.subsurface:
        _check_transport(geom, optics)
        irradiance = intensity * geom.light_diffuse[light_index][hit][:, None].astype(np.float64)
        if geom.transport.subsurface is not None:
            irradiance = transport.spread_hit(geom.transport.subsurface, hit, irradiance)
        diffuse = albedo * irradiance
    else:
        diffuse = albedo * intensity * geom.light_diffuse[light_index][hit][:, None]
    specular = intensity * geom.light_specular[light_index][hit][:, None]
    tint = _specular_tint(geom)
    if tint is not None:
        specular = specular * tint
    radiance[hit] += (diffuse + specular).astype(np.float32)


DOF_FNUMBER = 2.0  # effect ``dof``: an f/2 projector lens
PROJECTOR_GAMMA = 2.2  # effect ``tone``: a typical uncalibrated projector


def _dof_on(optics: Optics, sensor, working_distance: float):
    fnumber = optics.projector_fnumber or DOF_FNUMBER
    focus = optics.projector_focus_mm or working_distance
    return dataclasses.replace(optics, projector_fnumber=fnumber, projector_focus_mm=focus), sensor


def _tone_on(optics: Optics, sensor, working_distance: float):
    if optics.projector_gamma == 1.0:
        optics = dataclasses.replace(optics, projector_gamma=PROJECTOR_GAMMA)
    if sensor.response == "linear":
        sensor = dataclasses.replace(sensor, response="srgb")
    return optics, sensor


register(Effect(
    "dof", "projector depth of field: thin-lens defocus blur growing away from the focus distance "
    "(f/2, focused at the working distance)",
    "thin-lens circle of confusion, e.g. Hecht, Optics (5th ed.), sec. 5.7; Potmesil & Chakravarty, "
    "'A lens and aperture camera model for synthetic image generation', SIGGRAPH 1981", _dof_on))
register(Effect(
    "tone", "tone curves: projector gamma 2.2 (uncalibrated) and an sRGB camera response (JPEG-shooting "
    "camera) instead of linear RAW",
    "IEC 61966-2-1 (sRGB); Poynton, Digital Video and HD (2nd ed.), ch. 27 (gamma)", _tone_on))
