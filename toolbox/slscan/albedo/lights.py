"""Light calibration: point-light positions and RGB intensities from a flat matte panel.

Done once per rig. A matte panel of known reflectance is imaged under each ring light at
a few known poses (a virtual session records its placement; a real rig would take it
from a printed board on the panel, not implemented yet). Every panel pixel gives the
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
from dataclasses import dataclass, field
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
    """

    lights: tuple[Light, ...]
    ambient: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reference_distance: float = 1300.0
    position_sigma: tuple[float, ...] = ()
    fit: dict = field(default_factory=dict)

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
            cal = cls(
                lights, ambient, float(d["reference_distance_mm"]), sigma, dict(d.get("fit", {}))
            )
        except KeyError as exc:
            raise SlscanError(f"{where}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError, SlscanError) as exc:
            raise SlscanError(f"{where}: {exc}") from None
        if len(cal.ambient) != 3 or any(
            len(x.position) != 3 or len(x.intensity) != 3 for x in lights
        ):
            raise SlscanError(f"{where}: positions, intensities and ambient need 3 values each")
        if not lights:
            raise SlscanError(f"{where}: no lights")
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


def panel_samples(
    session: Session,
    view: ViewRecord,
    panel: MattePanel,
    *,
    rig_from_panel: np.ndarray | None = None,
    max_samples: int = 4000,
    edge_px: int = 3,
) -> PanelSamples:
    """Intersect the camera rays with the panel's front face and read the lit images there.

    rig_from_panel : (4, 4) the panel's pose; default: the view's recorded
        ``rig_from_object`` (the virtual rig records it)
    max_samples : pixels kept, on a regular grid over the face
    edge_px : pixels dropped next to the face's outline, besides ``panel.margin``
    """
    rig = session.calibration
    if rig is None:
        raise SlscanError(f"{session.root}: the session has no camera calibration")
    pose = rig_from_panel if rig_from_panel is not None else view.rig_from_object
    if pose is None:
        raise SlscanError(
            f"{session.root / view.name}: the panel's pose is unknown (the view records no rig_from_object)"
        )
    lit = read_lit_images(session, view, min_images=1)
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
    count = int(inside.sum())
    if count < 50:
        raise SlscanError(
            f"{session.root / view.name}: the panel covers {count} pixels; expected it to fill the view"
        )
    stride = max(1, int(np.ceil(np.sqrt(count / max_samples))))
    keep = np.zeros_like(inside)
    keep[stride // 2 :: stride, stride // 2 :: stride] = True
    keep &= inside
    rows, cols = np.nonzero(keep)
    return PanelSamples(
        view=view.name,
        points=points[rows, cols],
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
    progress: Callable[[str], None] | None = None,
) -> LightCalibration:
    """Calibrate the ring lights from a session of a matte panel at known poses.

    session : a light-calibration session (e.g. from
        :func:`slscan.virtual.panels.capture_light_calibration`); each view shows the
        panel under every ring light, with its pose recorded as ``rig_from_object``
    panel : the panel; default: ``SESSION/light_panel.json``
    initial : starting light positions; default: the session's rig description, else a
        250 mm ring around the camera
    views : names of the views to use; default all

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
    if not light_ids:
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
        samples.append(panel_samples(session, view, panel, max_samples=max_samples_per_view))
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
        {**cal.fit, "session": str(Path(session.root).resolve())},
    )
