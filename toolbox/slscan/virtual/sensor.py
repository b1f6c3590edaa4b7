"""The virtual camera's sensor: optical blur, vignetting, exposure, shot and read noise,
gain, response curve, quantisation (and the JPEG quality its captures are saved at)."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from slscan.errors import SlscanError
from slscan.virtual.effects import Effect, register

RESPONSES = ("linear", "srgb")
JPEG_QUALITY = 90  # effect ``jpeg``: a camera's usual "fine" JPEG


@dataclass(frozen=True)
class Sensor:
    """A linear sensor with photon (shot) noise, read noise and an ADC.

    bit_depth : {8, 16}
    full_well : electrons at which a pixel saturates
    read_noise : electrons RMS
    exposure : light collected, relative; at 1.0 a white Lambertian surface facing the
        projector at the working distance under full white reaches ``white_level``
    gain : analogue gain applied after collection (amplifies signal and noise)
    white_level : fraction of full scale reached by that reference white at exposure 1
    blur_sigma : camera blur (Gaussian sigma), camera px: everything between the lens and
        the image but the pixel's own area (the renderer already integrates the projector
        light over each pixel's footprint). The default 0.6 is a 1440 × 960 consumer
        camera of 9 µm pixel pitch (a 13 × 8.6 mm sensor; f = 1857 px is a 16.7 mm lens)
        at f/8, focused at the working distance. In quadrature: diffraction (Airy, 550 nm:
        σ = 0.42 λ N = 1.85 µm = 0.21 px); lens aberrations, MTF 0.64 at the pixel
        Nyquist frequency (55 lp/mm) as a consumer lens stopped down has (σ = √(-2 ln
        0.64) / π = 0.30 px); the anti-aliasing filter, a birefringent plate splitting
        each point into spots 0.8 px apart (σ = 0.4 px); demosaicing of the Bayer mosaic,
        between an edge-aware method (≈ 0 across an edge) and bilinear (green 0.5 px):
        0.25 px. √(0.21² + 0.30² + 0.40² + 0.25²) = 0.60 px. Depth of field adds little
        at f/8: 200 mm either side of focus blurs by 3.6–4.9 µm across (σ 0.10–0.14 px).
    noise : False renders the noise-free expectation (still quantised)
    response : {"linear", "srgb"}: the camera's tone curve between exposure and
        quantisation: "linear" (RAW), or the sRGB OETF (IEC 61966-2-1) on the fraction of
        full scale, as a camera that shoots JPEG applies it (effect ``tone``)
    vignetting : strength of the lens's cos⁴ light falloff: a pixel whose ray is at angle θ
        from the optical axis receives ``1 - vignetting * (1 - cos⁴ θ)`` of the light;
        0: none, 1: the full cos⁴ law of the camera's field of view (effect ``vignetting``)
    jpeg_quality : 0: captures are lossless (PNG); 1–100: the camera saves them as JPEG at
        this quality (session files ``.jpg``, ``camera.lossy`` true; effect ``jpeg``: 90)
    """

    bit_depth: int = 8
    full_well: float = 20000.0
    read_noise: float = 6.0
    exposure: float = 1.0
    gain: float = 1.0
    white_level: float = 0.55
    blur_sigma: float = 0.6
    noise: bool = True
    response: str = "linear"
    vignetting: float = 0.0
    jpeg_quality: int = 0

    def __post_init__(self) -> None:
        if self.bit_depth not in (8, 16):
            raise SlscanError(f"sensor bit depth must be 8 or 16, got {self.bit_depth}")
        if self.exposure <= 0 or self.gain <= 0:
            raise SlscanError("sensor exposure and gain must be positive")
        if not self.blur_sigma >= 0:
            raise SlscanError(f"sensor.blur_sigma: expected a blur of 0 px or more, got {self.blur_sigma!r}")
        if self.response not in RESPONSES:
            raise SlscanError(f"sensor.response: expected 'linear' or 'srgb', got {self.response!r}")
        v = self.vignetting
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 <= v <= 1):
            raise SlscanError(f"sensor.vignetting: expected a strength from 0 (none) to 1 (the full cos^4 law), "
                              f"got {v!r}")
        q = self.jpeg_quality
        if not (isinstance(q, int) and not isinstance(q, bool) and 0 <= q <= 100):
            raise SlscanError(f"sensor.jpeg_quality: expected 0 (lossless PNG) or a JPEG quality 1-100, got {q!r}")
        if q and self.bit_depth != 8:
            raise SlscanError(f"sensor.jpeg_quality: JPEG captures are 8 bit, but sensor.bit_depth is "
                              f"{self.bit_depth} (set jpeg_quality = 0 or bit_depth = 8)")

    @property
    def max_value(self) -> int:
        return 2**self.bit_depth - 1

    def to_dict(self) -> dict:
        return {
            "bit_depth": self.bit_depth, "full_well_e": self.full_well, "read_noise_e": self.read_noise,
            "exposure": self.exposure, "gain": self.gain, "white_level": self.white_level,
            "blur_sigma_px": self.blur_sigma, "noise": self.noise, "response": self.response,
            "vignetting": self.vignetting, "jpeg_quality": self.jpeg_quality,
        }

    def optical(self, radiance: np.ndarray) -> np.ndarray:
        """Apply the lens blur to a linear radiance image (h, w, 3) float32."""
        if self.blur_sigma <= 0:
            return radiance
        return cv2.GaussianBlur(radiance, (0, 0), self.blur_sigma, borderType=cv2.BORDER_REPLICATE)

    def vignette(self, irradiance: np.ndarray, camera) -> np.ndarray:
        """``irradiance`` (h, w, 3) times the lens's light falloff for ``camera``
        (:class:`~slscan.rig.PinholeModel`); unchanged when ``vignetting`` is 0."""
        if self.vignetting == 0:
            return irradiance
        if camera is None:
            raise SlscanError("sensor.vignetting: the falloff needs the camera's intrinsics (pass camera=)")
        falloff = 1 - np.float32(self.vignetting) * (1 - cos4_map(camera))
        return irradiance * falloff[..., None]

    def expose(self, radiance: np.ndarray, rng: np.random.Generator | None = None,
               *, exposure_scale: float = 1.0, camera=None) -> np.ndarray:
        """Digital image (h, w, 3) uint8/uint16 from linear ``radiance`` (h, w, 3).

        camera : the camera's :class:`~slscan.rig.PinholeModel`, needed for ``vignetting``
        """
        irradiance = self.vignette(self.optical(radiance.astype(np.float32, copy=False)), camera)
        electrons = irradiance * np.float32(self.white_level * self.exposure * exposure_scale * self.full_well)
        if self.noise:
            rng = rng or np.random.default_rng()
            sigma = np.sqrt(np.maximum(electrons, 0) + self.read_noise**2)
            electrons = electrons + sigma * rng.standard_normal(electrons.shape, dtype=np.float32)
        if self.response == "srgb":
            dn = srgb_oetf(np.clip(electrons * np.float32(self.gain / self.full_well), 0, 1)) * np.float32(self.max_value)
        else:
            dn = electrons * np.float32(self.gain * self.max_value / self.full_well)
        dn = np.clip(np.rint(dn), 0, self.max_value)
        return dn.astype(np.uint8 if self.bit_depth == 8 else np.uint16)

    def linear(self, radiance: np.ndarray, *, exposure_scale: float = 1.0) -> np.ndarray:
        """Noise-free, unquantised digital values (h, w, 3) float32, saturation not applied
        (the linear response, without vignetting)."""
        irradiance = self.optical(radiance.astype(np.float32, copy=False))
        return irradiance * np.float32(self.white_level * self.exposure * exposure_scale * self.gain * self.max_value)


def srgb_oetf(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear ``x`` in [0, 1], float32."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.0031308, x * np.float32(12.92),
                    np.float32(1.055) * np.power(np.maximum(x, 0.0031308), np.float32(1 / 2.4)) - np.float32(0.055))


@functools.lru_cache(maxsize=8)
def cos4_map(camera) -> np.ndarray:
    """cos⁴ of each pixel centre's ray angle from ``camera``'s optical axis (h, w) float32."""
    from slscan.virtual.render import camera_rays

    rays = camera_rays(camera)[: camera.height, : camera.width]
    cos = 1.0 / np.linalg.norm(rays, axis=-1)  # rays have z = 1
    out = (cos**4).astype(np.float32)
    out.flags.writeable = False
    return out


def jpeg_round_trip(image: np.ndarray, quality: int) -> np.ndarray:
    """``image`` (h, w, 3) uint8 RGB as it reads back from a JPEG saved at ``quality``
    (the bytes :func:`slscan.fsio.write_jpeg` writes)."""
    from slscan.fsio import decode_image, encode_jpeg

    return decode_image(encode_jpeg(image, quality))


def _vignetting_on(optics, sensor: Sensor, working_distance: float):
    return optics, sensor if sensor.vignetting else dataclasses.replace(sensor, vignetting=1.0)


def _jpeg_on(optics, sensor: Sensor, working_distance: float):
    return optics, sensor if sensor.jpeg_quality else dataclasses.replace(sensor, jpeg_quality=JPEG_QUALITY)


register(Effect(
    "vignetting", "camera lens vignetting: the cos^4 light falloff towards the image corners",
    "natural vignetting, cos^4 law: Hecht, Optics (5th ed.), sec. 6.3; Kang & Weiss, 'Can we calibrate a "
    "camera using an image of a flat, textureless Lambertian surface?', ECCV 2000", _vignetting_on))
register(Effect(
    "jpeg", "JPEG captures: the camera saves each image as JPEG at quality 90 (session files .jpg, "
    "camera.lossy true)",
    "ITU-T T.81 / ISO 10918-1 (JPEG baseline), as encoded by libjpeg through OpenCV", _jpeg_on))
