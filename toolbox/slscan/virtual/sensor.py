"""The virtual camera's sensor: optical blur, exposure, shot and read noise, gain, quantisation."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slscan.errors import SlscanError


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
    """

    bit_depth: int = 8
    full_well: float = 20000.0
    read_noise: float = 6.0
    exposure: float = 1.0
    gain: float = 1.0
    white_level: float = 0.55
    blur_sigma: float = 0.6
    noise: bool = True

    def __post_init__(self) -> None:
        if self.bit_depth not in (8, 16):
            raise SlscanError(f"sensor bit depth must be 8 or 16, got {self.bit_depth}")
        if self.exposure <= 0 or self.gain <= 0:
            raise SlscanError("sensor exposure and gain must be positive")
        if not self.blur_sigma >= 0:
            raise SlscanError(f"sensor.blur_sigma: expected a blur of 0 px or more, got {self.blur_sigma!r}")

    @property
    def max_value(self) -> int:
        return 2**self.bit_depth - 1

    def to_dict(self) -> dict:
        return {
            "bit_depth": self.bit_depth, "full_well_e": self.full_well, "read_noise_e": self.read_noise,
            "exposure": self.exposure, "gain": self.gain, "white_level": self.white_level,
            "blur_sigma_px": self.blur_sigma, "noise": self.noise,
        }

    def optical(self, radiance: np.ndarray) -> np.ndarray:
        """Apply the lens blur to a linear radiance image (h, w, 3) float32."""
        if self.blur_sigma <= 0:
            return radiance
        return cv2.GaussianBlur(radiance, (0, 0), self.blur_sigma, borderType=cv2.BORDER_REPLICATE)

    def expose(self, radiance: np.ndarray, rng: np.random.Generator | None = None,
               *, exposure_scale: float = 1.0) -> np.ndarray:
        """Digital image (h, w, 3) uint8/uint16 from linear ``radiance`` (h, w, 3)."""
        irradiance = self.optical(radiance.astype(np.float32, copy=False))
        electrons = irradiance * np.float32(self.white_level * self.exposure * exposure_scale * self.full_well)
        if self.noise:
            rng = rng or np.random.default_rng()
            sigma = np.sqrt(np.maximum(electrons, 0) + self.read_noise**2)
            electrons = electrons + sigma * rng.standard_normal(electrons.shape, dtype=np.float32)
        dn = electrons * np.float32(self.gain * self.max_value / self.full_well)
        dn = np.clip(np.rint(dn), 0, self.max_value)
        return dn.astype(np.uint8 if self.bit_depth == 8 else np.uint16)

    def linear(self, radiance: np.ndarray, *, exposure_scale: float = 1.0) -> np.ndarray:
        """Noise-free, unquantised digital values (h, w, 3) float32, saturation not applied."""
        irradiance = self.optical(radiance.astype(np.float32, copy=False))
        return irradiance * np.float32(self.white_level * self.exposure * exposure_scale * self.gain * self.max_value)
