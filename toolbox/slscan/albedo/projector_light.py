"""Albedo with the projector as the calibrated light: colour from any rig, no ring lights.

Every range map already comes with a white and a black frame of the projector, taken from
the same viewpoint as the patterns. The projector is a calibrated point light: its centre
is known from the projector calibration, and its emitted radiance is uniform over its
pixels unless a flat-field map was measured (:class:`~slscan.albedo.lights.ProjectorLight`).
Per camera pixel that sees the range map (ray cast from the camera, so the colour is
registered with the geometry by construction), in normalised units
(:mod:`slscan.albedo.radiometry`, the camera response undone, the pattern exposure
divided out)::

    albedo_c = (white_c - black_c) / (P_c * flat(u, v) * cos(theta) * (d_ref / d)**2)

``theta`` the angle between the range map's normal and the direction to the projector's
centre, ``d`` the distance to it, ``(u, v)`` where the point falls in the projector. The
black frame removes the ambient light (and the projector's black level). Pixels are left
out, as the 6-light un-shading leaves out lights, where the projector cannot light them
(outside its frame, or a shadow ray to its centre meets the range map), where it grazes
the surface (``cos(theta) < min_cos``), where the white frame is saturated or too dark,
next to a depth jump, and optionally near the mirror direction (possible highlights).

This is how commercial structured-light scanners with one camera (DAVID / HP 3D Scan)
colour their scans. Compared with the ring of lights it has one light, so it cannot
solve a finer normal from the images nor tell a highlight from paint: normal noise of the
range map goes straight into the albedo (so the normal is that of a plane fitted over as
wide a window as the surface stays planar within the range map's noise,
:func:`adaptive_normals`), and a glossy surface's highlight near the mirror direction
stays in it (``projector_highlight_deg`` leaves those pixels out).

:func:`calibrate_projector_light` measures ``P`` (and a coarse flat field) from a matte
panel of known reflectance at known poses: the same panel session that calibrates the
ring lights, whose views carry white and black frames.

References
----------
.. [1] Rocchini, Cignoni, Montani, Pingi, Scopigno, "A low cost 3D scanner based on
   structured light", Computer Graphics Forum 20(3), Eurographics 2001, §3.4 (the
   Lambertian model and the rejection of shadowed and saturated samples).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from slscan.albedo.lights import LightCalibration, MattePanel, PanelFit, ProjectorLight, panel_pixels, panel_plane
from slscan.albedo.photometric import AlbedoConfig, SpecularLobe
from slscan.albedo.radiometry import exposure_factor
from slscan.albedo.surface import occluded, rasterise
from slscan.capture.session import Session, ViewRecord, linearise
from slscan.decode.rangemap import RangeMap
from slscan.errors import SlscanError

log = logging.getLogger(__name__)

PROJECTOR_LIGHT_ID = -1
"""The "light index" of the projector in a view's result (``light_ids``), beside ring lights 0..k-1."""


@dataclass(frozen=True)
class FlatFrames:
    """A view's white and black frames in normalised units.

    white, black : (h, w, 3) float32 ``DN / max / exposure`` (grey repeated to RGB), the
        camera response undone; black is zeros when the pattern set has no black frame
    saturated : (h, w) bool, a channel of the white frame at the sensor's maximum
    dn_unit : one 8-bit digital number in these units (the dark-signal threshold's unit)
    white_frame : the white frame's record (file and frame index, for messages and logging)
    has_black : the session has a black frame (ambient subtracted)
    """

    white: np.ndarray
    black: np.ndarray
    saturated: np.ndarray
    dn_unit: float
    white_file: str
    has_black: bool


def flat_frame_records(session: Session, view: ViewRecord):
    """The records of ``view``'s all-white frame and all-black frame (None when the
    pattern set has none), from the pattern set's flat frames."""
    white = black = None
    for p in session.patterns:
        if p.family != "flat":
            continue
        value = list(p.params.get("value", []))
        if value == [255, 255, 255] and white is None:
            white = p.id
        elif value == [0, 0, 0] and black is None:
            black = p.id
    if white is None:
        raise SlscanError(
            f"{session.root}: the pattern set has no all-white frame; the projector-light albedo needs one"
        )
    try:
        return view.image_for(white), (view.image_for(black) if black is not None else None)
    except SlscanError:
        raise
    except Exception as exc:  # a view without one of its frames
        raise SlscanError(f"{session.root / view.name}: {exc}") from None


