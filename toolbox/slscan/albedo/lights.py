"""Light calibration: point-light positions and RGB intensities from a flat matte panel.

Done once per rig. A matte panel of known reflectance is imaged under each ring light at
a few poses. The pose is known when the session records it (the virtual rig does);
otherwise (a real rig, the panel placed by hand) the panel's plane comes from its own
range map: the panel session is a scan like any other (patterns, then one image per ring
light, switched by a relay or by the operator when asked), decoded, and a plane fitted to
each view's range map (:func:`fit_panel_plane`); its pixels are those of the range map on
that plane. Every panel pixel gives the
irradiance of every light at a known point and normal (:mod:`slscan.albedo.radiometry`).
The light positions, RGB intensities and the ambient light are fitted to all of them
together by Levenberg-Marquardt with an analytic sparse Jacobian, started from the
intensities and ambient that are linearly best for the initial positions.

The result, :class:`LightCalibration`, is a small JSON file (``LIGHTS.json``)::

    {"format": "slscan.light-calibration", "version": 1,
     "frame": "rig (camera) frame, mm", "reference_distance_mm": 1300.0,
     "ambient": [r, g, b],
     "lights": [{"position": [x, y, z], "intensity": [r, g, b], "position_sigma_mm": s}, ...],
     "fit": {...}}

References
----------
.. [1] Rocchini, Cignoni, Montani, Pingi, Scopigno, "A low cost 3D scanner based on
   structured light", Computer Graphics Forum 20(3), Eurographics 2001, §3.4.
.. [2] Marquardt, "An algorithm for least-squares estimation of nonlinear parameters",
   SIAM J. Applied Mathematics 11(2), 1963.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from slscan import __version__
from slscan.albedo.radiometry import read_lit_images
from slscan.capture.session import Session, ViewRecord, load_session
from slscan.errors import SlscanError
from slscan.fsio import read_json, write_json
from slscan.rig import Light, Rig, transform_points

log = logging.getLogger(__name__)

LIGHTS_FORMAT = "slscan.light-calibration"
LIGHTS_VERSION = 1
PANEL_FORMAT = "slscan.light-panel"
PANEL_FILE = "light_panel.json"
"""Description of the calibration panel, written into a light-calibration session."""


# --- the calibration panel -------------------------------------------------------------


@dataclass(frozen=True)
class MattePanel:
    """A flat Lambertian panel of known reflectance, the light-calibration target.

    Object frame (as every scene): centred, mm, y down, the front face at
    ``z = -thickness / 2`` facing -z (towards the camera when placed in front of it).

    width, height, thickness : mm
    albedo : (3,) linear RGB reflectance of the front face (e.g. a grey card's)
    margin : mm of the front face left out along its edges (blur, bevels)
    """

    width: float = 600.0
    height: float = 450.0
    thickness: float = 10.0
    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    margin: float = 20.0

    def __post_init__(self) -> None:
        if min(self.width, self.height) <= 2 * self.margin or self.thickness < 0:
            raise SlscanError(
                f"light panel: {self.width} x {self.height} mm with a {self.margin} mm margin leaves no face"
            )
        if len(self.albedo) != 3 or not all(0 < a <= 1 for a in self.albedo):
            raise SlscanError(f"light panel: albedo must be 3 values in (0, 1], got {self.albedo}")

    def front_plane(self, rig_from_panel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A point on the front face (3,) mm and its unit normal (3,), rig frame."""
        point = transform_points(rig_from_panel, np.array([0.0, 0.0, -self.thickness / 2]))
        normal = rig_from_panel[:3, :3] @ np.array([0.0, 0.0, -1.0])
        return point, normal

    def to_dict(self) -> dict:
        return {
            "format": PANEL_FORMAT,
            "width_mm": self.width,
            "height_mm": self.height,
            "thickness_mm": self.thickness,
            "albedo": list(self.albedo),
            "margin_mm": self.margin,
        }

    @classmethod
    def from_dict(cls, d: dict, where: str = "light panel") -> MattePanel:
        try:
            return cls(
                width=float(d["width_mm"]),
                height=float(d["height_mm"]),
                thickness=float(d.get("thickness_mm", 10.0)),
                albedo=tuple(float(a) for a in d["albedo"]),
                margin=float(d.get("margin_mm", 20.0)),
            )
        except KeyError as exc:
            raise SlscanError(f"{where}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise SlscanError(f"{where}: {exc}") from None


def read_panel(session_root: str | os.PathLike) -> MattePanel:
    """The panel described by ``SESSION/light_panel.json``."""
    path = Path(session_root) / PANEL_FILE
    d = read_json(path, "light-panel description")
    if not isinstance(d, dict) or d.get("format") != PANEL_FORMAT:
        raise SlscanError(f"{path}: not an slscan light-panel description")
    return MattePanel.from_dict(d, str(path))


# --- the calibration result --------------------------------------------------------------


PROJECTOR_LIGHT_FORMAT = "slscan.projector-light"


@dataclass(frozen=True)
class ProjectorLight:
    """The projector's full white as a calibrated point light (for albedo without ring lights).

    In normalised units (:mod:`slscan.albedo.radiometry`) a Lambertian surface of albedo
    ``a`` lit by the projector's white frame (its black frame subtracted) reads
    ``a_c * intensity_c * flat(u, v) * max(0, n . l) * (reference_distance / d)**2``,
    ``l`` the unit vector to the projector's centre and ``d`` its distance (mm).

    intensity : (3,) RGB, what a white surface facing the projector at
        ``reference_distance`` mm reads; (1, 1, 1) uncalibrated (albedo then is relative
        to the projector's white at that distance)
    reference_distance : mm
    flat_field : (gh, gw) relative emitted radiance over the projector's frame (a coarse
        grid spanning the projector's pixels, median 1: vignetting, hot spot), or None
        (uniform)
    source : how it was made, in words ("nominal (uncalibrated)", the panel session)
    """

    intensity: tuple[float, float, float] = (1.0, 1.0, 1.0)
    reference_distance: float = 1300.0
    flat_field: tuple[tuple[float, ...], ...] | None = None
    source: str = "nominal (uncalibrated)"

    def __post_init__(self) -> None:
        if len(self.intensity) != 3 or not all(np.isfinite(i) and i > 0 for i in self.intensity):
            raise SlscanError(f"projector light: intensity must be 3 positive values, got {self.intensity}")
        if not (np.isfinite(self.reference_distance) and self.reference_distance > 0):
            raise SlscanError(
                f"projector light: reference distance must be positive, got {self.reference_distance}"
            )
        if self.flat_field is not None:
            grid = np.asarray(self.flat_field, float)
            if grid.ndim != 2 or min(grid.shape) < 1 or not np.all(np.isfinite(grid) & (grid > 0)):
                raise SlscanError("projector light: flat_field must be a 2-D grid of positive numbers")

    @property
    def calibrated(self) -> bool:
        return not self.source.startswith("nominal")

    def flat_at(self, uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """Relative radiance (n,) at projector pixels ``uv`` (n, 2) of a ``size`` = (w, h)
        projector, bilinear over the flat-field grid (its cells span the frame evenly); 1
        without a flat field."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        if self.flat_field is None:
            return np.ones(len(uv))
        from scipy.ndimage import map_coordinates

        grid = np.asarray(self.flat_field, np.float64)
        gh, gw = grid.shape
        w, h = size
        # cell i's centre sits at projector pixel (i + 0.5) * w / gw - 0.5
        x = np.clip((uv[:, 0] + 0.5) * gw / w - 0.5, 0, gw - 1)
        y = np.clip((uv[:, 1] + 0.5) * gh / h - 0.5, 0, gh - 1)
        return map_coordinates(grid, [y, x], order=1, mode="nearest")

    def to_dict(self) -> dict:
        return {
            "format": PROJECTOR_LIGHT_FORMAT,
            "intensity": [float(i) for i in self.intensity],
            "reference_distance_mm": float(self.reference_distance),
            "flat_field": None if self.flat_field is None else [list(map(float, r)) for r in self.flat_field],
            "source": self.source,
        }

    @classmethod
    def from_dict(cls, d: Any, where: str = "projector light") -> ProjectorLight:
        if not isinstance(d, dict):
            raise SlscanError(f"{where}: expected a table with 'intensity' and 'reference_distance_mm'")
        try:
            flat = d.get("flat_field")
            return cls(
                tuple(float(i) for i in d["intensity"]),
                float(d["reference_distance_mm"]),
                None if flat is None else tuple(tuple(float(x) for x in row) for row in flat),
                str(d.get("source", "given")),
            )
        except KeyError as exc:
            raise SlscanError(f"{where}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise SlscanError(f"{where}: {exc}") from None



@dataclass(frozen=True)
class LightCalibration:
    """Calibrated ring lights: positions (mm, rig frame), RGB intensities, ambient light.

    Intensities and ambient are in normalised image units (see
    :mod:`slscan.albedo.radiometry`): light ``k`` gives a white (albedo 1) surface
    facing it at ``reference_distance`` mm the image value ``intensity``.

    lights : the ring lights, indexed as the sessions' lit images
    ambient : (3,) RGB irradiance present in every lit image
    reference_distance : mm, the distance at which ``intensity`` is measured
    position_sigma : (k,) mm, 1-sigma position uncertainty of each light from the fit
        (0 when not fitted)
    fit : how the calibration was made (residual, samples, session), for the record
    projector : the projector's white as a calibrated light (from the panel's white and
        black frames), or None; with it ``lights`` may be empty (a rig without ring lights)
    """

    lights: tuple[Light, ...]
    ambient: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reference_distance: float = 1300.0
    position_sigma: tuple[float, ...] = ()
    fit: dict = field(default_factory=dict)
    projector: ProjectorLight | None = None

    @property
    def positions(self) -> np.ndarray:
        """(k, 3) float64 mm."""
        return np.array([light.position for light in self.lights], float).reshape(-1, 3)

    @property
    def intensities(self) -> np.ndarray:
        """(k, 3) float64 RGB."""
        return np.array([light.intensity for light in self.lights], float).reshape(-1, 3)

    @classmethod
    def from_rig(
        cls, rig: Rig, *, ambient: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ) -> LightCalibration:
        """The nominal lights of a rig description (uncalibrated; no ambient unless given)."""
        if not rig.lights:
            raise SlscanError("the rig describes no ring lights")
        return cls(
            tuple(rig.lights),
            tuple(ambient),
            rig.working_distance,
            (0.0,) * len(rig.lights),
            {"source": "rig description (nominal, not calibrated)"},
        )

    def to_dict(self) -> dict:
        sigma = self.position_sigma or (0.0,) * len(self.lights)
        return {
            "format": LIGHTS_FORMAT,
            "version": LIGHTS_VERSION,
            "written_by": f"slscan {__version__}",
            "frame": "rig (camera) frame, mm",
            "units": "intensity and ambient: image value / (2^bits - 1) / exposure factor, "
            "for albedo 1 facing the light at reference_distance_mm",
            "reference_distance_mm": self.reference_distance,
            "ambient": [float(a) for a in self.ambient],
            "lights": [
                {**light.to_dict(), "position_sigma_mm": float(s)}
                for light, s in zip(self.lights, sigma)
            ],
            "fit": self.fit,
            **({"projector": self.projector.to_dict()} if self.projector is not None else {}),
        }

    @classmethod
    def from_dict(cls, d: Any, where: str = "light calibration") -> LightCalibration:
        if not isinstance(d, dict) or d.get("format") != LIGHTS_FORMAT:
            raise SlscanError(
                f"{where}: not an slscan light calibration (format {d.get('format') if isinstance(d, dict) else None!r})"
            )
        if d.get("version") != LIGHTS_VERSION:
            raise SlscanError(
                f"{where}: light-calibration version {d.get('version')} is not supported"
            )
        try:
            lights = tuple(Light.from_dict(x) for x in d["lights"])
            ambient = tuple(float(a) for a in d.get("ambient", (0, 0, 0)))
            sigma = tuple(float(x.get("position_sigma_mm", 0.0)) for x in d["lights"])
            projector = d.get("projector")
            if projector is not None:
                projector = ProjectorLight.from_dict(projector, f"{where}: projector")
            cal = cls(
                lights, ambient, float(d["reference_distance_mm"]), sigma, dict(d.get("fit", {})), projector
            )
        except KeyError as exc:
            raise SlscanError(f"{where}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError, SlscanError) as exc:
            raise SlscanError(f"{where}: {exc}") from None
        if len(cal.ambient) != 3 or any(
            len(x.position) != 3 or len(x.intensity) != 3 for x in lights
        ):
            raise SlscanError(f"{where}: positions, intensities and ambient need 3 values each")
        if not lights and cal.projector is None:
            raise SlscanError(f"{where}: no lights (and no projector light)")
        numbers = [cal.reference_distance, *cal.ambient, *cal.position_sigma]
        numbers += [v for x in lights for v in (*x.position, *x.intensity)]
        if not np.isfinite(np.asarray(numbers, np.float64)).all():
            raise SlscanError(f"{where}: positions, intensities, ambient and reference distance must be finite "
                              "numbers (got NaN or inf)")
        return cal


def write_lights(path: str | os.PathLike, calibration: LightCalibration) -> Path:
    """Write ``calibration`` as JSON, atomically."""
    path = Path(path)
    write_json(path, calibration.to_dict())
    return path


def read_lights(path: str | os.PathLike) -> LightCalibration:
    """Read a light calibration written by :func:`write_lights`."""
    return LightCalibration.from_dict(read_json(path, "light calibration"), str(path))


# --- observations -------------------------------------------------------------------------


@dataclass(frozen=True)
class PanelSamples:
    """Panel pixels of one view: where they are and what each light gave them.

    points : (n, 3) float64 mm rig frame; normal : (3,) unit, the panel's
    values : (k, n, 3) float64 normalised units; usable : (k, n) bool (not saturated)
    lights : (k,) int light index of each row
    """

    view: str
    points: np.ndarray
    normal: np.ndarray
    values: np.ndarray
    usable: np.ndarray
    lights: np.ndarray


@dataclass(frozen=True)
class PanelFit:
    """The panel's plane in one view, fitted to its range map (pose not recorded).

    rig_from_panel : (4, 4) a pose whose front face (``MattePanel.front_plane``) is the
        fitted plane, centred on the panel's pixels (its in-plane rotation is arbitrary)
    mask : (h, w) bool camera pixels on the plane (range map within ``tolerance_mm``),
        ``edge_px`` away from its outline
    rms_mm : RMS distance of the inliers to the plane
    """

    rig_from_panel: np.ndarray
    mask: np.ndarray
    rms_mm: float


def fit_panel_plane(
    session: Session,
    view: ViewRecord,
    range_map,
    panel: MattePanel,
    *,
    tolerance_mm: float = 3.0,
    edge_px: int = 6,
) -> PanelFit:
    """Fit the panel's front plane to ``view``'s range map (rig frame, mm).

    The largest plane is found by least squares, twice trimmed to the range-map pixels within
    ``tolerance_mm`` of it (a background wall or the panel's stand left out); the panel's
    pixels are the inliers, eroded by ``edge_px`` (blur and the panel's edges).
    """
    import cv2

    from slscan.albedo.surface import rasterise

    rig = session.calibration
    if rig is None:
        raise SlscanError(f"{session.root}: the session has no camera calibration")
    surface = rasterise(range_map, rig.camera)
    pts = surface.points[surface.hit]
    where = f"{session.root / view.name}: panel plane"
    if len(pts) < 100:
        raise SlscanError(f"{where}: the range map covers {len(pts)} pixels; expected the panel to fill the view")
    keep = np.ones(len(pts), bool)
    centre = normal = None
    for round_ in range(4):  # wide first (the fit may start tilted by a background), then the tolerance
        centre = pts[keep].mean(0)
        normal = np.linalg.svd(pts[keep] - centre, full_matrices=False)[2][2]
        dist = np.abs((pts - centre) @ normal)
        limit = max(tolerance_mm, 3 * 1.4826 * float(np.median(dist[keep]))) if round_ < 2 else tolerance_mm
        keep = dist <= limit
        if keep.sum() < 100:
            raise SlscanError(f"{where}: fewer than 100 range-map pixels lie on one plane; is the panel flat?")
    if normal @ centre > 0:
        normal = -normal  # towards the camera
    mask = np.zeros(surface.hit.shape, bool)
    mask[surface.hit] = keep
    if edge_px > 0:
        mask = cv2.erode(mask.astype(np.uint8), np.ones((2 * edge_px + 1,) * 2, np.uint8)).astype(bool)
    centre = pts[keep].mean(0)
    z = -normal
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = centre - normal * (panel.thickness / 2)  # the front face through the centre
    rms = float(np.sqrt(np.mean(((pts[keep] - centre) @ normal) ** 2)))
    return PanelFit(pose, mask, rms)


def fit_panel_planes(
    session: Session, range_maps_dir, panel: MattePanel, views: list[ViewRecord] | None = None
) -> dict[str, PanelFit]:
    """:func:`fit_panel_plane` for each view (default all) from a decode output folder."""
    from slscan.albedo.unshade import load_range_map

    fits = {}
    for view in views or session.views:
        range_map, _ = load_range_map(range_maps_dir, view)
        fits[view.name] = fit_panel_plane(session, view, range_map, panel)
        log.info("%s: panel plane fitted to the range map, RMS %.2f mm", view.name, fits[view.name].rms_mm)
    return fits


def _panel_pose(session: Session, view: ViewRecord, rig_from_panel: np.ndarray | None) -> np.ndarray:
    pose = rig_from_panel if rig_from_panel is not None else view.rig_from_object
    if pose is None:
        raise SlscanError(
            f"{session.root / view.name}: the panel's pose is unknown (the view records no rig_from_object; "
            "give the panel's range maps, slscan decode --out, to fit its plane)"
        )
    return np.asarray(pose, float)


def panel_plane(
    session: Session, view: ViewRecord, panel: MattePanel, *, rig_from_panel: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """A point on the panel's front face (3,) mm and its unit normal (3,), rig frame, from
    ``rig_from_panel`` (default: the view's recorded ``rig_from_object``)."""
    return panel.front_plane(_panel_pose(session, view, rig_from_panel))


def panel_pixels(
    session: Session,
    view: ViewRecord,
    panel: MattePanel,
    *,
    rig_from_panel: np.ndarray | None = None,
    edge_px: int = 3,
    fit: PanelFit | None = None,
) -> np.ndarray:
    """(h, w) bool: the camera pixels whose ray meets the panel's front face inside its
    margin, ``edge_px`` pixels away from its outline.

    rig_from_panel : (4, 4) the panel's pose; default: the view's recorded
        ``rig_from_object`` (the virtual rig records it)
    fit : the panel's plane fitted to its range map instead (its pixels are the fit's mask)
    """
    if fit is not None:
        return fit.mask.copy()
    rig = session.calibration
    if rig is None:
        raise SlscanError(f"{session.root}: the session has no camera calibration")
    pose = _panel_pose(session, view, rig_from_panel)
    cam = rig.camera
    h, w = cam.height, cam.width
    grid = np.stack(np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float)), axis=-1)
    rays = cam.rays_local(grid)
    centre, normal = panel.front_plane(pose)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (normal @ centre) / (rays @ normal)
    points = rays * t[..., None]
    local = transform_points(np.linalg.inv(pose), points)
    inside = (
        (t > 0)
        & (np.abs(local[..., 0]) <= panel.width / 2 - panel.margin)
        & (np.abs(local[..., 1]) <= panel.height / 2 - panel.margin)
        & ((rays @ normal) < 0)
    )
    if edge_px > 0:
        import cv2

        inside = cv2.erode(
            inside.astype(np.uint8), np.ones((2 * edge_px + 1,) * 2, np.uint8)
        ).astype(bool)
    return inside


def panel_samples(
    session: Session,
    view: ViewRecord,
    panel: MattePanel,
    *,
    rig_from_panel: np.ndarray | None = None,
    max_samples: int = 4000,
    edge_px: int = 3,
    fit: PanelFit | None = None,
) -> PanelSamples:
    """Intersect the camera rays with the panel's front face and read the lit images there.

    rig_from_panel : (4, 4) the panel's pose; default: the view's recorded
        ``rig_from_object`` (the virtual rig records it)
    max_samples : pixels kept, on a regular grid over the face
    edge_px : pixels dropped next to the face's outline, besides ``panel.margin``
    fit : the panel's plane fitted to its range map (:func:`fit_panel_plane`) instead of a pose
    """
    if fit is not None:
        rig_from_panel = fit.rig_from_panel
    inside = panel_pixels(session, view, panel, rig_from_panel=rig_from_panel, edge_px=edge_px, fit=fit)
    centre, normal = panel_plane(session, view, panel, rig_from_panel=rig_from_panel)
    count = int(inside.sum())
    if count < 50:
        raise SlscanError(
            f"{session.root / view.name}: the panel covers {count} pixels; expected it to fill the view"
        )
    lit = read_lit_images(session, view, min_images=1)
    stride = max(1, int(np.ceil(np.sqrt(count / max_samples))))
    keep = np.zeros_like(inside)
    keep[stride // 2 :: stride, stride // 2 :: stride] = True
    keep &= inside
    rows, cols = np.nonzero(keep)
    rays = session.calibration.camera.rays_local(np.stack([cols, rows], axis=1).astype(float))
    points = rays * ((normal @ centre) / (rays @ normal))[:, None]
    return PanelSamples(
        view=view.name,
        points=points,
        normal=normal,
        values=lit.values[:, rows, cols].astype(np.float64),
        usable=~lit.saturated[:, rows, cols],
        lights=lit.lights,
    )


# --- the fit ------------------------------------------------------------------------------------


def _stack(samples: list[PanelSamples], n_lights: int):
    """Per-light design data over all views: points, normals, values, weights."""
    points = np.concatenate([s.points for s in samples])
    normals = np.concatenate([np.broadcast_to(s.normal, s.points.shape) for s in samples])
    n = len(points)
    values = np.zeros((n_lights, n, 3))
    weight = np.zeros((n_lights, n))
    start = 0
    for s in samples:
        stop = start + len(s.points)
        for row, k in enumerate(s.lights):
            values[k, start:stop] = s.values[row]
            weight[k, start:stop] = s.usable[row]
        start = stop
    return points, normals, values, weight


def _linear_part(g: np.ndarray, y: np.ndarray, w: np.ndarray, fit_ambient: bool):
    """Intensities (k, 3) and ambient (3,) minimising sum w (y - amb - I_k g)^2.

    g : (k, n) geometric factor; y : (k, n, 3) values over albedo; w : (k, n) weights
    """
    k = g.shape[0]
    swg = (w * g).sum(1)
    swgg = (w * g * g).sum(1)
    intensities = np.zeros((k, 3))
    ambient = np.zeros(3)
    for c in range(3):
        swgy = (w * g * y[..., c]).sum(1)
        if fit_ambient:
            m = np.zeros((k + 1, k + 1))
            b = np.zeros(k + 1)
            m[0, 0] = w.sum()
            m[0, 1:] = m[1:, 0] = swg
            m[1:, 1:] = np.diag(swgg)
            b[0] = (w * y[..., c]).sum()
            b[1:] = swgy
            sol = np.linalg.solve(m + 1e-12 * np.eye(k + 1), b)
            ambient[c], intensities[:, c] = sol[0], sol[1:]
        else:
            intensities[:, c] = swgy / np.maximum(swgg, 1e-12)
    return intensities, ambient


def _levenberg_marquardt(residuals, jacobian, x0, x_scale, *, max_iterations=200, tol=1e-10):
    """Minimise ``|residuals(x)|^2`` by Levenberg-Marquardt on the (small) normal equations.

    ``jacobian`` may return a sparse matrix; returns (x, cost, iterations, converged).
    """
    x = x0.astype(float).copy()
    r = residuals(x)
    cost = float(r @ r)
    damping = 1e-3
    for iteration in range(1, max_iterations + 1):
        jac = jacobian(x)
        jtj = jac.T @ jac
        jtj = (jtj.toarray() if hasattr(jtj, "toarray") else np.asarray(jtj)) * np.outer(
            x_scale, x_scale
        )
        grad = (jac.T @ r) * x_scale
        diag = np.maximum(np.diag(jtj), 1e-12)
        while True:
            try:
                step = -np.linalg.solve(jtj + damping * np.diag(diag), grad) * x_scale
            except np.linalg.LinAlgError:
                step = np.zeros_like(x)
            r_new = residuals(x + step)
            cost_new = float(r_new @ r_new)
            if cost_new < cost:
                x, r = x + step, r_new
                improvement = (cost - cost_new) / max(cost, 1e-300)
                cost = cost_new
                damping = max(damping / 3, 1e-9)
                break
            damping *= 10
            if damping > 1e12:
                return x, cost, iteration, True  # no step improves: at the minimum
        if improvement < tol or np.all(np.abs(step) <= tol * (np.abs(x) + x_scale)):
            return x, cost, iteration, True
    return x, cost, max_iterations, False


def fit_lights(
    samples: list[PanelSamples],
    panel: MattePanel,
    initial_positions: np.ndarray,
    *,
    reference_distance: float,
    fit_ambient: bool = True,
) -> LightCalibration:
    """Fit light positions, intensities and ambient light to panel samples.

    initial_positions : (k, 3) mm starting guess (the nominal ring, or the rig's
        description); a guess within a few hundred mm converges
    Returns the calibration with 1-sigma position uncertainties from the fit's Jacobian.
    """
    if not samples:
        raise SlscanError("light calibration: no panel views")
    n_lights = len(initial_positions)
    points, normals, values, weight = _stack(samples, n_lights)
    for k in range(n_lights):
        if weight[k].sum() < 10:
            raise SlscanError(
                f"light calibration: light {k} has no usable panel pixels (no lit image of it, or all saturated)"
            )
    albedo = np.asarray(panel.albedo, float)
    y = values / albedo
    sqrt_w = np.sqrt(weight)
    n_points = len(points)
    ref2 = reference_distance**2

    def geometric(positions: np.ndarray):
        """g (k, n) and its gradient (k, n, 3) with respect to each light's position."""
        d = positions[:, None, :] - points[None]
        dist = np.maximum(np.linalg.norm(d, axis=-1), 1e-9)
        dot = np.einsum("kni,ni->kn", d, normals)
        front = dot > 0
        g = np.where(front, ref2 * dot / dist**3, 0.0)
        grad = ref2 * (normals[None] / dist[..., None] ** 3 - 3 * (dot / dist**5)[..., None] * d)
        return g, np.where(front[..., None], grad, 0.0)

    # unknowns: positions (k, 3), intensities (k, 3), ambient (3)
    n_pos, n_int = 3 * n_lights, 3 * n_lights
    n_par = n_pos + n_int + (3 if fit_ambient else 0)
    row_w = (sqrt_w[..., None] * albedo).ravel()  # (k * n * 3,) row scale of the residuals
    kk, nn, cc = np.meshgrid(np.arange(n_lights), np.arange(n_points), np.arange(3), indexing="ij")
    kk, nn, cc = kk.ravel(), nn.ravel(), cc.ravel()
    cols = [3 * kk, 3 * kk + 1, 3 * kk + 2, n_pos + 3 * kk + cc]
    if fit_ambient:
        cols.append(n_pos + n_int + cc)
    cols = np.stack(cols, axis=1)
    rows = np.repeat(np.arange(len(kk)), cols.shape[1])

    def unpack(x: np.ndarray):
        positions = x[:n_pos].reshape(-1, 3)
        intensities = x[n_pos : n_pos + n_int].reshape(-1, 3)
        ambient = x[n_pos + n_int :] if fit_ambient else np.zeros(3)
        return positions, intensities, ambient

    def residuals(x: np.ndarray) -> np.ndarray:
        positions, intensities, ambient = unpack(x)
        g, _ = geometric(positions)
        model = ambient + g[..., None] * intensities[:, None, :]
        return (model - y).ravel() * row_w

    def jacobian(x: np.ndarray):
        from scipy.sparse import csr_matrix

        positions, intensities, _ = unpack(x)
        g, grad = geometric(positions)
        dpos = grad[kk, nn] * intensities[kk, cc][:, None]  # (rows, 3)
        parts = [dpos, g[kk, nn][:, None]]
        if fit_ambient:
            parts.append(np.ones((len(kk), 1)))
        values = np.concatenate(parts, axis=1) * row_w[:, None]
        return csr_matrix((values.ravel(), (rows, cols.ravel())), shape=(len(kk), n_par))

    x0_pos = np.asarray(initial_positions, float)
    g0, _ = geometric(x0_pos)
    i0, a0 = _linear_part(g0, y, weight, fit_ambient)
    x0 = np.concatenate([x0_pos.ravel(), i0.ravel(), a0 if fit_ambient else []])
    x_scale = np.concatenate([np.full(n_pos, 100.0), np.full(n_int + n_par - n_pos - n_int, 0.1)])
    x, cost, iterations, converged = _levenberg_marquardt(residuals, jacobian, x0, x_scale)
    positions, intensities, ambient = unpack(x)
    dof = max(1, int(weight.sum()) * 3 - n_par)
    rms = float(np.sqrt(cost / dof))
    try:
        jac = jacobian(x)
        cov = np.linalg.inv((jac.T @ jac).toarray()) * rms**2
        sigma = np.sqrt(np.clip(np.diag(cov)[:n_pos], 0, None)).reshape(-1, 3)
        position_sigma = tuple(float(np.linalg.norm(s)) for s in sigma)
    except np.linalg.LinAlgError:
        position_sigma = (float("inf"),) * n_lights
    if not converged:
        log.warning("light calibration: the fit did not converge in %d iterations", iterations)
    lights = tuple(
        Light(tuple(map(float, p)), tuple(map(float, i))) for p, i in zip(positions, intensities)
    )
    fit = {
        "rms": rms,
        "samples": len(points),
        "views": [s.view for s in samples],
        "panel": panel.to_dict(),
        "iterations": iterations,
        "ambient_fitted": fit_ambient,
    }
    return LightCalibration(
        lights, tuple(map(float, ambient)), float(reference_distance), position_sigma, fit
    )


def calibrate_lights(
    session: Session | str | os.PathLike,
    *,
    panel: MattePanel | None = None,
    initial: LightCalibration | np.ndarray | None = None,
    views: list[str] | None = None,
    max_samples_per_view: int = 4000,
    fit_ambient: bool = True,
    projector: bool = True,
    range_maps: str | os.PathLike | None = None,
    progress: Callable[[str], None] | None = None,
) -> LightCalibration:
    """Calibrate the ring lights (and the projector as a light) from a session of a matte
    panel at known poses.

    session : a light-calibration session (e.g. from
        :func:`slscan.virtual.panels.capture_light_calibration`); each view shows the
        panel under every ring light, with its pose recorded as ``rig_from_object``
    panel : the panel; default: ``SESSION/light_panel.json``
    initial : starting light positions; default: the session's rig description, else a
        250 mm ring around the camera
    views : names of the views to use; default all
    projector : also measure the projector's white as a light
        (:func:`slscan.albedo.projector_light.calibrate_projector_light`) when the views
        have white frames; a session with white frames and no lit images (a rig without
        ring lights) gives a calibration of the projector only
    range_maps : the panel session's range maps (``slscan decode --out``): the panel's
        plane in each view whose pose is not recorded (a real rig) is fitted to its range
        map (:func:`fit_panel_plane`)

    The intensities are in normalised units relative to ``panel.albedo``, the reference
    distance is the rig's working distance.
    """
    if not isinstance(session, Session):
        session = load_session(session)
    panel = panel or read_panel(session.root)
    rig = session.calibration
    if rig is None:
        raise SlscanError(f"{session.root}: the session has no calibration (camera model needed)")
    chosen = [session.view(v) for v in views] if views else list(session.views)
    light_ids = sorted({r.light for v in chosen for r in v.lit_images()})
    unposed = [v for v in chosen if v.rig_from_object is None]
    fits = fit_panel_planes(session, range_maps, panel, unposed) if range_maps is not None and unposed else {}

    def projector_light():
        if not (projector and _has_white_frame(session)):
            return None
        from slscan.albedo.projector_light import calibrate_projector_light

        sub = session if not views else replace(session, views=tuple(chosen))
        return calibrate_projector_light(sub, panel, fits=fits)

    if not light_ids:
        if projector and _has_white_frame(session):
            log.info("%s: no lit images; the projector light only", session.root)
            return LightCalibration(
                (), (0.0, 0.0, 0.0), rig.working_distance, (),
                {"source": "panel session (projector only)", "session": str(Path(session.root).resolve()),
                 "panel": panel.to_dict()},
                projector_light(),
            )
        raise SlscanError(f"{session.root}: no lit images in the session; nothing to calibrate")
    n_lights = max(light_ids) + 1
    missing = sorted(set(range(n_lights)) - set(light_ids))
    if missing:
        raise SlscanError(
            f"{session.root}: no lit image of light(s) {missing}; every light needs panel images"
        )
    if isinstance(initial, LightCalibration):
        x0 = initial.positions
    elif initial is not None:
        x0 = np.asarray(initial, float).reshape(-1, 3)
    elif len(rig.lights) >= n_lights:
        x0 = np.array([light.position for light in rig.lights[:n_lights]], float)
    else:
        a = 2 * np.pi * np.arange(n_lights) / n_lights
        x0 = np.stack([250 * np.cos(a), 250 * np.sin(a), np.zeros(n_lights)], axis=1)
    if len(x0) != n_lights:
        raise SlscanError(f"light calibration: {len(x0)} initial positions for {n_lights} lights")
    samples = []
    for view in chosen:
        samples.append(
            panel_samples(session, view, panel, max_samples=max_samples_per_view, fit=fits.get(view.name))
        )
        if progress:
            progress(view.name)
    cal = fit_lights(
        samples, panel, x0, reference_distance=rig.working_distance, fit_ambient=fit_ambient
    )
    return LightCalibration(
        cal.lights,
        cal.ambient,
        cal.reference_distance,
        cal.position_sigma,
        {**cal.fit, "session": str(Path(session.root).resolve()),
         **({"panel_planes_rms_mm": {k: f.rms_mm for k, f in fits.items()}} if fits else {})},
        projector_light(),
    )


def _has_white_frame(session: Session) -> bool:
    return any(p.family == "flat" and list(p.params.get("value", [])) == [255, 255, 255] for p in session.patterns)
