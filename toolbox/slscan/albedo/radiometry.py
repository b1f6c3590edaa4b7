"""Radiometry of the lit images: camera response normalisation and the point-light model.

Image values are brought to **normalised units**: ``DN / (2**bits - 1) / exposure``,
where ``exposure`` is the product of the capture settings recorded in the view's
``exposure`` metadata (see :func:`exposure_factor`). In these units a pixel seeing a
Lambertian surface of RGB albedo ``a`` lit by point lights reads

    v_c = a_c * (ambient_c + sum_k I_kc * max(0, n . l_k) * (d_ref / d_k)**2)
          + (specular terms, see :mod:`slscan.albedo.unshade`)

with ``l_k`` the unit vector from the surface point to light ``k``, ``d_k`` its distance
(mm), ``d_ref`` the reference distance of the light calibration and ``I_k`` the light's
RGB intensity. The light calibration (:mod:`slscan.albedo.lights`) measures ``I_k`` and
``ambient`` in the same normalised units, so a camera white level or gain that the
metadata does not record is absorbed into them, and albedo comes out on the absolute
scale of the calibration panel's known reflectance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slscan.capture.session import ImageRecord, Session, ViewRecord, linearise
from slscan.errors import SlscanError

EXPOSURE_KEYS = ("white_level", "exposure", "gain")
"""Sensor settings multiplied into the exposure factor when a view records them."""


def exposure_factor(session: Session, view: ViewRecord, *, lit: bool = True) -> float:
    """How much signal one unit of radiance gives in the lit images of ``view`` (relative),
    or in its pattern images (the white and black frames) with ``lit=False``.

    The product of ``white_level``, ``exposure`` and ``gain`` (from the view's
    ``exposure["sensor"]`` block, or the top level of ``exposure``), times
    ``lit_exposure`` when the lit images were taken with a different exposure than the
    patterns. Missing settings count as 1, so a real rig that records nothing gets 1 and
    its light calibration absorbs the camera's response.
    """
    meta = view.exposure or {}
    where = f"{session.root / 'session.json'}: view {view.name}: exposure"
    if not isinstance(meta, dict):
        raise SlscanError(f"{where}: expected a table of capture settings, got {meta!r}")
    sensor = meta.get("sensor", {})
    if not isinstance(sensor, dict):
        raise SlscanError(f"{where}.sensor: expected a table, got {sensor!r}")
    factor = 1.0
    for key in EXPOSURE_KEYS:
        value = sensor.get(key, meta.get(key, 1.0))
        factor *= _positive(value, f"{where}.{key}")
    lit_exposure = _positive(meta.get("lit_exposure", 1.0), f"{where}.lit_exposure")
    return factor * lit_exposure if lit else factor


def _positive(value, where: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise SlscanError(f"{where}: expected a number, got {value!r}") from None
    if not np.isfinite(number) or number <= 0:
        raise SlscanError(f"{where}: expected a positive number, got {value!r}")
    return number


@dataclass(frozen=True)
class LitImages:
    """The lit images of one view in normalised units.

    values : (k, h, w, 3) float32, ``DN / max / exposure`` (grey sessions repeated to RGB);
        for a camera with an sRGB response (``camera.response``) the curve is undone first
    dn_unit : one digital number of a linear camera in normalised units (an sRGB camera's
        step is smaller in the dark and larger in the highlights)
    saturated : (k, h, w) bool, a channel reached the sensor's maximum
    lights : (k,) int, the ring light of each image
    records : the image records, in the same order
    exposure : the view's exposure factor (see :func:`exposure_factor`)
    """

    values: np.ndarray
    saturated: np.ndarray
    lights: np.ndarray
    records: tuple[ImageRecord, ...]
    exposure: float
    dn_unit: float


def read_lit_images(session: Session, view: ViewRecord, *, min_images: int = 1) -> LitImages:
    """Read and normalise the lit images of ``view``.

    Raises
    ------
    SlscanError
        Fewer than ``min_images`` lit images, two images of the same light, or an
        unreadable image (naming the view or the file).
    """
    records = tuple(view.lit_images())
    if len(records) < min_images:
        raise SlscanError(
            f"{session.root / view.name}: {len(records)} lit image(s) (kind 'lit' in session.json); "
            f"albedo needs at least {min_images}"
        )
    lights = np.array([r.light for r in records], dtype=np.int64)
    if len(set(lights.tolist())) != len(lights):
        raise SlscanError(
            f"{session.root / view.name}: two lit images of the same light {lights.tolist()}"
        )
    factor = exposure_factor(session, view)
    max_value = float(2**session.bit_depth - 1)
    w, h = session.camera_size
    values = np.empty((len(records), h, w, 3), np.float32)
    saturated = np.empty((len(records), h, w), bool)
    for i, rec in enumerate(records):
        image = session.read_image(view, rec)
        if image.ndim == 2:
            image = np.repeat(image[..., None], 3, axis=2)
        saturated[i] = np.any(image >= max_value, axis=-1)
        if session.response == "linear":
            values[i] = image.astype(np.float32) * np.float32(1.0 / (max_value * factor))
        else:  # light, not the camera's tone curve: sRGB codes back to fractions of full scale
            values[i] = linearise(image, session.response) * np.float32(1.0 / factor)
    return LitImages(values, saturated, lights, records, factor, 1.0 / (max_value * factor))


def light_geometry(
    points: np.ndarray, positions: np.ndarray, reference_distance: float
) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions to the lights and inverse-square falloff.

    points : (n, 3) float64 mm, rig frame
    positions : (k, 3) float64 mm, light positions
    Returns ``directions`` (k, n, 3) unit vectors from each point to each light and
    ``falloff`` (k, n) ``(reference_distance / distance)**2``.
    """
    d = positions[:, None, :] - points[None, :, :]
    dist = np.linalg.norm(d, axis=-1)
    dist = np.maximum(dist, 1e-9)
    return d / dist[..., None], (reference_distance / dist) ** 2


def lambert_irradiance(
    points: np.ndarray,
    normals: np.ndarray,
    positions: np.ndarray,
    intensities: np.ndarray,
    reference_distance: float,
) -> np.ndarray:
    """Irradiance (k, n, 3) of each light on each surface point, normalised units.

    ``I_kc * max(0, n . l_k) * (reference_distance / d_k)**2``; shadows are not tested.

    points, normals : (n, 3) mm and unit vectors, rig frame
    positions : (k, 3) mm; intensities : (k, 3) RGB
    """
    directions, falloff = light_geometry(points, positions, reference_distance)
    cos = np.clip(np.einsum("kni,ni->kn", directions, normals), 0.0, None)
    return (cos * falloff)[..., None] * np.asarray(intensities, float)[:, None, :]