def read_flat_frames(session: Session, view: ViewRecord) -> FlatFrames:
    """Read and normalise ``view``'s white and black frames (see :class:`FlatFrames`)."""
    white_rec, black_rec = flat_frame_records(session, view)
    factor = exposure_factor(session, view, lit=False)
    max_value = float(2**session.bit_depth - 1)

    def read(rec) -> tuple[np.ndarray, np.ndarray]:
        image = session.read_image(view, rec)
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        saturated = np.any(image >= max_value, axis=-1)
        if session.response == "linear":
            values = image.astype(np.float32) * np.float32(1.0 / (max_value * factor))
        else:
            values = linearise(image, session.response) * np.float32(1.0 / factor)
        return values, saturated

    white, saturated = read(white_rec)
    black = read(black_rec)[0] if black_rec is not None else np.zeros_like(white)
    return FlatFrames(white, black, saturated, 1.0 / (255.0 * factor), white_rec.file, black_rec is not None)


def projector_light_of(session: Session, lights: LightCalibration | None) -> ProjectorLight:
    """The projector light to use: the light calibration's, else the nominal one (uniform,
    intensity 1 at the rig's working distance: albedo relative to the projector's white)."""
    if lights is not None and lights.projector is not None:
        return lights.projector
    distance = session.calibration.working_distance if session.calibration is not None else 1300.0
    return ProjectorLight(reference_distance=distance)


