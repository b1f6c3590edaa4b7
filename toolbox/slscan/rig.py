"""Geometric models of a structured-light rig: camera, projector, ring lights.

Conventions (see ``docs/capture-session.md``, section Conventions):

- Lengths in millimetres. The **rig frame** is the camera frame: origin at the camera's
  centre of projection, x right, y down, z forward (OpenCV).
- Pixel coordinates follow OpenCV: the centre of pixel ``(col, row)`` is at ``(col, row)``.
- Poses are 4×4 matrices named ``a_from_b``: ``p_a = a_from_b @ p_b``.
- Distortion coefficients follow OpenCV's order ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from slscan.errors import SlscanError

# --- small geometry helpers -------------------------------------------------------------


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, -1.0, 0.0)) -> np.ndarray:
    """Pose ``rig_from_device`` (4, 4) of a device at ``eye`` whose +z looks at ``target``.

    ``up`` is the rig direction that should appear up in the device image (-y in OpenCV).
    """
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    if np.linalg.norm(x) < 1e-9:
        raise SlscanError("look_at: viewing direction is parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def rotation_about_axis(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation matrix (3, 3) for ``angle_rad`` about the unit ``axis`` (Rodrigues)."""
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1 - math.cos(angle_rad)) * (k @ k)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 ``pose`` to ``points`` (..., 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def _as_pose(value: Any, what: str) -> np.ndarray:
    pose = np.asarray(value, dtype=float)
    if pose.shape != (4, 4) or not np.allclose(pose[3], [0, 0, 0, 1]):
        raise SlscanError(f"{what}: expected a 4x4 rigid transform, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise SlscanError(f"{what}: the transform holds non-finite numbers (NaN or inf)")
    r = pose[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise SlscanError(f"{what}: the 3x3 part is not a rotation")
    return pose


# --- lens model -----------------------------------------------------------------------------


def distort(xn: np.ndarray, yn: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apply OpenCV's radial-tangential model to normalised coordinates ``xn, yn``."""
    k1, k2, p1, p2, k3 = dist
    r2 = xn * xn + yn * yn
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return xd, yd


def undistort(
    xd: np.ndarray, yd: np.ndarray, dist: np.ndarray, iterations: int = 30, tol: float = 1e-14
):
    """Invert :func:`distort` by fixed-point iteration; exact to ~1e-12 for lens-like models.

    Stops after ``iterations`` or once no coordinate moved by more than ``tol`` (normalised
    units: ~1e-11 px at a 1000 px focal length), typically after a third of them.
    """
    if not np.any(dist):
        return xd.copy(), yd.copy()
    xn, yn = xd.copy(), yd.copy()
    for _ in range(iterations):
        xe, ye = distort(xn, yn, dist)
        ex, ey = xe - xd, ye - yd
        xn -= ex
        yn -= ey
        if ex.size == 0 or max(np.abs(ex).max(), np.abs(ey).max()) <= tol:
            break
    return xn, yn


@dataclass(frozen=True)
class PinholeModel:
    """A pinhole device with OpenCV intrinsics and distortion.

    width, height : int, px
    fx, fy, cx, cy : float, px
    dist : (5,) float, OpenCV ``(k1, k2, p1, p2, k3)``
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise SlscanError(f"device size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise SlscanError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if len(self.dist) != 5:
            raise SlscanError(f"expected 5 distortion coefficients, got {len(self.dist)}")
        if not np.isfinite([self.fx, self.fy, self.cx, self.cy, *self.dist]).all():
            raise SlscanError(
                f"intrinsics must be finite numbers, got fx={self.fx}, fy={self.fy}, cx={self.cx}, "
                f"cy={self.cy}, distortion {tuple(self.dist)}"
            )

    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix (3, 3)."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=float)

    def project_local(self, points: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) of ``points`` (..., 3) given in the device's own frame (mm)."""
        z = points[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xn, yn = points[..., 0] / z, points[..., 1] / z
        xd, yd = distort(xn, yn, self.dist_array)
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)

    def rays_local(self, pixels: np.ndarray) -> np.ndarray:
        """Ray directions (..., 3) with z = 1 in the device frame through ``pixels`` (..., 2)."""
        xd = (pixels[..., 0] - self.cx) / self.fx
        yd = (pixels[..., 1] - self.cy) / self.fy
        xn, yn = undistort(xd, yd, self.dist_array)
        return np.stack([xn, yn, np.ones_like(xn)], axis=-1)

    def scaled(self, factor: float) -> PinholeModel:
        """The same lens on a sensor with ``factor`` times the pixels per side."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return replace(
            self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5, cy=(self.cy + 0.5) * sy - 0.5,
        )

    def to_dict(self) -> dict:
        return {
            "width": self.width, "height": self.height,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "dist": list(self.dist),
        }

    @classmethod
    def from_dict(cls, d: dict, what: str = "device") -> PinholeModel:
        try:
            return cls(
                width=int(d["width"]), height=int(d["height"]),
                fx=float(d["fx"]), fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
                dist=tuple(float(v) for v in d.get("dist", (0, 0, 0, 0, 0))),
            )
        except KeyError as exc:
            raise SlscanError(f"{what}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise SlscanError(f"{what}: {exc}") from None


@functools.lru_cache(maxsize=4)
def pixel_rays(camera: PinholeModel) -> np.ndarray:
    """Unit ray directions (h, w, 3) through the pixel centres, in the camera's own frame
    (the rig frame for the rig's camera), distortion undone.

    Cached per camera model; the array is read-only.
    """
    grid = np.stack(
        np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float)),
        axis=-1,
    )
    rays = camera.rays_local(grid)
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    rays.flags.writeable = False
    return rays


@dataclass(frozen=True, eq=False)
class Projector:
    """The projector as an inverse pinhole camera placed in the rig frame.

    lens : PinholeModel, projector pixels
    rig_from_projector : (4, 4) float64, mm
    """

    lens: PinholeModel
    rig_from_projector: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        object.__setattr__(self, "rig_from_projector", _as_pose(self.rig_from_projector, "projector pose"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Projector):
            return NotImplemented
        return self.lens == other.lens and np.array_equal(self.rig_from_projector, other.rig_from_projector)

    __hash__ = None  # mutable array inside

    @property
    def center(self) -> np.ndarray:
        """Centre of projection (3,) in the rig frame, mm."""
        return self.rig_from_projector[:3, 3].copy()

    @property
    def axis(self) -> np.ndarray:
        return self.rig_from_projector[:3, 2].copy()

    def project(self, points: np.ndarray) -> np.ndarray:
        """Continuous projector pixel coordinates (..., 2) of rig-frame ``points`` (..., 3)."""
        local = transform_points(np.linalg.inv(self.rig_from_projector), points)
        return self.lens.project_local(local)

    def column_planes(self, columns: np.ndarray) -> np.ndarray:
        """Light planes (n, 4) ``[a, b, c, d]`` with unit normal, ``a x + b y + c z + d = 0``.

        Each plane holds the projector centre and every ray of the (continuous) projector
        column ``u`` in ``columns``; exact when the projector lens has no distortion.
        """
        u = np.asarray(columns, float).reshape(-1)
        xn = (u - self.lens.cx) / self.lens.fx
        # normal (1, 0, -xn) in the projector frame, rotated: R[:, 0] - xn R[:, 2]
        # (written out: an (n, 3) @ (3, 3) product is several times slower)
        rot = self.rig_from_projector[:3, :3]
        n = [rot[i, 0] - xn * rot[i, 2] for i in range(3)]
        scale = 1.0 / np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        n = [c * scale for c in n]
        c = self.center
        return np.stack([*n, -(n[0] * c[0] + n[1] * c[1] + n[2] * c[2])], axis=1)

    def to_dict(self) -> dict:
        return {"lens": self.lens.to_dict(), "rig_from_projector": self.rig_from_projector.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Projector:
        try:
            return cls(PinholeModel.from_dict(d["lens"], "projector lens"), np.asarray(d["rig_from_projector"]))
        except KeyError as exc:
            raise SlscanError(f"projector: missing field {exc.args[0]!r}") from None


@dataclass(frozen=True)
class Light:
    """A point light of the ring around the camera.

    position : (3,) mm, rig frame
    intensity : (3,) relative RGB; 1.0 gives the projector's full white at the reference distance
    """

    position: tuple[float, float, float]
    intensity: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def to_dict(self) -> dict:
        return {"position": list(self.position), "intensity": list(self.intensity)}

    @classmethod
    def from_dict(cls, d: dict) -> Light:
        try:
            return cls(tuple(map(float, d["position"])), tuple(map(float, d.get("intensity", (1, 1, 1)))))
        except KeyError as exc:
            raise SlscanError(f"light: missing field {exc.args[0]!r}") from None


@dataclass(frozen=True)
class Rig:
    """Camera (at the rig origin), projector and lights: a calibrated structured-light rig."""

    camera: PinholeModel
    projector: Projector
    lights: tuple[Light, ...] = ()
    working_distance: float = 1300.0
    """Distance (mm) along the camera axis to the centre of the working volume."""

    def validate(self) -> None:
        """Raise :class:`SlscanError` for a rig that cannot triangulate."""
        baseline = float(np.linalg.norm(self.projector.center))
        if baseline < 1.0:
            raise SlscanError(
                f"degenerate rig: camera and projector centres are {baseline:.3f} mm apart; "
                "triangulation needs a baseline"
            )
        cos_angle = float(np.clip(self.projector.axis @ np.array([0, 0, 1.0]), -1, 1))
        if cos_angle <= 0:
            raise SlscanError("degenerate rig: the projector looks away from the camera's field")

    @property
    def axes_angle_deg(self) -> float:
        """Angle between camera and projector optical axes, degrees."""
        return math.degrees(math.acos(float(np.clip(self.projector.axis[2], -1, 1))))

    def to_dict(self) -> dict:
        return {
            "camera": self.camera.to_dict(),
            "projector": self.projector.to_dict(),
            "lights": [light.to_dict() for light in self.lights],
            "working_distance_mm": self.working_distance,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Rig:
        try:
            return cls(
                camera=PinholeModel.from_dict(d["camera"], "camera"),
                projector=Projector.from_dict(d["projector"]),
                lights=tuple(Light.from_dict(x) for x in d.get("lights", [])),
                working_distance=float(d.get("working_distance_mm", 1300.0)),
            )
        except KeyError as exc:
            raise SlscanError(f"rig: missing field {exc.args[0]!r}") from None


def default_rig(
    *,
    scale: float = 1.0,
    projector_scale: float = 1.0,
    working_distance: float = 1300.0,
    axes_angle_deg: float = 20.0,
    n_lights: int = 6,
    light_ring_radius: float = 250.0,
    camera_size: tuple[int, int] = (1440, 960),
    projector_size: tuple[int, int] = (1024, 768),
    sampling_mm: float = 0.7,
    camera_distortion: tuple[float, float, float, float, float] = (-0.06, 0.04, 0.0, 0.0, 0.0),
) -> Rig:
    """The paper's rig: 1440×960 camera, 1024×768 projector, ~20° apart, at ~1.3 m.

    Both devices sample about ``sampling_mm`` (0.7) mm per pixel at the working distance
    (the paper's 0.7 mm × 1.4 mm sampling with 511 lines two projector pixels apart): both
    focal lengths are ``working_distance / sampling_mm`` px. The camera has mild barrel
    distortion (``camera_distortion``, OpenCV order) and its principal point is off-centre
    by (+3.2, −2.1) px. The projector sits to the camera's right and looks at the point on
    the camera axis at ``working_distance``. ``scale`` and ``projector_scale`` shrink the
    sensors (same field of view) for quick tests.
    """
    f_cam = working_distance / sampling_mm
    (cw, ch), (pw, ph) = camera_size, projector_size
    camera = PinholeModel(cw, ch, f_cam, f_cam, (cw - 1) / 2 + 3.2, (ch - 1) / 2 - 2.1, tuple(camera_distortion))
    camera = camera.scaled(scale) if scale != 1.0 else camera
    proj_lens = PinholeModel(pw, ph, f_cam, f_cam, (pw - 1) / 2, (ph - 1) / 2)
    proj_lens = proj_lens.scaled(projector_scale) if projector_scale != 1.0 else proj_lens
    target = np.array([0.0, 0.0, working_distance])
    a = math.radians(axes_angle_deg)
    eye = target + working_distance * np.array([math.sin(a), 0.0, -math.cos(a)])
    projector = Projector(proj_lens, look_at(eye, target))
    lights = tuple(
        Light(
            (
                light_ring_radius * math.cos(2 * math.pi * i / n_lights),
                light_ring_radius * math.sin(2 * math.pi * i / n_lights),
                0.0,
            ),
            (0.8, 0.8, 0.8),
        )
        for i in range(n_lights)
    )
    return Rig(camera, projector, lights, working_distance)
