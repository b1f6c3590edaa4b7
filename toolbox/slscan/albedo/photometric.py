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
   the RGB albedo (3), started from the range map's normal and from linear photometric
   stereo, the better fit kept. The range map gives position and shadows; the images
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
CHUNK = 40000  # pixels solved at once (bounds memory: ~50 floats per pixel and light)


@dataclass(frozen=True)
class AlbedoConfig:
    """How the albedo stage un-shades the lit images."""

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
    """Gauss-Newton iterations per pixel (photometric normals)."""
    smoothness_deg: float = 2.0
    """Photometric normals are regularised towards their neighbours' (a Gaussian Markov
    field weighted by how well each pixel's images pin its normal down): the expected
    normal change between neighbouring pixels, degrees. 0 turns it off."""
    specular_samples: int = 12000
    """Pixels the specular lobe is fitted on."""

    def __post_init__(self) -> None:
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


@dataclass(frozen=True)
class _Geometry:
    """Per light and pixel: direction to the light (k, n, 3), falloff (k, n), half vector."""

    directions: np.ndarray
    falloff: np.ndarray
    half: np.ndarray


def _geometry(points: np.ndarray, positions: np.ndarray, reference_distance: float) -> _Geometry:
    d = positions[:, None, :] - points[None, :, :]
    dist = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
    directions = d / dist[..., None]
    eye = -points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-9)
    half = directions + eye[None]
    half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
    return _Geometry(directions, (reference_distance / dist) ** 2, half)


def _tangents(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ref = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, ref)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def _shading(geo: _Geometry, n: np.ndarray, lobe: SpecularLobe):
    """Diffuse factor D (k, n) and specular factor B (k, n), both with falloff."""
    cos = np.einsum("kni,ni->kn", geo.directions, n)
    diffuse = np.clip(cos, 0.0, None) * geo.falloff
    if lobe.strength > 0:
        hn = np.clip(np.einsum("kni,ni->kn", geo.half, n), 0.0, None)
        specular = lobe.strength * hn**lobe.shininess * geo.falloff
    else:
        specular = np.zeros_like(diffuse)
    return diffuse, specular


def _model(geo, n, a, intens, ambient, lobe, *, jacobian: bool = False):
    """Predicted values (k, n, 3) and, optionally, their Jacobian (k, n, 3, 5) in
    (normal tangent 1, tangent 2, albedo r, g, b) and the tangents used."""
    diffuse, specular = _shading(geo, n, lobe)
    irradiance = diffuse[..., None] * intens[:, None, :] + ambient  # (k, n, 3)
    model = a[None] * irradiance + specular[..., None] * intens[:, None, :]
    if not jacobian:
        return model, None, None
    t1, t2 = _tangents(n)
    facing = np.einsum("kni,ni->kn", geo.directions, n) > 0
    jac = np.empty(model.shape + (5,))
    if lobe.strength > 0:
        hn = np.clip(np.einsum("kni,ni->kn", geo.half, n), 1e-12, None)
        dspec = lobe.strength * lobe.shininess * hn ** (lobe.shininess - 1) * geo.falloff
    for j, t in enumerate((t1, t2)):
        dd = np.where(facing, np.einsum("kni,ni->kn", geo.directions, t), 0.0) * geo.falloff
        col = a[None] * (dd[..., None] * intens[:, None, :])
        if lobe.strength > 0:
            col = (
                col + (dspec * np.einsum("kni,ni->kn", geo.half, t))[..., None] * intens[:, None, :]
            )
        jac[..., j] = col
    jac[..., 2:] = 0.0
    for c in range(3):
        jac[:, :, c, 2 + c] = irradiance[..., c]
    return model, jac, (t1, t2)


def _linear_albedo(values, weight, geo, n, intens, ambient, lobe) -> np.ndarray:
    """Least-squares albedo (n, 3) for fixed normals."""
    diffuse, specular = _shading(geo, n, lobe)
    e = diffuse[..., None] * intens[:, None, :] + ambient
    w = weight[..., None]
    target = values - specular[..., None] * intens[:, None, :]
    return (w * e * target).sum(0) / np.maximum((w * e * e).sum(0), 1e-12)


def _linear_normals(values, weight, geo, intens) -> np.ndarray:
    """Photometric-stereo normals (n, 3) from the grey level, Lambertian, ambient ignored."""
    grey = (values / intens[:, None, :]).mean(-1)
    a = geo.directions * geo.falloff[..., None]
    m = np.einsum("kni,knj,kn->nij", a, a, weight) + 1e-9 * np.eye(3)
    g = np.linalg.solve(m, np.einsum("kni,kn,kn->ni", a, grey, weight)[..., None])[..., 0]
    norm = np.linalg.norm(g, axis=1, keepdims=True)
    return np.where(norm > 1e-12, g / np.maximum(norm, 1e-300), np.array([[0.0, 0.0, -1.0]]))


