"""The virtual rig's geometry from settings (a recipe's ``[capture.rig_params]``) or from a
rig file (``slscan capture --rig RIG.json``)."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.rig import Projector, Rig, default_rig, look_at


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
    projector_distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    """Projector lens distortion, OpenCV's (k1, k2, p1, p2, k3); none by default (kamino410's
    projector, calibrated: about (-0.11, 0.15, 0.006, -0.001, 0))."""
    baseline_direction_deg: float = 0.0
    """Where the projector sits seen from the camera, degrees in the camera's image plane from
    its right (+x) towards up (-y): 0 beside the camera on its right (the paper's rig), 90
    above it (its columns then nearly contain the camera centre: rows pin depth). The
    projector is turned to look at the same point, its columns kept upright."""
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
        if len(self.projector_distortion) != 5 or not all(math.isfinite(v) for v in self.projector_distortion):
            raise SlscanError(f"projector_distortion: expected 5 finite numbers (k1, k2, p1, p2, k3), "
                              f"got {list(self.projector_distortion)}")
        if not (math.isfinite(self.baseline_direction_deg) and -180 <= self.baseline_direction_deg <= 360):
            raise SlscanError(f"baseline_direction_deg: expected -180 to 360 degrees, got {self.baseline_direction_deg}")
        if not 0 <= self.lights <= 64:
            raise SlscanError(f"lights: expected 0 to 64 ring lights, got {self.lights}")

    def rig(self, *, scale: float = 1.0, projector_scale: float = 1.0) -> Rig:
        """The rig, its sensors scaled by ``scale`` (camera) and ``projector_scale``."""
        from dataclasses import replace

        rig = default_rig(
            scale=scale, projector_scale=projector_scale, working_distance=self.working_distance,
            axes_angle_deg=self.axes_angle_deg, n_lights=self.lights, light_ring_radius=self.light_ring_radius,
            camera_size=self.camera_size, projector_size=self.projector_size, sampling_mm=self.sampling_mm,
            camera_distortion=self.camera_distortion,
        )
        if not any(self.projector_distortion) and self.baseline_direction_deg == 0:
            return rig
        lens = replace(rig.projector.lens, dist=tuple(float(v) for v in self.projector_distortion))
        pose = rig.projector.rig_from_projector
        if self.baseline_direction_deg != 0:
            a, phi = math.radians(self.axes_angle_deg), math.radians(self.baseline_direction_deg)
            target = np.array([0.0, 0.0, self.working_distance])
            eye = target + self.working_distance * np.array(
                [math.sin(a) * math.cos(phi), -math.sin(a) * math.sin(phi), -math.cos(a)])
            pose = look_at(eye, target)
        return replace(rig, projector=Projector(lens, pose))


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
    except (TypeError, ValueError, AttributeError, OverflowError, KeyError, IndexError) as exc:
        reason = f"missing {exc.args[0]!r}" if isinstance(exc, KeyError) and exc.args else str(exc)
        raise SlscanError(f"{path}: not a rig as Rig.to_dict writes it ({reason})") from None
    if not (math.isfinite(rig.working_distance) and rig.working_distance > 0):
        raise SlscanError(f"{path}: working_distance_mm must be positive, got {rig.working_distance}")
    if scale != 1.0 or projector_scale != 1.0:
        from dataclasses import replace

        rig = replace(rig, camera=rig.camera.scaled(scale),
                      projector=type(rig.projector)(rig.projector.lens.scaled(projector_scale),
                                                    rig.projector.rig_from_projector))
    return rig