def projector_geometry(
    points: np.ndarray, normals: np.ndarray, centre: np.ndarray, reference_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cosine of incidence (n,), inverse-square falloff ``(d_ref / d)**2`` (n,) and unit
    directions to the projector (n, 3), for points and unit normals (n, 3) mm, rig frame."""
    d = np.asarray(centre, float)[None] - points
    dist = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
    direction = d / dist[:, None]
    cos = np.einsum("ij,ij->i", direction, normals)
    return cos, (reference_distance / dist) ** 2, direction


def projector_albedo_view(
    session: Session,
    view: ViewRecord | str,
    range_map: RangeMap,
    light: ProjectorLight,
    config: AlbedoConfig | None = None,
    *,
    range_map_source: str = "range map",
):
    """Albedo of one view from its white and black frames, the projector as the light.

    range_map : the view's range map (rig frame, mm)
    light : the projector light (:func:`projector_light_of`)
    Returns a :class:`~slscan.albedo.unshade.ViewAlbedo` of the same form as the ring
    lights' (one "light", :data:`PROJECTOR_LIGHT_ID`: ``shadow`` its projector shadow and
    grazing pixels, ``highlight`` its saturated and mirror-direction pixels).
    """
    import time

    from slscan.albedo.unshade import ViewAlbedo, _check_range_map, mixed_pixels, vertex_albedo

    config = config or AlbedoConfig()
    view = session.view(view) if isinstance(view, str) else view
    rig = session.calibration
    if rig is None:
        raise SlscanError(f"{session.root}: the session has no calibration (camera and projector are needed)")
    _check_range_map(range_map, view, range_map_source)
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    frames = read_flat_frames(session, view)
    if not frames.has_black:
        log.warning("%s: the pattern set has no black frame: ambient light is not subtracted", view.name)
    seconds["read"] = time.perf_counter() - t
    t = time.perf_counter()
    surface = rasterise(range_map, rig.camera)
    h, w = surface.hit.shape
    rows, cols = np.nonzero(surface.hit & ~mixed_pixels(surface, config.edge_px))
    points = surface.points[rows, cols]
    normals = surface.normals[rows, cols]
    if config.projector_normal_window_px > 1:
        fitted = adaptive_normals(surface.points, surface.hit, config.projector_normal_window_px)[rows, cols]
        ok = np.all(np.isfinite(fitted), axis=1)
        normals = np.where(ok[:, None], fitted, normals)
    centre = rig.projector.center
    cos, falloff, direction = projector_geometry(points, normals, centre, light.reference_distance)
    uv = rig.projector.project(points)
    pw, ph = rig.projector.lens.width, rig.projector.lens.height
    in_frame = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= pw - 0.5)
    in_frame &= (uv[:, 1] >= -0.5) & (uv[:, 1] <= ph - 0.5)
    shadowed = ~in_frame | (cos <= 0)
    cast = occluded(range_map, points[~shadowed], normals[~shadowed], centre[None], offset=config.shadow_offset_mm)
    shadowed[np.flatnonzero(~shadowed)[cast[0]]] = True
    grazing = ~shadowed & (cos < config.min_cos)
    seconds["geometry"] = time.perf_counter() - t
    t = time.perf_counter()
    signal = (frames.white[rows, cols] - frames.black[rows, cols]).astype(np.float64)
    luminance = signal @ np.array([0.2126, 0.7152, 0.0722])
    dark = luminance < config.projector_min_signal_dn * frames.dn_unit
    saturated = frames.saturated[rows, cols]
    highlight = saturated.copy()
    if config.projector_highlight_deg > 0:
        eye = -points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-9)
        half = direction + eye
        half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
        highlight |= np.einsum("ij,ij->i", half, normals) > np.cos(np.radians(config.projector_highlight_deg))
    flat = light.flat_at(uv, (pw, ph)) if light.flat_field is not None else np.ones(len(rows))
    irradiance = np.clip(cos, 1e-6, None) * falloff * flat
    ok = ~shadowed & ~grazing & ~highlight & ~dark
    albedo_px = signal / (irradiance[:, None] * np.asarray(light.intensity, float)[None])
    ok &= np.all(np.isfinite(albedo_px), axis=1)
    seconds["solve"] = time.perf_counter() - t
    albedo = np.full((h, w, 3), np.nan, np.float32)
    albedo[rows[ok], cols[ok]] = albedo_px[ok]
    valid = np.zeros((h, w), bool)
    valid[rows[ok], cols[ok]] = True
    normal = np.full((h, w, 3), np.nan, np.float32)
    normal[rows, cols] = normals
    shadow_img = np.zeros((1, h, w), bool)
    shadow_img[0, rows, cols] = shadowed | grazing
    highlight_img = np.zeros((1, h, w), bool)
    highlight_img[0, rows, cols] = highlight
    per_vertex = vertex_albedo(range_map, albedo, valid, rig.camera)
    if not valid.any():
        log.info("%s: no pixel is lit by the projector well enough; the albedo image is empty", view.name)
    return ViewAlbedo(
        view.name,
        albedo,
        valid,
        valid.astype(np.uint8),
        normal,
        shadow_img,
        highlight_img,
        np.array([PROJECTOR_LIGHT_ID]),
        per_vertex,
        surface,
        SpecularLobe(),
        seconds,
    )


def window_normals(points: np.ndarray, hit: np.ndarray, window: int, *, residual: bool = False):
    """Normals (h, w, 3) of the planes fitted (least squares, PCA) to the points (h, w, 3)
    mm of the ``hit`` pixels in a ``window`` x ``window`` neighbourhood of each pixel,
    turned towards the camera; NaN where fewer than 6 points are in the window. With
    ``residual``, also the mean squared distance (h, w) mm² of the window's points to
    their plane (the covariance's smallest eigenvalue; NaN likewise)."""
    import cv2

    h, w = hit.shape
    wgt = hit.astype(np.float64)
    # centred on the surface's mean point: the second moments then keep their precision
    origin = points[hit].mean(0) if hit.any() else np.zeros(3)
    p = np.where(hit[..., None], points - origin, 0.0)

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(a, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)

    n = box(wgt)
    mean = np.stack([box(p[..., i]) for i in range(3)], axis=-1) / np.maximum(n, 1)[..., None]
    cov = np.empty((h, w, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            second = box(p[..., i] * p[..., j]) / np.maximum(n, 1)
            cov[..., i, j] = cov[..., j, i] = second - mean[..., i] * mean[..., j]
    good = (n >= 6) & hit
    normals = np.full((h, w, 3), np.nan)
    spread = np.full((h, w), np.nan)
    if good.any():
        values, vectors = np.linalg.eigh(cov[good])
        v = vectors[..., 0]  # the smallest eigenvalue's
        v[np.einsum("ij,ij->i", v, points[good]) > 0] *= -1
        normals[good] = v
        spread[good] = np.maximum(values[:, 0], 0.0)
    return (normals, spread) if residual else normals


ADAPTIVE_WINDOWS = (5, 9, 21, 41)
"""Window sizes (px) :func:`adaptive_normals` chooses from, up to the configured largest."""
NOISE_FACTOR = 4.0
"""A window is planar enough while its fit residual is under this many times the noise's."""


def adaptive_normals(points: np.ndarray, hit: np.ndarray, largest: int) -> np.ndarray:
    """Normals (h, w, 3) of the largest window (of :data:`ADAPTIVE_WINDOWS`, up to
    ``largest`` px) in which the range surface is still a plane within its noise.

    The noise is the range map's own: the median plane-fit residual over the smallest
    window. A pixel takes the normal of the largest window whose residual is at most
    :data:`NOISE_FACTOR` times that; where even the smallest exceeds it (relief, a
    crease), the smallest window's. A noisy flat board so gets the widest plane, a clean
    carved relief keeps its detail.
    """
    windows = [w for w in ADAPTIVE_WINDOWS if w <= largest] or [largest]
    out, spread = window_normals(points, hit, windows[0], residual=True)
    finite = np.isfinite(spread)
    noise = float(np.median(spread[finite])) if finite.any() else 0.0
    planar = finite.copy()  # still planar at every window so far
    for window in windows[1:]:
        normals, spread = window_normals(points, hit, window, residual=True)
        planar &= np.isfinite(spread) & (spread <= NOISE_FACTOR * noise)
        out = np.where(planar[..., None], normals, out)
    return out


# --- calibration from a matte panel ---------------------------------------------------------


def calibrate_projector_light(
    session: Session,
    panel: MattePanel,
    *,
    fits: dict[str, PanelFit] | None = None,
    grid: tuple[int, int] | None = (8, 6),
    max_samples_per_view: int = 20000,
    min_cos: float = 0.5,
) -> ProjectorLight:
    """Measure the projector's white as a light from a matte panel at known poses.

    session : a panel session whose views have white (and black) frames, e.g. the ring
        lights' panel session (``slscan capture-lights`` or a real one through
        ``slscan scan``)
    panel : the panel (its reflectance sets the absolute scale)
    fits : the panel's plane per view name fitted to its range map
        (:func:`slscan.albedo.lights.fit_panel_plane`), for views without a recorded pose
    grid : (columns, rows) of the flat-field grid over the projector's frame, or None for
        a uniform projector; cells seen by fewer than 50 panel pixels are set to 1

    Every panel pixel the projector lights gives ``P_c * flat = (white - black) / (albedo
    * cos * falloff)``; ``P`` is the median of those over all views (robust to the odd
    saturated or shadowed pixel), the flat field the median per cell over ``P``,
    normalised to median 1.
    """
    rig = session.calibration
    if rig is None:
        raise SlscanError(f"{session.root}: the session has no calibration (camera and projector are needed)")
    cam = rig.camera
    albedo = np.asarray(panel.albedo, float)
    ref = rig.working_distance
    ratios, uvs = [], []
    for view in session.views:
        fit = (fits or {}).get(view.name)
        pose = fit.rig_from_panel if fit is not None else None
        centre_pt, normal = panel_plane(session, view, panel, rig_from_panel=pose)
        frames = read_flat_frames(session, view)
        mask = panel_pixels(session, view, panel, rig_from_panel=pose, fit=fit)
        rows, cols = np.nonzero(mask)
        if len(rows) > max_samples_per_view:
            pick = np.linspace(0, len(rows) - 1, max_samples_per_view).astype(np.int64)
            rows, cols = rows[pick], cols[pick]
        rays = cam.rays_local(np.stack([cols, rows], axis=1).astype(float))
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (normal @ centre_pt) / (rays @ normal)
        points = rays * t[:, None]
        normals = np.broadcast_to(normal, points.shape)
        cos, falloff, _ = projector_geometry(points, normals, rig.projector.center, ref)
        uv = rig.projector.project(points)
        pw, ph = rig.projector.lens.width, rig.projector.lens.height
        ok = (cos >= min_cos) & (uv[:, 0] >= 0) & (uv[:, 0] <= pw - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= ph - 1)
        ok &= ~frames.saturated[rows, cols]
        signal = (frames.white[rows, cols] - frames.black[rows, cols]).astype(np.float64)
        ok &= signal.min(axis=1) > 4 * frames.dn_unit
        ratios.append(signal[ok] / (albedo * (cos * falloff)[ok, None]))
        uvs.append(uv[ok])
    ratio = np.concatenate(ratios) if ratios else np.zeros((0, 3))
    uv = np.concatenate(uvs) if uvs else np.zeros((0, 2))
    if len(ratio) < 100:
        raise SlscanError(
            f"{session.root}: only {len(ratio)} panel pixels lit by the projector (unsaturated, not grazing); "
            "the projector light needs the panel in the projected area"
        )
    intensity = np.median(ratio, axis=0)
    flat = None
    if grid is not None:
        gw, gh = grid
        cell_x = np.clip((uv[:, 0] + 0.5) * gw / pw, 0, gw - 1e-9).astype(int)
        cell_y = np.clip((uv[:, 1] + 0.5) * gh / ph, 0, gh - 1e-9).astype(int)
        lum = (ratio / intensity).mean(axis=1)
        cells = np.ones((gh, gw))
        for j in range(gh):
            for i in range(gw):
                sel = (cell_x == i) & (cell_y == j)
                if sel.sum() >= 50:
                    cells[j, i] = np.median(lum[sel])
        cells /= np.median(cells)
        intensity = intensity * np.median(lum)  # the flat field's median is 1
        flat = tuple(tuple(float(x) for x in row) for row in cells)
    return ProjectorLight(
        tuple(float(i) for i in intensity), float(ref), flat, f"panel session {session.root.resolve()}"
    )