def _gauss_newton(values, weight, geo, n0, intens, ambient, lobe, iterations):
    """Levenberg-Marquardt per pixel on normal and albedo; returns (albedo, normal, cost)."""
    n = n0.copy()
    a = _linear_albedo(values, weight, geo, n, intens, ambient, lobe)
    w = weight[..., None]
    model, jac, (t1, t2) = _model(geo, n, a, intens, ambient, lobe, jacobian=True)
    cost = (w * (values - model) ** 2).sum((0, 2))
    damping = np.full(len(n), 1e-3)
    eye = np.eye(5)
    for _ in range(iterations):
        jtj, jtr = _normal_equations(jac, w, values - model)
        diag = np.maximum(np.einsum("npp->np", jtj), 1e-12)
        step = np.linalg.solve(
            jtj + damping[:, None, None] * (eye * diag[:, None, :]) + 1e-15 * eye, jtr[..., None]
        )[..., 0]
        n_new = n + step[:, :1] * t1 + step[:, 1:2] * t2
        n_new /= np.linalg.norm(n_new, axis=1, keepdims=True)
        a_new = a + step[:, 2:]
        model_new, jac_new, (t1_new, t2_new) = _model(
            geo, n_new, a_new, intens, ambient, lobe, jacobian=True
        )
        cost_new = (w * (values - model_new) ** 2).sum((0, 2))
        better = cost_new < cost
        n[better], a[better], cost[better] = n_new[better], a_new[better], cost_new[better]
        model[:, better], jac[:, better] = model_new[:, better], jac_new[:, better]
        t1[better], t2[better] = t1_new[better], t2_new[better]
        damping = np.where(better, np.maximum(damping / 3, 1e-9), np.minimum(damping * 10, 1e9))
    return a, n, cost


