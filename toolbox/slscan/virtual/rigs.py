"""The virtual rig's geometry from settings (a recipe's ``[capture.rig_params]``) or from a
rig file (``slscan capture --rig RIG.json``)."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

from slscan.errors import SlscanError
from slscan.rig import Rig, default_rig


@dataclass(frozen=True)
class RigParams:
    """The parameters of :func:`slscan.rig.default_rig`; the defaults are the paper's rig."""

    camera_size: tuple[int, int] = (1440, 960)
    """Camera width and height, px (before ``camera_scale``)."""
    projector_size: tuple[int, int] = (1024, 768)
    """Projector width and height, px (before ``projector_scale``)."""
    sampling_mm: float = 0.7
    """mm per camera and projector pixel at the working distance: both focal lengths are
    ``working_distance / sampling_mm`` px (1857 px by default)."""
    working_distance: float = 1300.0
    """mm from the camera to the turntable's centre, on the camera axis; the projector is as
    far from it."""
    axes_angle_deg: float = 20.0
    """Angle between the camera's and the projector's optical axes (the projector on the
    camera's right): the triangulation angle."""
    camera_distortion: tuple[float, float, float, float, float] = (-0.06, 0.04, 0.0, 0.0, 0.0)
    """Camera lens distortion, OpenCV's (k1, k2, p1, p2, k3)."""
    lights: int = 6
    """Ring lights around the camera (for the albedo images)."""
    light_ring_radius: float = 250.0
    """Radius of the ring of lights, mm."""

    def __post_init__(self) -> None:
        for name in ("camera_size", "projector_size"):
            w, h = getattr(self, name)
            if not (8 <= w <= 20000 and 8 <= h <= 20000):
                raise SlscanError(f"{name}: expected [width, height] of 8 to 20000 px, got [{w}, {h}]")
        for name in ("sampling_mm", "working_distance", "light_ring_radius"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SlscanError(f"{name}: expected a positive number, got {value}")
        if not 1.0 <= self.axes_angle_deg <= 80.0:
            raise SlscanError(f"axes_angle_deg: expected 1 to 80 degrees (the projector must see what the "
                              f"camera sees, from aside), got {self.axes_angle_deg}")
        if not 0 <= self.lights <= 64:
            raise SlscanError(f"lights: expected 0 to 64 ring lights, got {self.lights}")

    def rig(self, *, scale: float = 1.0, projector_scale: float = 1.0) -> Rig:
        """The rig, its sensors scaled by ``scale`` (camera) and ``projector_scale``."""
        return default_rig(
            scale=scale, projector_scale=projector_scale, working_distance=self.working_distance,
            axes_angle_deg=self.axes_angle_deg, n_lights=self.lights, light_ring_radius=self.light_ring_radius,
            camera_size=self.camera_size, projector_size=self.projector_size, sampling_mm=self.sampling_mm,
            camera_distortion=self.camera_distortion,
        )


def load_rig_file(path: str | os.PathLike, *, scale: float = 1.0, projector_scale: float = 1.0) -> Rig:
    """The rig in ``path``: a JSON object as :meth:`slscan.rig.Rig.to_dict` writes it, or a
    capture session's ``session.json`` (its ``calibration``, e.g. another virtual session's
    true rig). ``scale`` and ``projector_scale`` shrink its sensors (same field of view)."""
    path = Path(path)
    if not path.is_file():
        raise SlscanError(f"{path}: rig file not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SlscanError(f"{path}: not valid JSON ({exc})") from None
    if isinstance(data, dict) and isinstance(data.get("calibration"), dict):
        data = data["calibration"]  # a session.json
    if not isinstance(data, dict):
        raise SlscanError(f"{path}: expected a rig object (camera, projector, lights, working_distance_mm)")
    try:
        rig = Rig.from_dict(data)
        rig.validate()
    except SlscanError as exc:
        raise SlscanError(f"{path}: {exc}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        raise SlscanError(f"{path}: not a rig as Rig.to_dict writes it ({exc})") from None
    if not (math.isfinite(rig.working_distance) and rig.working_distance > 0):
        raise SlscanError(f"{path}: working_distance_mm must be positive, got {rig.working_distance}")
    if scale != 1.0 or projector_scale != 1.0:
        from dataclasses import replace

        rig = replace(rig, camera=rig.camera.scaled(scale),
                      projector=type(rig.projector)(rig.projector.lens.scaled(projector_scale),
                                                    rig.projector.rig_from_projector))
    return rig
