"""Photometric inversion per pixel: normal and RGB albedo from the lit values, on arrays.

For every camera pixel that sees the range map, each lit image ``k`` is modelled as
(normalised units, :mod:`slscan.albedo.radiometry`)

    v_kc = a_c * (ambient_c + I_kc * max(0, n . l_k) * (d_ref / d_k)**2)
           + I_kc * s * max(0, n . h_k)**m * (d_ref / d_k)**2

a Lambertian albedo ``a`` (RGB) plus a light-coloured Blinn-Phong lobe (strength ``s``,
shininess ``m``; ``h_k`` the half vector between light and eye) shared by the whole view.
The surface point comes from the range map; the lights from the light calibration.

Per pixel (after Rushmeier & Bernardini [2]_ and Rocchini et al. [1]_ §3.4):

1. **Usable lights**: a light is left out where the range map shadows it (shadow rays,
   :func:`slscan.albedo.surface.occluded`), where it grazes the surface, where the image
   is saturated, and where it is far darker than the pixel's brightest light (a cast
   shadow whose occluder the range map lacks).
2. **Specular lobe** (``specular="fit"``, :func:`fit_specular`): ``s`` and ``m`` are
   fitted once per view on a sample of pixels by variable projection (every pixel's
   normal and albedo re-solved inside). The ring lights sit close to the lens, so every
   light's highlight falls on the same surface patches: a highlight there is in all
   images at once and no per-pixel outlier test can see it; the lobe's shape across
   lights and pixels can.
3. **Normal and albedo** (``normals="photometric"``, :func:`solve_pixels`):
   Levenberg-Marquardt on the 3 x (lights) measurements for the normal (2 unknowns) and
   the RGB albedo (3), started from the range map's normal and, where linear photometric
   stereo lands elsewhere (or the first start did not converge), from that too, the better
   fit kept. Each pixel iterates until its step is negligible; the damped 5 x 5 system is
   solved in closed form (the albedo block is diagonal: eliminated, leaving a 2 x 2), on
   the pixels still iterating only, as whole-array numpy operations. The range map gives position and shadows; the images
   give the fine normal (the range map's normals are noisy at the scale of a pixel, and
   any normal error becomes an albedo error). ``normals="range"`` keeps the range map's
   normal and solves the albedo only (linear).
4. **Robust rejection**: a light whose residual is above the fit by more than
   ``outlier_threshold`` (a highlight the lobe does not explain) or below it (a shadow)
   is dropped, one per round, and the pixel re-solved.
5. **Consistent normals** (:func:`regularise_normals`, per view on the image grid): each
   photometric normal is pulled towards its neighbours in proportion to how poorly its
   own images determine it (in highlights, where normal and lobe trade off), then the
   albedo is re-solved for the regularised normals.
6. Pixels left with fewer than ``min_lights`` usable lights are invalid (NaN), not guessed.

References
----------
.. [1] Rocchini, Cignoni, Montani, Pingi, Scopigno, "A low cost 3D scanner based on
   structured light", Computer Graphics Forum 20(3), Eurographics 2001, §3.4.
.. [2] Rushmeier, Bernardini, "Computing consistent normals and colors from photometric
   data", Proc. 3-D Digital Imaging and Modeling (3DIM), 1999.
.. [3] Golub, Pereyra, "Separable nonlinear least squares: the variable projection
   method and its applications", Inverse Problems 19(2), 2003 (the lobe fit).
.. [4] Woodham, "Photometric method for determining surface orientation from multiple
   images", Optical Engineering 19(1), 1980 (linear photometric stereo, the second start).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from slscan.albedo.lights import LightCalibration
from slscan.errors import SlscanError

log = logging.getLogger(__name__)

NORMALS = ("photometric", "range")
SPECULAR = ("fit", "none")
LIGHT_SOURCES = ("auto", "ring", "projector")
CHUNK = 40000  # pixels solved at once (bounds memory: ~50 floats per pixel and light)


@dataclass(frozen=True)
class AlbedoConfig:
    """How the albedo stage un-shades the lit images."""

    light: str = "auto"
    """{"auto", "ring", "projector"}: which light the albedo comes from. "ring": the
    paper's 6-light un-shading of the lit images; "projector": the projector's white frame
    (black frame subtracted) as one calibrated point light, with the range map's normals
    (:mod:`slscan.albedo.projector_light`, for rigs without ring lights); "auto": the ring
    when every view has ``min_lights`` lit images and the lights are known, else the
    projector."""
    min_lights: int = 3
    """Pixels with fewer usable lights (unshadowed, not grazing, not saturated, not
    rejected) are invalid."""
    normals: str = "photometric"
    """{"photometric", "range"}: solve the fine normal from the images (started from the
    range map's), or take the range map's normal as it is."""
    specular: str = "fit"
    """{"fit", "none"}: fit a light-coloured Blinn-Phong lobe per view, or assume matte."""
    outlier_threshold: float = 0.15
    """A light whose luminance is off the fit by more than this fraction (or by the noise
    floor, whichever is larger) is rejected: above, a highlight; below, a shadow."""
    noise_dn: float = 2.0
    """Noise floor of the outlier test, digital numbers per channel (8-bit scale)."""
    max_rejections: int = 2
    """Lights rejected at most per pixel by the outlier test."""
    min_cos: float = 0.25
    """Lights meeting the range surface more obliquely (cos of incidence) are not used:
    near the terminator relief shadows itself and the normal's error is amplified."""
    shadow_ratio: float = 0.5
    """Before any fit, a light whose shading-corrected luminance is below this fraction
    of the pixel's brightest is taken as cast shadow (one the range map missed: its
    occluder was never scanned). The brightest, not the median: where most lights are
    shadowed the median is a shadowed one."""
    edge_px: int = 1
    """Pixels this close to the range map's border or to a depth jump are invalid: they
    mix two surfaces (or surface and background) in the camera's blur."""
    shadow_offset_mm: float = 1.0
    """Shadow rays start this far off the range surface."""
    iterations: int = 8
    """Levenberg-Marquardt iterations per pixel at most (photometric normals); a pixel stops
    as soon as it has converged."""
    smoothness_deg: float = 2.0
    """Photometric normals are regularised towards their neighbours' (a Gaussian Markov
    field weighted by how well each pixel's images pin its normal down): the expected
    normal change between neighbouring pixels, degrees. 0 turns it off."""
    specular_samples: int = 6000
    """Pixels the specular lobe is fitted on (a random sample of the well-lit ones). 6000
    fit the figurine's lobe as 12000 did (0.127, 34.9 against 0.127, 34.7; the albedo
    benchmark's table unchanged within 0.1 point) at half the cost."""

    projector_highlight_deg: float = 0.0
    """Projector light: pixels whose normal is within this angle (degrees) of the half
    vector between projector and camera are left out as possible highlights (one light
    cannot tell a highlight from paint per pixel). 0 keeps them."""
    projector_normal_window_px: int = 21
    """Projector light: the largest window (pixels, odd) over which a plane is fitted to the
    range surface for the normal (:func:`slscan.albedo.projector_light.adaptive_normals`:
    each pixel takes the largest of 5, 9, 21, 41 px still planar within 4 times the range
    map's own noise); 0 keeps the range map's vertex normals. One light cannot correct a
    normal from the images, and a noisy range map's normals are noisy albedo: on
    kamino410's real chessboard (Gray code at 3-3.7 m) the white squares' albedo varies by
    20 % with the vertex normals and 3.5 % with these (the raw white frame: 3.2 %); on the
    virtual figurine at half size, whose range map is clean, they cost 0.6 point of median
    error (4.1 -> 4.7 %; p95 30.1 -> 29.4 %), on the tile they gain 0.1
    (``benchmarks/albedo_light.py``, ``benchmarks/real_projector_albedo.py``)."""
    projector_min_signal_dn: float = 4.0
    """Projector light: pixels whose white frame is brighter than the black by less than
    this (8-bit digital numbers, luminance) are left out (projector shadow, dark paint)."""

    def __post_init__(self) -> None:
        if self.light not in LIGHT_SOURCES:
            raise SlscanError(
                f"unknown albedo light {self.light!r}: expected one of {', '.join(LIGHT_SOURCES)}"
            )
        if self.normals not in NORMALS:
            raise SlscanError(
                f"unknown albedo normals {self.normals!r}: expected one of {', '.join(NORMALS)}"
            )
        if self.specular not in SPECULAR:
            raise SlscanError(
                f"unknown albedo specular {self.specular!r}: expected one of {', '.join(SPECULAR)}"
            )
        if self.min_lights < 1:
            raise SlscanError(f"albedo min_lights must be at least 1, got {self.min_lights}")
        if self.normals == "photometric" and self.min_lights < 3:
            raise SlscanError("albedo: photometric normals need min_lights >= 3")
        if self.projector_normal_window_px < 0 or (
            self.projector_normal_window_px and self.projector_normal_window_px % 2 == 0
        ):
            raise SlscanError(
                f"albedo projector_normal_window_px must be 0 or odd, got {self.projector_normal_window_px}"
            )
        if not 0 < self.outlier_threshold:
            raise SlscanError(
                f"albedo outlier_threshold must be positive, got {self.outlier_threshold}"
            )


@dataclass(frozen=True)
class SpecularLobe:
    """A light-coloured Blinn-Phong lobe: ``strength * max(0, n . h)**shininess``."""

    strength: float = 0.0
    shininess: float = 1.0

    def to_dict(self) -> dict:
        return {"strength": self.strength, "shininess": self.shininess}


# --- the per-pixel model -----------------------------------------------------------------
#
# Inside this module arrays are laid out pixels last, so that every operation of the
# solver is an element-wise operation over contiguous rows of pixels: normals and albedo
# (3, n), lit values (k, 3, n), per light and pixel (k, n), per-light vectors (3, k, n).
# The public functions take and return the documented (n, 3) / (k, n, 3) arrays.

STEP_TOLERANCE = 1e-6
"""A pixel's solve stops once its Levenberg-Marquardt step moves the normal by less than
this (radians) and the albedo by less than this fraction."""
DAMPING_CONVERGED = 1.0
"""...but only while the damping is below this: a heavily damped step is small because it
is damped, not because the pixel has converged."""
SECOND_START_DEG = 2.0
"""The second start (linear photometric stereo) is solved only where it lies further than
this from the first start's solution, or where the first did not converge: closer, it
falls in the same basin (measured: ``benchmarks/albedo.py``)."""
COMPACT_SHARE = 0.6
"""The working arrays are compacted to the pixels still iterating once fewer than this
share of them is."""


@dataclass(frozen=True)
class _Geometry:
    """Per light and pixel: direction to the light (3, k, n), falloff (k, n), half vector
    (3, k, n) between light and eye."""

    directions: np.ndarray
    falloff: np.ndarray
    half: np.ndarray


def _geometry(points: np.ndarray, positions: np.ndarray, reference_distance: float) -> _Geometry:
    """points : (n, 3) mm; positions : (k, 3) mm."""
    p = np.ascontiguousarray(points.T)  # (3, n)
    d = positions.T[:, :, None] - p[:, None, :]  # (3, k, n)
    dist = np.maximum(np.sqrt(_dot(d, d)), 1e-9)
    directions = d / dist
    eye = -p / np.maximum(np.sqrt((p * p).sum(0)), 1e-9)
    half = directions + eye[:, None, :]
    half /= np.maximum(np.sqrt(_dot(half, half)), 1e-12)
    return _Geometry(directions, (reference_distance / dist) ** 2, half)


def _take(geo: _Geometry, sel) -> _Geometry:
    """The geometry of the pixels ``sel`` (indices or mask)."""
    return _Geometry(geo.directions[:, :, sel], geo.falloff[:, sel], geo.half[:, :, sel])


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Dot product over the leading axis of length 3: (3, ...) . (3, ...) -> (...)."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _normalised(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(_dot(v, v))


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (3, n) each of unit normals n (3, n): ``t1 = n x ref``, ``t2 = n x t1``."""
    zero = np.zeros_like(n[0])
    by_x = np.abs(n[0]) < 0.9  # ref = x axis, else y axis
    t1 = np.where(by_x, np.stack([zero, n[2], -n[1]]), np.stack([-n[2], zero, n[0]]))
    t1 = _normalised(t1)
    t2 = np.stack(
        [n[1] * t1[2] - n[2] * t1[1], n[2] * t1[0] - n[0] * t1[2], n[0] * t1[1] - n[1] * t1[0]]
    )
    return t1, t2


def _shading(geo: _Geometry, n: np.ndarray, lobe: SpecularLobe) -> tuple[np.ndarray, np.ndarray]:
    """Diffuse factor D (k, n) and specular factor B (k, n), both with falloff."""
    diffuse = np.maximum(_dot(geo.directions, n[:, None, :]), 0.0) * geo.falloff
    if lobe.strength > 0:
        hn = np.maximum(_dot(geo.half, n[:, None, :]), 0.0)
        specular = lobe.strength * hn**lobe.shininess * geo.falloff
    else:
        specular = np.zeros_like(diffuse)
    return diffuse, specular


def _model(geo, n, a, intens, ambient, lobe) -> tuple[np.ndarray, np.ndarray]:
    """Predicted values (k, 3, n) and irradiance (k, 3, n) at normals n and albedo a (3, n).

    intens : (k, 3, 1) light intensities; ambient : (1, 3, 1)
    """
    diffuse, specular = _shading(geo, n, lobe)
    irradiance = diffuse[:, None, :] * intens + ambient
    return a * irradiance + specular[:, None, :] * intens, irradiance


def _cost(values, weight, geo, n, a, intens, ambient, lobe) -> np.ndarray:
    """Weighted sum of squared residuals (n,) at normals n and albedo a."""
    model, _ = _model(geo, n, a, intens, ambient, lobe)
    r = values - model
    return (weight[:, None, :] * (r * r)).sum((0, 1))


@dataclass(frozen=True)
class _System:
    """The normal equations ``J^T W J``, ``J^T W r`` of each pixel's fit in blocks, over
    the unknowns (normal tangent 1, tangent 2, albedo r, g, b); the albedo block is
    diagonal (each channel's albedo touches only that channel).

    hnn : (3, n) the normal block (11, 12, 22); hna : (2, 3, n); haa : (3, n) diagonal
    gn : (2, n); ga : (3, n); t1, t2 : (3, n) the tangents of the normal unknowns
    dd, ds : (2, k, n) derivatives of the diffuse and specular factors along t1, t2 (ds
    None when matte): J's normal columns are ``intens * (a * dd + ds)``
    irradiance, residual : (k, 3, n)
    """

    hnn: np.ndarray
    hna: np.ndarray
    haa: np.ndarray
    gn: np.ndarray
    ga: np.ndarray
    t1: np.ndarray
    t2: np.ndarray
    dd: np.ndarray
    ds: np.ndarray | None
    irradiance: np.ndarray
    residual: np.ndarray


def _system(values, weight, geo, n, a, intens, ambient, lobe) -> _System:
    """Jacobian and normal equations of the per-pixel model at normals n, albedo a (3, n).

    The normal columns of J are ``intens_kc * (a_c * dd_k + ds_k)``: their products are
    summed over the channels first, on (k, n) arrays, and never formed per channel.
    """
    t1, t2 = _tangents(n)
    cos = _dot(geo.directions, n[:, None, :])
    facing_falloff = np.where(cos > 0, geo.falloff, 0.0)
    irradiance = (cos * facing_falloff)[:, None, :] * intens + ambient
    model = a * irradiance
    dd = np.stack([_dot(geo.directions, t[:, None, :]) * facing_falloff for t in (t1, t2)])
    w = weight
    i2 = intens[..., 0] ** 2  # (k, 3)
    p2 = np.einsum("kc,cn->kn", i2, a * a) * w
    p1 = np.einsum("kc,cn->kn", i2, a) * w
    hnn = np.stack(
        [(dd[0] * dd[0] * p2).sum(0), (dd[0] * dd[1] * p2).sum(0), (dd[1] * dd[1] * p2).sum(0)]
    )
    ds = None
    if lobe.strength > 0:
        hn = _dot(geo.half, n[:, None, :])
        base = lobe.strength * np.maximum(hn, 1e-12) ** (lobe.shininess - 1) * geo.falloff
        model += (base * np.maximum(hn, 0.0))[:, None, :] * intens
        ds = np.stack([lobe.shininess * base * _dot(geo.half, t[:, None, :]) for t in (t1, t2)])
        p0 = i2.sum(1)[:, None] * w
        for i, (j, m) in enumerate(((0, 0), (0, 1), (1, 1))):
            hnn[i] += ((dd[j] * ds[m] + ds[j] * dd[m]) * p1 + ds[j] * ds[m] * p0).sum(0)
    residual = values - model
    wi = w[:, None, :] * intens
    wie = wi * irradiance
    wir = wi * residual
    hna = np.stack([a * (wie * d[:, None, :]).sum(0) for d in dd])
    r1 = (wir * a).sum(1)  # (k, n)
    gn = np.stack([(d * r1).sum(0) for d in dd])
    if ds is not None:
        hna += np.stack([(wie * d[:, None, :]).sum(0) for d in ds])
        r0 = wir.sum(1)
        gn += np.stack([(d * r0).sum(0) for d in ds])
    wirr = w[:, None, :] * irradiance
    haa = (wirr * irradiance).sum(0)
    ga = (wirr * residual).sum(0)
    return _System(hnn, hna, haa, gn, ga, t1, t2, dd, ds, irradiance, residual)


def _normal_columns(s: _System, a: np.ndarray, intens: np.ndarray) -> np.ndarray:
    """J's normal columns (2, k, 3, n)."""
    cols = a * s.dd[:, :, None, :]
    if s.ds is not None:
        cols = cols + s.ds[:, :, None, :]
    return cols * intens


def _block_solve(s: _System, damping, rn: np.ndarray, ra: np.ndarray):
    """Solve ``(J^T W J + damping diag(J^T W J)) x = (rn, ra)`` for every pixel in closed
    form: the diagonal albedo block eliminated, then the 2 x 2 normal block (its Schur
    complement) solved. rn : (2, n); ra : (3, n). Returns the normal part (2, n) in the
    tangents and the albedo part (3, n); zero where the system is singular."""
    h11 = s.hnn[0] + damping * np.maximum(s.hnn[0], 1e-12) + 1e-15
    h22 = s.hnn[2] + damping * np.maximum(s.hnn[2], 1e-12) + 1e-15
    inv = 1.0 / (s.haa + damping * np.maximum(s.haa, 1e-12) + 1e-15)  # (3, n)
    b0, b1 = s.hna[0] * inv, s.hna[1] * inv
    s11 = h11 - (b0 * s.hna[0]).sum(0)
    s12 = s.hnn[1] - (b0 * s.hna[1]).sum(0)
    s22 = h22 - (b1 * s.hna[1]).sum(0)
    r1 = rn[0] - (b0 * ra).sum(0)
    r2 = rn[1] - (b1 * ra).sum(0)
    det = s11 * s22 - s12 * s12
    with np.errstate(divide="ignore", invalid="ignore"):
        x1 = (s22 * r1 - s12 * r2) / det
        x2 = (s11 * r2 - s12 * r1) / det
    bad = ~(np.isfinite(x1) & np.isfinite(x2))
    x1[bad], x2[bad] = 0.0, 0.0
    xa = (ra - s.hna[0] * x1 - s.hna[1] * x2) * inv
    return np.stack([x1, x2]), xa


def _linear_albedo(values, weight, geo, n, intens, ambient, lobe) -> np.ndarray:
    """Least-squares albedo (3, n) for fixed normals (3, n)."""
    diffuse, specular = _shading(geo, n, lobe)
    e = diffuse[:, None, :] * intens + ambient
    we = weight[:, None, :] * e
    target = values - specular[:, None, :] * intens
    return (we * target).sum(0) / np.maximum((we * e).sum(0), 1e-12)


def _linear_normals(values, weight, geo, intens) -> np.ndarray:
    """Photometric-stereo normals (3, n) from the grey level, Lambertian, ambient ignored:
    the 3 x 3 normal equations of every pixel solved in closed form (adjugate)."""
    grey = (values / intens).mean(1)  # (k, n)
    a = geo.directions * geo.falloff  # (3, k, n)
    wa = a * weight
    m = np.einsum("ikn,jkn->ijn", wa, a) + 1e-9 * np.eye(3)[:, :, None]  # (3, 3, n)
    b = (wa * grey).sum(1)  # (3, n)
    c0, c1, c2 = m[0], m[1], m[2]  # rows (symmetric)
    adj = np.stack([_cross(c1, c2), _cross(c2, c0), _cross(c0, c1)])  # rows of the adjugate
    det = _dot(c0, adj[0])
    g = np.einsum("ijn,jn->in", adj, b) / det
    norm = np.sqrt(_dot(g, g))
    ok = (norm > 1e-12) & np.isfinite(norm)
    fallback = np.array([0.0, 0.0, -1.0])[:, None]
    return np.where(ok, g / np.where(ok, norm, 1.0), fallback)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross product over the leading axis: (3, n) x (3, n)."""
    return np.stack(
        [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
    )


def _levenberg_marquardt(values, weight, geo, n0, intens, ambient, lobe, iterations):
    """Levenberg-Marquardt per pixel on normal and albedo, each pixel until it converges
    (:data:`STEP_TOLERANCE`) or for ``iterations``; returns (albedo, normal, cost,
    converged). Only the pixels still iterating are computed: the working arrays are
    compacted to them as they thin out."""
    n = n0.copy()
    a = _linear_albedo(values, weight, geo, n, intens, ambient, lobe)
    cost = _cost(values, weight, geo, n, a, intens, ambient, lobe)
    damping = np.full(n.shape[1], 1e-3)
    converged = np.zeros(n.shape[1], bool)
    work = np.arange(n.shape[1])  # pixels in the working arrays
    live = np.ones(len(work), bool)  # of those, the ones still iterating
    v, w, g = values, weight, geo
    for _ in range(iterations):
        nw, aw, lam = n[:, work], a[:, work], damping[work]
        s = _system(v, w, g, nw, aw, intens, ambient, lobe)
        xn, xa = _block_solve(s, lam, s.gn, s.ga)
        n_new = _normalised(nw + xn[0] * s.t1 + xn[1] * s.t2)
        a_new = aw + xa
        cost_new = _cost(v, w, g, n_new, a_new, intens, ambient, lobe)
        better = live & (cost_new < cost[work])
        moved = work[better]
        n[:, moved], a[:, moved], cost[moved] = n_new[:, better], a_new[:, better], cost_new[better]
        damping[work] = np.where(better, np.maximum(lam / 3, 1e-9), np.minimum(lam * 10, 1e9))
        small = (np.abs(xn).max(0) < STEP_TOLERANCE) & (
            np.abs(xa).max(0) < STEP_TOLERANCE * (np.abs(aw).max(0) + STEP_TOLERANCE)
        )
        done = live & small & (lam <= DAMPING_CONVERGED)
        converged[work[done]] = True
        live &= ~done
        if not live.any():
            break
        if live.mean() < COMPACT_SHARE:
            work, v, w, g = work[live], v[:, :, live], w[:, live], _take(g, live)
            live = np.ones(len(work), bool)
    return a, n, cost, converged


def _solve_normals(values, weight, geo, n0, intens, ambient, lobe, iterations, second_start=True):
    """Levenberg-Marquardt from the range normal and, where it may find another minimum,
    from linear photometric stereo; the better fit kept. Returns (albedo, normal, cost)."""
    a, n, cost, converged = _levenberg_marquardt(
        values, weight, geo, n0, intens, ambient, lobe, iterations
    )
    if not second_start:
        return a, n, cost
    start = _linear_normals(values, weight, geo, intens)
    far = _dot(start, n) < np.cos(np.radians(SECOND_START_DEG))
    sel = np.flatnonzero(far | ~converged)
    if len(sel):
        a2, n2, cost2, _ = _levenberg_marquardt(
            values[:, :, sel],
            weight[:, sel],
            _take(geo, sel),
            start[:, sel],
            intens,
            ambient,
            lobe,
            iterations,
        )
        b = cost2 < cost[sel]
        a[:, sel[b]], n[:, sel[b]], cost[sel[b]] = a2[:, b], n2[:, b], cost2[b]
    return a, n, cost


def _pixels_last(values: np.ndarray) -> np.ndarray:
    """(k, n, 3) -> (k, 3, n) contiguous."""
    return np.ascontiguousarray(np.asarray(values, float).transpose(0, 2, 1))


def _light_terms(lights: LightCalibration, light_ids: np.ndarray):
    """Intensities (k, 3, 1), ambient (1, 3, 1) and positions (k, 3) of the lit images."""
    intens = lights.intensities[light_ids][:, :, None]
    ambient = np.asarray(lights.ambient, float)[None, :, None]
    return intens, ambient, lights.positions[light_ids]


def fit_specular(
    values: np.ndarray,
    weight: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    lights: LightCalibration,
    light_ids: np.ndarray,
    *,
    initial: SpecularLobe = SpecularLobe(0.05, 10.0),
    rounds: int = 8,
    iterations: int = 6,
) -> SpecularLobe:
    """Fit one Blinn-Phong lobe to pixels, every pixel's normal and albedo re-solved inside.

    values : (k, n, 3) normalised; weight : (k, n) 1 for usable lights, 0 otherwise
    points, normals : (n, 3) mm, unit (starting normals)
    Variable projection: each round solves every pixel for the current lobe, then takes
    one Gauss-Newton step in (strength, log shininess) on the residuals with the pixels'
    own unknowns projected out.
    """
    intens, ambient, positions = _light_terms(lights, np.asarray(light_ids, int))
    v = _pixels_last(values)
    weight = np.asarray(weight, float)
    geo = _geometry(np.asarray(points, float), positions, lights.reference_distance)
    start = np.ascontiguousarray(np.asarray(normals, float).T)
    strength, shininess = float(initial.strength), float(initial.shininess)
    w = weight[:, None, :]
    for round_ in range(rounds):
        lobe = SpecularLobe(strength, shininess)
        a, n, _ = _solve_normals(
            v, weight, geo, start, intens, ambient, lobe, iterations, second_start=round_ == 0
        )
        start = n
        s = _system(v, weight, geo, n, a, intens, ambient, lobe)
        hn = np.maximum(_dot(geo.half, n[:, None, :]), 1e-12)
        base = hn**shininess * geo.falloff
        # (2, k, 3, n): d/d strength, d/d log shininess
        jg = np.stack([base, strength * shininess * np.log(hn) * base])[:, :, None, :] * intens
        wjg = w * jg
        # the pixels' own unknowns projected out: h = Jg'WJg - C' H^-1 C and
        # g = Jg'Wr - C' H^-1 J'Wr, with C = J'W Jg (5 x 2) per pixel
        h = np.einsum("gkcn,hkcn->gh", wjg, jg)
        g = np.einsum("gkcn,kcn->g", wjg, s.residual)
        cn = np.einsum(
            "jkcn,gkcn->gjn", _normal_columns(s, a, intens), wjg
        )  # (2, 2, n): C's normal rows
        ca = (wjg * s.irradiance).sum(1)  # (2, 3, n): C's albedo rows
        for col in range(2):
            xn, xa = _block_solve(s, 0.0, cn[col], ca[col])
            h[:, col] -= (cn * xn).sum((1, 2)) + (ca * xa).sum((1, 2))
            g[col] -= (xn * s.gn).sum() + (xa * s.ga).sum()
        try:
            step = np.linalg.solve(h + 1e-6 * np.diag(np.diag(h)) + 1e-18 * np.eye(2), g)
        except np.linalg.LinAlgError:
            break
        new_strength = max(strength + step[0], 0.0)
        new_shininess = float(
            np.clip(np.exp(np.log(shininess) + np.clip(step[1], -1.0, 1.0)), 1.0, 2000.0)
        )
        done = (
            abs(new_strength - strength) < 1e-4 + 1e-3 * strength
            and abs(np.log(new_shininess / shininess)) < 1e-3
        )
        strength, shininess = new_strength, new_shininess
        if done or strength == 0.0:
            break
    return SpecularLobe(float(strength), float(shininess))


@dataclass(frozen=True)
class PixelSolution:
    """Per-pixel result of :func:`solve_pixels`, over n pixels and k lit images.

    albedo : (n, 3) float64 linear RGB, NaN where invalid; normal : (n, 3) unit
    valid : (n,) bool; used : (k, n) bool lights used in the final fit
    highlight, shadow : (k, n) bool lights rejected above / below the fit
    (shadow also holds the lights the range map shadows, passed in as ``shadowed``)
    """

    albedo: np.ndarray
    normal: np.ndarray
    valid: np.ndarray
    used: np.ndarray
    highlight: np.ndarray
    shadow: np.ndarray
    info: np.ndarray | None = None
    """(n, 3, 3) information matrix of each normal (per unit noise variance), photometric only."""
    noise: float = 0.0
    """Residual RMS per measurement of the final fits, normalised units."""


def _normal_information(values, weight, geo, n, a, intens, ambient, lobe):
    """Information (n, 3, 3) on each normal with the albedo marginalised, unit noise; and
    the fit's cost (n,)."""
    s = _system(values, weight, geo, n, a, intens, ambient, lobe)
    b = s.hna / (s.haa + 1e-12)  # (2, 3, n)
    s11 = s.hnn[0] - (b[0] * s.hna[0]).sum(0)
    s12 = s.hnn[1] - (b[0] * s.hna[1]).sum(0)
    s22 = s.hnn[2] - (b[1] * s.hna[1]).sum(0)
    t1, t2 = s.t1, s.t2
    info = (
        s11 * t1[:, None] * t1[None]
        + s12 * (t1[:, None] * t2[None] + t2[:, None] * t1[None])
        + s22 * t2[:, None] * t2[None]
    )  # (3, 3, n)
    cost = (weight[:, None, :] * s.residual**2).sum((0, 1))
    return info.transpose(2, 0, 1), cost


def solve_pixels(
    values: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    lights: LightCalibration,
    light_ids: np.ndarray,
    *,
    usable: np.ndarray | None = None,
    shadowed: np.ndarray | None = None,
    lobe: SpecularLobe = SpecularLobe(),
    config: AlbedoConfig = AlbedoConfig(),
    dn_unit: float = 1.0 / 255.0,
) -> PixelSolution:
    """Albedo of each pixel from its lit values, surface point and (range) normal.

    values : (k, n, 3) normalised units, image ``i`` lit by light ``light_ids[i]``
    points, normals : (n, 3) float mm and unit vectors, rig frame
    usable : (k, n) bool, e.g. not saturated; default all
    shadowed : (k, n) bool, lights the range map occludes; default none
    lobe : the view's specular lobe (strength 0: matte)
    dn_unit : one digital number in normalised units (noise floor of the outlier test)
    """
    values = np.asarray(values, float)
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    k, n_pix = values.shape[:2]
    if points.shape != (n_pix, 3) or normals.shape != (n_pix, 3):
        raise SlscanError(
            f"albedo: {n_pix} pixels of values but points {points.shape}, normals {normals.shape}"
        )
    light_ids = np.asarray(light_ids, int)
    if len(light_ids) != k:
        raise SlscanError(f"albedo: {k} lit values but {len(light_ids)} light ids")
    if light_ids.max(initial=-1) >= len(lights.lights) or light_ids.min(initial=0) < 0:
        raise SlscanError(
            f"albedo: light {int(light_ids.max())} is not in the light calibration ({len(lights.lights)} lights)"
        )
    usable = np.ones((k, n_pix), bool) if usable is None else usable.copy()
    shadowed = np.zeros((k, n_pix), bool) if shadowed is None else shadowed
    intens, ambient, positions = _light_terms(lights, light_ids)
    albedo = np.full((n_pix, 3), np.nan)
    normal_out = normals.copy()
    used = np.zeros((k, n_pix), bool)
    highlight = np.zeros((k, n_pix), bool)
    shadow = shadowed.copy()
    noise = config.noise_dn * dn_unit * np.sqrt(3.0) * 3.0
    info = np.zeros((n_pix, 3, 3))
    sq_sum, n_meas = 0.0, 0.0
    for start in range(0, n_pix, CHUNK):
        sl = slice(start, min(n_pix, start + CHUNK))
        geo = _geometry(points[sl], positions, lights.reference_distance)
        v = _pixels_last(values[:, sl])  # (k, 3, m)
        n_range = np.ascontiguousarray(normals[sl].T)  # (3, m)
        cos0 = _dot(geo.directions, n_range[:, None, :])
        use = usable[:, sl] & ~shadowed[:, sl] & (cos0 > config.min_cos)
        hl = np.zeros_like(use)
        sh = np.zeros_like(use)
        if config.shadow_ratio > 0:
            # dark outliers first: a cast shadow the range map missed would bend a
            # photometric normal to explain it
            diffuse, _ = _shading(geo, n_range, SpecularLobe())
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = (v / intens).mean(1) / diffuse
            ratio = np.where(use & np.isfinite(ratio), ratio, 0.0)
            dark = use & (ratio < config.shadow_ratio * ratio.max(axis=0))
            sh |= dark
            use &= ~dark
        n_cur = n_range.copy()
        a_cur = np.zeros((3, use.shape[1]))
        todo = np.ones(use.shape[1], bool)
        for round_ in range(config.max_rejections + 1):
            sel = np.flatnonzero(todo & (use.sum(0) >= config.min_lights))
            if len(sel) == 0:
                break
            gsel = _take(geo, sel)
            vsel = v[:, :, sel]
            wsel = use[:, sel].astype(float)
            if config.normals == "photometric":
                # later rounds start from the pixel's own solution, one light fewer
                a, n_new, _ = _solve_normals(
                    vsel,
                    wsel,
                    gsel,
                    n_cur[:, sel],
                    intens,
                    ambient,
                    lobe,
                    config.iterations,
                    second_start=round_ == 0,
                )
            else:
                n_new = n_cur[:, sel]
                a = _linear_albedo(vsel, wsel, gsel, n_new, intens, ambient, lobe)
            a_cur[:, sel], n_cur[:, sel] = a, n_new
            if round_ == config.max_rejections:
                break
            model, _ = _model(gsel, n_new, a, intens, ambient, lobe)
            grey_model = model.sum(1)
            resid = (vsel - model).sum(1)
            limit = np.maximum(config.outlier_threshold * grey_model, noise)
            score = np.where(use[:, sel], np.abs(resid) / limit, 0.0)
            worst = np.argmax(score, axis=0)
            cols = np.arange(len(sel))
            reject = (score[worst, cols] > 1.0) & (use[:, sel].sum(0) > config.min_lights)
            todo[:] = False
            todo[sel[reject]] = True
            rk, rp = worst[reject], sel[reject]
            use[rk, rp] = False
            above = resid[worst[reject], cols[reject]] > 0
            hl[rk[above], rp[above]] = True
            sh[rk[~above], rp[~above]] = True
            if not reject.any():
                break
        ok = use.sum(0) >= config.min_lights
        ok &= np.all(np.isfinite(a_cur), axis=0)
        if config.normals == "photometric" and ok.any():
            sel = np.flatnonzero(ok)
            wsel = use[:, sel].astype(float)
            h3, cost = _normal_information(
                v[:, :, sel],
                wsel,
                _take(geo, sel),
                n_cur[:, sel],
                a_cur[:, sel],
                intens,
                ambient,
                lobe,
            )
            info[sl][sel] = h3
            sq_sum += float(cost.sum())
            n_meas += float(wsel.sum() * 3 - 5 * len(sel))
        albedo[sl][ok] = a_cur.T[ok]
        normal_out[sl] = np.where(ok[:, None], n_cur.T, normals[sl])
        used[:, sl] = use & ok
        highlight[:, sl] = hl
        shadow[:, sl] |= sh
    valid = np.all(np.isfinite(albedo), axis=1)
    rms = float(np.sqrt(sq_sum / n_meas)) if n_meas > 0 else 0.0
    return PixelSolution(
        albedo,
        normal_out,
        valid,
        used,
        highlight,
        shadow,
        info if config.normals == "photometric" else None,
        rms,
    )


def regularise_normals(
    normals: np.ndarray,
    info: np.ndarray,
    valid: np.ndarray,
    *,
    smoothness_deg: float = 2.0,
    noise: float = 1.0,
    iterations: int = 30,
    crease_deg: float = 10.0,
) -> np.ndarray:
    """Photometric normals regularised towards their neighbours (Gaussian Markov field).

    Minimises ``sum_i |n_i - m_i|^2_(H_i / noise^2) + sum_(i~j) w_ij |n_i - n_j|^2 /
    smoothness^2`` by Jacobi iterations, renormalising each time; ``m_i`` is the
    per-pixel estimate and ``H_i`` its information matrix, so a normal the images pin
    down stays and a poorly determined one (in highlights) follows its neighbours. Links
    between neighbours whose estimates differ by much more than ``crease_deg`` are
    weakened (Cauchy weight), so creases and relief edges are kept.

    normals : (h, w, 3) unit; info : (h, w, 3, 3); valid : (h, w) bool
    Returns (h, w, 3) float64 (input normals where not valid).
    """
    if smoothness_deg <= 0 or not valid.any():
        return normals.astype(np.float64)
    rows, cols = np.nonzero(valid)
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    if (box[0].stop - box[0].start, box[1].stop - box[1].start) != valid.shape:
        out = normals.astype(np.float64).copy()
        out[box] = regularise_normals(
            normals[box],
            info[box],
            valid[box],
            smoothness_deg=smoothness_deg,
            noise=noise,
            iterations=iterations,
            crease_deg=crease_deg,
        )
        return out
    lam = 1.0 / np.radians(smoothness_deg) ** 2
    n0 = np.where(valid[..., None], np.nan_to_num(normals.astype(np.float64)), 0.0)
    h = info[valid] / max(noise, 1e-12) ** 2
    iso = (1e-2 * np.einsum("nii->n", h) / 3 + 1e-9)[:, None, None] * np.eye(3)
    h_iso = h + iso
    hb = np.einsum("nij,nj->ni", h_iso, n0[valid])
    tau2 = np.radians(crease_deg) ** 2
    shifts = ((0, 1), (0, -1), (1, 0), (-1, 0))
    weights = []
    for dy, dx in shifts:
        nb = _shift(n0, dy, dx)
        vb = _shift(valid, dy, dx)
        d2 = ((nb - n0) ** 2).sum(-1)
        weights.append((vb & valid) / (1.0 + d2 / tau2))
    degree = sum(weights)[valid]
    a = h_iso + (lam * degree)[:, None, None] * np.eye(3)
    a_inv = np.linalg.inv(a)
    n = n0.copy()
    for _ in range(iterations):
        acc = sum(w[..., None] * _shift(n, dy, dx) for w, (dy, dx) in zip(weights, shifts))
        new = np.einsum("nij,nj->ni", a_inv, hb + lam * acc[valid])
        new /= np.maximum(np.linalg.norm(new, axis=1, keepdims=True), 1e-12)
        n[valid] = new
    return np.where(valid[..., None], n, normals)


def _shift(a: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``a`` moved by (dy, dx) pixels, zero-filled (no wrap-around)."""
    out = np.zeros_like(a)
    h, w = a.shape[:2]
    ys, yd = (slice(0, h - dy), slice(dy, h)) if dy >= 0 else (slice(-dy, h), slice(0, h + dy))
    xs, xd = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
    out[yd, xd] = a[ys, xs]
    return out


def albedo_for_normals(
    values: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    lights: LightCalibration,
    light_ids: np.ndarray,
    used: np.ndarray,
    lobe: SpecularLobe = SpecularLobe(),
) -> np.ndarray:
    """Least-squares albedo (n, 3) for given normals and usable lights (n, 3), chunked."""
    out = np.empty((len(points), 3))
    intens, ambient, positions = _light_terms(lights, np.asarray(light_ids, int))
    for start in range(0, len(points), CHUNK):
        sl = slice(start, min(len(points), start + CHUNK))
        geo = _geometry(points[sl], positions, lights.reference_distance)
        out[sl] = _linear_albedo(
            _pixels_last(values[:, sl]),
            used[:, sl].astype(float),
            geo,
            np.ascontiguousarray(normals[sl].T),
            intens,
            ambient,
            lobe,
        ).T
    return out


def fit_view_lobe(
    values: np.ndarray,
    usable: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    lights: LightCalibration,
    light_ids: np.ndarray,
    config: AlbedoConfig = AlbedoConfig(),
) -> SpecularLobe:
    """The specular lobe of a view, fitted on a random sample of its well-lit pixels.

    values : (k, n, 3) normalised; usable : (k, n) bool (unshadowed, unsaturated)
    points, normals : (n, 3) mm and unit range-map normals, rig frame
    Pixels need at least 4 usable, non-grazing lights; with fewer than 100 such pixels
    the surface is taken as matte (strength 0).
    """
    positions = lights.positions[np.asarray(light_ids, int)]
    weight = np.empty(usable.shape, bool)
    for start in range(0, len(points), CHUNK):
        sl = slice(start, min(len(points), start + CHUNK))
        geo = _geometry(points[sl], positions, lights.reference_distance)
        cos0 = _dot(geo.directions, np.ascontiguousarray(normals[sl].T)[:, None, :])
        weight[:, sl] = usable[:, sl] & (cos0 > config.min_cos)
    candidates = np.flatnonzero(weight.sum(0) >= max(config.min_lights, 4))
    if len(candidates) < 100:
        log.info("too few pixels (%d) to fit a specular lobe: taken as matte", len(candidates))
        return SpecularLobe()
    rng = np.random.default_rng(0)
    size = min(config.specular_samples, len(candidates))
    sample = np.sort(rng.choice(candidates, size=size, replace=False))
    lobe = fit_specular(
        values[:, sample],
        weight[:, sample].astype(float),
        points[sample],
        normals[sample],
        lights,
        light_ids,
    )
    log.info("specular lobe: strength %.4f, shininess %.1f", lobe.strength, lobe.shininess)
    return lobe