def _normal_equations(
    jac: np.ndarray, w: np.ndarray, resid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``J^T W J`` (n, p, p) and ``J^T W r`` (n, p) per pixel, as batched matrix products.

    jac : (k, n, 3, p); w : (k, n, 1); resid : (k, n, 3)
    """
    k, n, c, p = jac.shape
    j = np.ascontiguousarray(jac.transpose(1, 0, 2, 3)).reshape(n, k * c, p)
    wj = j * np.broadcast_to(w, (k, n, c)).transpose(1, 0, 2).reshape(n, k * c, 1)
    r = resid.transpose(1, 0, 2).reshape(n, k * c, 1)
    return np.swapaxes(wj, 1, 2) @ j, (np.swapaxes(wj, 1, 2) @ r)[..., 0]


def _solve_normals(values, weight, geo, n0, intens, ambient, lobe, iterations, starts=None):
    """Best of Gauss-Newton from the range normal and from linear photometric stereo."""
    if starts is None:
        starts = (n0, _linear_normals(values, weight, geo, intens))
    best = None
    for start in starts:
        a, n, cost = _gauss_newton(values, weight, geo, start, intens, ambient, lobe, iterations)
        if best is None:
            best = [a, n, cost]
        else:
            b = cost < best[2]
            best[0][b], best[1][b], best[2][b] = a[b], n[b], cost[b]
    return best


def _take(geo: _Geometry, sel) -> _Geometry:
    return _Geometry(geo.directions[:, sel], geo.falloff[:, sel], geo.half[:, sel])


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

    values : (k, n, 3) normalised; weight : (k, n) 1 for usable lights
    points, normals : (n, 3) mm, unit (starting normals)
    Variable projection: each round solves every pixel for the current lobe, then takes
    one Gauss-Newton step in (strength, log shininess) on the residuals with the pixels'
    own unknowns projected out.
    """
    intens = lights.intensities[light_ids]
    ambient = np.asarray(lights.ambient, float)
    geo = _geometry(points, lights.positions[light_ids], lights.reference_distance)
    strength, shininess = float(initial.strength), float(initial.shininess)
    w = weight[..., None]
    starts = None
    for _ in range(rounds):
        lobe = SpecularLobe(strength, shininess)
        a, n, _ = _solve_normals(
            values, weight, geo, normals, intens, ambient, lobe, iterations, starts
        )
        starts = (n,)
        model, jac, _ = _model(geo, n, a, intens, ambient, lobe, jacobian=True)
        hn = np.clip(np.einsum("kni,ni->kn", geo.half, n), 1e-12, None)
        base = hn**shininess * geo.falloff
        jg = np.stack(
            [
                base[..., None] * intens[:, None, :],
                (strength * shininess * np.log(hn) * base)[..., None] * intens[:, None, :],
            ],
            axis=-1,
        )  # (k, n, 3, 2): d/d strength, d/d log shininess
        jl, jg, r = jac * w[..., None], jg * w[..., None], (values - model) * w
        jtj = np.einsum("kncp,kncq->npq", jl, jl) + 1e-12 * np.eye(5)
        x = np.linalg.solve(jtj, np.einsum("kncp,kncq->npq", jl, jg))
        pg = jg - np.einsum("kncp,npq->kncq", jl, x)
        h = np.einsum("kncp,kncq->pq", pg, pg)
        g = np.einsum("kncp,knc->p", pg, r)
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
    model, jac, (t1, t2) = _model(geo, n, a, intens, ambient, lobe, jacobian=True)
    h, _ = _normal_equations(jac, weight[..., None], values - model)
    hnn, hna, haa = h[:, :2, :2], h[:, :2, 2:], h[:, 2:, 2:]
    schur = hnn - hna @ np.linalg.solve(haa + 1e-12 * np.eye(3), np.swapaxes(hna, 1, 2))
    basis = np.stack([t1, t2], axis=-1)  # (n, 3, 2)
    cost = (weight[..., None] * (values - model) ** 2).sum((0, 2))
    return basis @ schur @ np.swapaxes(basis, 1, 2), cost


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
    intens = lights.intensities[light_ids]
    ambient = np.asarray(lights.ambient, float)
    positions = lights.positions[light_ids]
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
        v = values[:, sl]
        cos0 = np.einsum("kni,ni->kn", geo.directions, normals[sl])
        use = usable[:, sl] & ~shadowed[:, sl] & (cos0 > config.min_cos)
        hl = np.zeros_like(use)
        sh = np.zeros_like(use)
        if config.shadow_ratio > 0:
            # dark outliers first: a cast shadow the range map missed would bend a
            # photometric normal to explain it
            diffuse, _ = _shading(geo, normals[sl], SpecularLobe())
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = (v / intens[:, None, :]).mean(-1) / diffuse
            ratio = np.where(use & np.isfinite(ratio), ratio, 0.0)
            dark = use & (ratio < config.shadow_ratio * ratio.max(axis=0))
            sh |= dark
            use &= ~dark
        n_cur = normals[sl].copy()
        a_cur = np.zeros((use.shape[1], 3))
        todo = np.ones(use.shape[1], bool)
        for round_ in range(config.max_rejections + 1):
            sel = np.flatnonzero(todo & (use.sum(0) >= config.min_lights))
            if len(sel) == 0:
                break
            gsel = _take(geo, sel)
            wsel = use[:, sel].astype(float)
            if config.normals == "photometric":
                starts = None if round_ == 0 else (n_cur[sel],)
                a, n_new, _ = _solve_normals(
                    v[:, sel],
                    wsel,
                    gsel,
                    normals[sl][sel] if round_ == 0 else n_cur[sel],
                    intens,
                    ambient,
                    lobe,
                    config.iterations,
                    starts,
                )
            else:
                n_new = n_cur[sel]
                a = _linear_albedo(v[:, sel], wsel, gsel, n_new, intens, ambient, lobe)
            a_cur[sel], n_cur[sel] = a, n_new
            if round_ == config.max_rejections:
                break
            model, _, _ = _model(gsel, n_new, a, intens, ambient, lobe)
            grey_model = model.sum(-1)
            resid = (v[:, sel] - model).sum(-1)
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
        ok &= np.all(np.isfinite(a_cur), axis=1)
        if config.normals == "photometric" and ok.any():
            sel = np.flatnonzero(ok)
            wsel = use[:, sel].astype(float)
            h3, cost = _normal_information(
                v[:, sel], wsel, _take(geo, sel), n_cur[sel], a_cur[sel], intens, ambient, lobe
            )
            info[sl][sel] = h3
            sq_sum += float(cost.sum())
            n_meas += float(wsel.sum() * 3 - 5 * len(sel))
        albedo[sl][ok] = a_cur[ok]
        normal_out[sl] = np.where(ok[:, None], n_cur, normals[sl])
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
    intens = lights.intensities[light_ids]
    ambient = np.asarray(lights.ambient, float)
    for start in range(0, len(points), CHUNK):
        sl = slice(start, min(len(points), start + CHUNK))
        geo = _geometry(points[sl], lights.positions[light_ids], lights.reference_distance)
        out[sl] = _linear_albedo(
            values[:, sl], used[:, sl].astype(float), geo, normals[sl], intens, ambient, lobe
        )
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
    geo = _geometry(points, lights.positions[light_ids], lights.reference_distance)
    cos0 = np.einsum("kni,ni->kn", geo.directions, normals)
    weight = usable & (cos0 > config.min_cos)
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
