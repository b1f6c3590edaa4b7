"""Un-shaded images: the albedo stage for a view and a session, and its files.

For every camera pixel that sees the view's range map (ray cast from the camera, so the
result is registered with the geometry by construction), the lit images are inverted
per pixel by :mod:`slscan.albedo.photometric`: cast shadows found by shadow rays against
the range map, a specular lobe fitted per view, photometric normals regularised between
neighbours, and outliers rejected. Pixels next to the range map's border or a depth jump
mix two surfaces in the camera's blur and are left invalid.

Files written per view by :func:`albedo_session`: ``VIEW_albedo.png`` (16-bit **linear**
RGB reflectance x 65535, 0 where invalid), ``VIEW_valid.png`` (255 where valid),
``VIEW.ply`` (the range map with per-vertex albedo) and one ``albedo.json``.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from slscan import __version__
from slscan.albedo.lights import LightCalibration, ProjectorLight, read_lights
from slscan.albedo.photometric import (
    AlbedoConfig,
    SpecularLobe,
    albedo_for_normals,
    fit_view_lobe,
    regularise_normals,
    solve_pixels,
)
from slscan.albedo.radiometry import read_lit_images
from slscan.albedo.surface import SurfaceMap, occluded, rasterise
from slscan.capture.session import Session, ViewRecord, load_session
from slscan.colour import albedo_png, srgb8
from slscan.decode.rangemap import RangeMap, read_ply
from slscan.errors import SlscanError
from slscan.executor import LOCAL, Executor
from slscan.fsio import atomic_output_dir, glob_results, read_json, write_json, write_png

log = logging.getLogger(__name__)

ALBEDO_FORMAT = "slscan.albedo"
ALBEDO_VERSION = 1
# --- one view -------------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewAlbedo:
    """The albedo stage's result for one view.

    albedo : (h, w, 3) float32 linear RGB reflectance, NaN where invalid
    valid : (h, w) bool; lights_used : (h, w) uint8 lights in the final fit
    normal : (h, w, 3) float32 normals used (photometric or range), NaN off the range map
    shadow, highlight : (k, h, w) bool per lit image: light shadowed (by the range map or
        rejected below the fit) / rejected above the fit
    light_ids : (k,) int light of each lit image
    vertex_albedo : (n, 3) float32 linear RGB per range-map vertex, NaN where unknown
    surface : the range map rasterised into the camera
    lobe : the view's fitted specular lobe
    """

    view: str
    albedo: np.ndarray
    valid: np.ndarray
    lights_used: np.ndarray
    normal: np.ndarray
    shadow: np.ndarray
    highlight: np.ndarray
    light_ids: np.ndarray
    vertex_albedo: np.ndarray
    surface: SurfaceMap
    lobe: SpecularLobe
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def metrics(self) -> dict[str, float]:
        seen = self.surface.hit
        n_seen = max(int(seen.sum()), 1)
        return {
            "pixels_on_range_map": float(seen.sum()),
            "valid_share": float(self.valid.sum() / n_seen),
            "mean_lights_used": float(self.lights_used[self.valid].mean())
            if self.valid.any()
            else 0.0,
            "shadowed_share": float(self.shadow[:, seen].mean()) if seen.any() else 0.0,
            "highlight_share": float(self.highlight[:, seen].mean()) if seen.any() else 0.0,
            "specular_strength": self.lobe.strength,
            "specular_shininess": self.lobe.shininess,
        }


@dataclass(frozen=True)
class AlbedoSummary:
    """What :func:`albedo_session` keeps of a view once its files are written: counts and
    metrics, not the per-pixel arrays (146 full-size views of those are about 19 GiB).

    view : the view's name; valid_pixels : pixels with an albedo; seen_pixels : pixels on
    the range map; light_ids : the light of each lit image used; lobe : the fitted
    specular lobe; metrics, seconds : as :class:`ViewAlbedo`'s; unusable : why the view
    was left out, or None; light : {"ring", "projector"}, what lit it
    """

    view: str
    valid_pixels: int
    seen_pixels: int
    light_ids: tuple[int, ...]
    lobe: SpecularLobe
    metrics: dict[str, float]
    seconds: dict[str, float]
    unusable: str | None = None
    light: str = "ring"

    @classmethod
    def of(cls, result: ViewAlbedo) -> AlbedoSummary:
        light = "projector" if result.light_ids.tolist() == [-1] else "ring"
        return cls(result.view, int(result.valid.sum()), int(result.surface.hit.sum()),
                   tuple(int(k) for k in result.light_ids), result.lobe, dict(result.metrics), dict(result.seconds),
                   _why_unusable(result, light), light)


def mixed_pixels(surface: SurfaceMap, edge_px: int = 1, *, jump_mm: float = 10.0) -> np.ndarray:
    """(h, w) bool: pixels within ``edge_px`` of the range map's border or of a depth jump
    larger than ``jump_mm`` between neighbouring pixels."""
    from scipy import ndimage

    hit = surface.hit
    if edge_px <= 0:
        return np.zeros_like(hit)
    z = np.where(hit, surface.points[..., 2], np.nan)
    edge = np.zeros_like(hit)
    for axis in (0, 1):
        dz = np.abs(np.diff(z, axis=axis))
        jump = ~(dz <= jump_mm)  # NaN (border) counts as a jump
        if axis == 0:
            edge[1:] |= jump
            edge[:-1] |= jump
        else:
            edge[:, 1:] |= jump
            edge[:, :-1] |= jump
    edge &= hit
    if edge_px > 1:
        edge = ndimage.binary_dilation(edge, iterations=edge_px - 1) & hit
    return edge


def _check_range_map(range_map: RangeMap, view: ViewRecord, where: str) -> None:
    if range_map.view and range_map.view != view.name:
        raise SlscanError(
            f"{where}: the range map is of view {range_map.view!r}, not of view {view.name!r}"
        )


def vertex_albedo(range_map: RangeMap, albedo: np.ndarray, valid: np.ndarray, camera) -> np.ndarray:
    """Albedo (n, 3) float32 at each range-map vertex: bilinear over valid pixels, NaN if none."""
    h, w = valid.shape
    out = np.full((len(range_map.vertices), 3), np.nan, np.float32)
    if len(range_map.vertices) == 0:
        return out
    pix = camera.project_local(range_map.vertices)
    finite = np.all(np.isfinite(pix), axis=1)
    x = np.where(finite, pix[:, 0], -10.0)
    y = np.where(finite, pix[:, 1], -10.0)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    acc = np.zeros((len(x), 3))
    wsum = np.zeros(len(x))
    clean = np.where(valid[..., None], albedo, 0.0)
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            wt = np.where(inside, (1 - np.abs(x - xi)) * (1 - np.abs(y - yi)), 0.0)
            xi, yi = np.clip(xi, 0, w - 1), np.clip(yi, 0, h - 1)
            wt = wt * valid[yi, xi]
            acc += wt[:, None] * clean[yi, xi]
            wsum += wt
    has = wsum > 1e-6
    out[has] = (acc[has] / wsum[has, None]).astype(np.float32)
    return out


def albedo_view(
    session: Session,
    view: ViewRecord | str,
    range_map: RangeMap,
    lights: LightCalibration,
    config: AlbedoConfig | None = None,
    *,
    rec=None,
    view_index: int = 0,
    range_map_source: str = "range map",
) -> ViewAlbedo:
    """Un-shade one view: RGB albedo per pixel, registered with ``range_map``.

    range_map : the view's range map (rig frame, mm), e.g. ``decode_view(...).range_map``
    lights : the light calibration (positions, intensities, ambient)
    config : default :class:`AlbedoConfig`
    rec : an ``rr.RecordingStream`` for lit images, masks, the un-shaded image and, on
        the virtual rig, the error against ground truth; or None

    Raises
    ------
    SlscanError
        The range map is of another view, the view has too few lit images, or a lit
        image's light is not in ``lights``.
    """
    config = config or AlbedoConfig()
    view = session.view(view) if isinstance(view, str) else view
    rig = session.calibration
    if rig is None:
        raise SlscanError(
            f"{session.root}: the session has no calibration (the camera model is needed)"
        )
    _check_range_map(range_map, view, range_map_source)
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    lit = read_lit_images(session, view, min_images=config.min_lights)
    for rec_, k in zip(lit.records, lit.lights):
        if k >= len(lights.lights) or k < 0:
            raise SlscanError(
                f"{session.image_path(view, rec_)}: lit by light {k}, which the light calibration lacks "
                f"(it has lights 0..{len(lights.lights) - 1})"
            )
    seconds["read"] = time.perf_counter() - t
    t = time.perf_counter()
    surface = rasterise(range_map, rig.camera)
    rows, cols = np.nonzero(surface.hit & ~mixed_pixels(surface, config.edge_px))
    points = surface.points[rows, cols]
    normals = surface.normals[rows, cols]
    positions = lights.positions[lit.lights]
    shadowed = occluded(range_map, points, normals, positions, offset=config.shadow_offset_mm)
    seconds["geometry"] = time.perf_counter() - t
    values = lit.values[:, rows, cols].astype(np.float64)
    usable = ~lit.saturated[:, rows, cols]
    t = time.perf_counter()
    lobe = SpecularLobe()
    if config.specular == "fit" and len(rows):
        lobe = fit_view_lobe(
            values, usable & ~shadowed, points, normals, lights, lit.lights, config
        )
    seconds["specular"] = time.perf_counter() - t
    t = time.perf_counter()
    solution = solve_pixels(
        values,
        points,
        normals,
        lights,
        lit.lights,
        usable=usable,
        shadowed=shadowed,
        lobe=lobe,
        config=config,
        dn_unit=lit.dn_unit,
    )
    h, w = surface.hit.shape
    if solution.info is not None and config.smoothness_deg > 0 and solution.valid.any():
        # on the pixel grid, cropped to the pixels solved
        r0, c0 = rows.min(), cols.min()
        rr, cc = rows - r0, cols - c0
        shape = (rr.max() + 1, cc.max() + 1)
        valid_img = np.zeros(shape, bool)
        valid_img[rr, cc] = solution.valid
        normal_img = np.zeros(shape + (3,))
        normal_img[rr, cc] = solution.normal
        info_img = np.zeros(shape + (3, 3))
        info_img[rr, cc] = solution.info
        smooth = regularise_normals(
            normal_img,
            info_img,
            valid_img,
            smoothness_deg=config.smoothness_deg,
            noise=solution.noise,
        )[rr, cc]
        ok = solution.valid
        new_albedo = solution.albedo.copy()
        new_albedo[ok] = albedo_for_normals(
            values[:, ok], points[ok], smooth[ok], lights, lit.lights, solution.used[:, ok], lobe
        )
        new_normal = np.where(ok[:, None], smooth, solution.normal)
        solution = replace(solution, albedo=new_albedo, normal=new_normal)
    seconds["solve"] = time.perf_counter() - t
    k = len(lit.lights)
    albedo = np.full((h, w, 3), np.nan, np.float32)
    albedo[rows, cols] = solution.albedo
    valid = np.zeros((h, w), bool)
    valid[rows, cols] = solution.valid
    used = np.zeros((h, w), np.uint8)
    used[rows, cols] = solution.used.sum(0)
    normal = np.full((h, w, 3), np.nan, np.float32)
    normal[rows, cols] = solution.normal
    shadow = np.zeros((k, h, w), bool)
    shadow[:, rows, cols] = solution.shadow
    highlight = np.zeros((k, h, w), bool)
    highlight[:, rows, cols] = solution.highlight
    per_vertex = vertex_albedo(range_map, albedo, valid, rig.camera)
    result = ViewAlbedo(
        view.name,
        albedo,
        valid,
        used,
        normal,
        shadow,
        highlight,
        lit.lights,
        per_vertex,
        surface,
        lobe,
        seconds,
    )
    if result.valid.sum() == 0:
        log.info(
            "%s: no pixel has %d usable lights; the albedo image is empty",
            view.name,
            config.min_lights,
        )
    if rec is not None:
        _log_view(rec, session, view, result, range_map, lights, view_index)
    return result


def _log_view(rec, session, view, result: ViewAlbedo, range_map, lights, view_index) -> None:
    from slscan.viewer import log_albedo as rlog

    truth = None
    if view.ground_truth is not None:
        try:
            truth = session.load_ground_truth(view).albedo
        except SlscanError as exc:
            log.warning("%s: %s", view.name, exc)
    frames = {r.file: i for i, r in enumerate(view.images)}
    records = {r.light: r for r in view.lit_images()}
    if result.light_ids.tolist() == [-1]:  # the projector: its white frame is the "lit image"
        from slscan.albedo.projector_light import flat_frame_records

        records = {-1: flat_frame_records(session, view)[0]}
    for i, light in enumerate(result.light_ids):
        record = records[int(light)]
        rlog.log_lit_image(
            rec,
            session.read_image(view, record),
            view_index=view_index,
            frame_index=frames[record.file],
            light=int(light),
            shadow=result.shadow[i],
            highlight=result.highlight[i],
        )
    rlog.log_unshaded(rec, result.albedo, result.valid, view_index=view_index, normal=result.normal)
    if truth is not None:
        rlog.log_albedo_error(rec, result.albedo, truth, result.valid, view_index=view_index)
    rlog.log_albedo_mesh(
        rec,
        range_map.vertices,
        range_map.faces,
        range_map.normals,
        result.vertex_albedo,
        view_index=view_index,
    )
    if isinstance(lights, LightCalibration):
        rlog.log_lights(rec, lights)
    rlog.log_albedo_metrics(rec, result.metrics, view_index=view_index)


# --- files -------------------------------------------------------------------------------------


def write_albedo_ply(range_map: RangeMap, per_vertex: np.ndarray, path: str | os.PathLike) -> Path:
    """The range map with albedo, as a binary PLY that MeshLab opens, atomically.

    Vertex properties: those of :func:`slscan.decode.rangemap.write_ply` with
    ``red green blue`` replaced by the 8-bit sRGB albedo (black where unknown), plus
    ``albedo_red albedo_green albedo_blue`` (float, linear, NaN where unknown).
    """
    from dataclasses import replace

    from slscan.decode.rangemap import write_ply

    extra = {f"albedo_{c}": per_vertex[:, i] for i, c in enumerate(("red", "green", "blue"))}
    return write_ply(replace(range_map, colors=srgb8(per_vertex)), path, extra=extra)


def range_map_files(range_maps_dir: str | os.PathLike) -> dict[str, Path]:
    """View name → range-map PLY, from ``DIR/range_maps.json`` (or ``DIR/VIEW.ply`` files)."""
    folder = Path(range_maps_dir)
    if not folder.is_dir():
        raise SlscanError(f"{folder}: range-map folder not found")
    index = folder / "range_maps.json"
    if index.is_file():
        meta = read_json(index, "range-map index")
        try:
            return {e["view"]: folder / e["file"] for e in meta["views"]}
        except (KeyError, TypeError):
            raise SlscanError(
                f"{index}: expected a 'views' list of {{view, file}} entries"
            ) from None
    return {p.stem: p for p in glob_results(folder, "*.ply")}


def load_range_map(range_maps_dir: str | os.PathLike, view: ViewRecord) -> tuple[RangeMap, str]:
    """The range map of ``view`` from a decode output folder, checked to be of that view."""
    files = range_map_files(range_maps_dir)
    if view.name not in files:
        raise SlscanError(
            f"{range_maps_dir}: no range map of view {view.name!r} (it has {', '.join(sorted(files)) or 'none'})"
        )
    path = files[view.name]
    range_map = read_ply(path)
    _check_range_map(range_map, view, str(path))
    return range_map, str(path)


def _left_out_by_decode(range_maps_dir: str | os.PathLike) -> dict[str, str]:
    """Views decode found unusable (``left_out`` of ``range_maps.json``): name → reason."""
    index = Path(range_maps_dir) / "range_maps.json"
    if not index.is_file():
        return {}
    meta = read_json(index, "range-map index")
    left_out = meta.get("left_out", {}) if isinstance(meta, dict) else {}
    return {str(k): str(v) for k, v in left_out.items()} if isinstance(left_out, dict) else {}


def _why_unusable(result: ViewAlbedo, light: str = "ring") -> str | None:
    """Why a view's albedo is unusable, in words, or None when it is usable."""
    images = "white frame is" if light == "projector" else "lit images are"
    if not result.valid.any():
        if light == "projector":
            return "no pixel is lit by the projector well enough (its white frame is dark, saturated or shadowed)"
        return "no pixel has enough usable lights (its lit images are dark or saturated)"
    if not np.nanmax(result.albedo[result.valid]) > 0:
        return f"its {images} black over the range map (no lit pixels)"
    return None


def _albedo_task(task: tuple) -> tuple[AlbedoSummary, ViewAlbedo | None, RangeMap | None, str]:
    """Un-shade one view and write its files (runs in a worker process); the full result
    and range map come back only when ``full`` (for logging), the summary always."""
    session, view_name, range_maps_dir, lights, config, folder, full = task
    view = session.view(view_name)
    range_map, source = load_range_map(range_maps_dir, view)
    if isinstance(lights, ProjectorLight):
        from slscan.albedo.projector_light import projector_albedo_view

        result = projector_albedo_view(session, view, range_map, lights, config, range_map_source=source)
    else:
        result = albedo_view(session, view, range_map, lights, config, range_map_source=source)
    folder = Path(folder)
    write_png(folder / f"{view.name}_albedo.png", albedo_png(result.albedo, result.valid))
    write_png(folder / f"{view.name}_valid.png", (result.valid * 255).astype(np.uint8))
    write_albedo_ply(range_map, result.vertex_albedo, folder / f"{view.name}.ply")
    summary = AlbedoSummary.of(result)
    return (summary, result, range_map, source) if full else (summary, None, None, source)


def choose_light(
    session: Session, lights: LightCalibration | None, config: AlbedoConfig
) -> tuple[str, str]:
    """Which light the albedo of ``session`` comes from, and why, in words.

    "ring" when forced (``config.light``), or under "auto" when the session has lit
    images and the ring lights are known (a light calibration with lights, or the
    session's rig description; a view with too few lit images is then an error, not a
    silent change of light); "projector" otherwise (forced, no lit images: the real-rig
    default, or no known ring lights). Raises when the forced ring cannot be had.
    """
    lit = max((len(v.lit_images()) for v in session.views), default=0)
    known = (lights is not None and len(lights.lights) > 0) or (
        lights is None and session.calibration is not None and bool(session.calibration.lights)
    )
    if config.light == "ring":
        if not known:
            raise SlscanError(
                f"{session.root}: no light calibration given and the session describes no lights "
                "(--light ring needs calibrated ring lights: slscan calibrate-lights)"
            )
        return "ring", "forced (light = ring)"
    if config.light == "projector":
        return "projector", "forced (light = projector)"
    if lit and known:
        return "ring", "the session has lit images and the ring lights are known"
    if not lit:
        return "projector", "no view has lit images (a rig without ring lights)"
    return "projector", "the ring lights are not known (no light calibration, none in the session's rig)"


def albedo_session(
    session: Session | str | os.PathLike,
    range_maps_dir: str | os.PathLike,
    out: str | os.PathLike,
    *,
    lights: LightCalibration | str | os.PathLike | None = None,
    config: AlbedoConfig | None = None,
    overwrite: bool = False,
    rec=None,
    progress: Callable[[str], None] | None = None,
    executor: Executor = LOCAL,
) -> list[AlbedoSummary]:
    """Un-shade every view of a session into folder ``out``, atomically; a summary per
    usable view (the images are in ``out``: :func:`slscan.colour.read_albedo_png`).

    Per view writes ``VIEW_albedo.png`` (16-bit **linear** RGB, ``albedo * 65535``, 0
    where invalid), ``VIEW_valid.png`` (8-bit mask, 255 valid) and ``VIEW.ply`` (the
    range map with per-vertex albedo); and ``albedo.json`` (lights, settings, per-view
    metrics and specular lobe).

    lights : a :class:`LightCalibration` or the path of ``LIGHTS.json``; default: the
        session's rig description (nominal lights, no ambient; a warning says so)
    config : its ``light`` chooses the ring lights or the projector (:func:`choose_light`);
        the projector light is ``lights.projector`` when calibrated, else nominal
    config : default :class:`AlbedoConfig`
    rec : an ``rr.RecordingStream`` (logged from this process, view by view), or None
    executor : where the views are un-shaded: local processes (default), or a Dask
        cluster whose workers can read the session and range-map folders
    """
    config = config or AlbedoConfig()
    if not isinstance(session, Session):
        session = load_session(session)
    executor.start(len(session.views), [__name__, "open3d"])  # they import while we check
    if lights is not None and not isinstance(lights, LightCalibration):
        lights_source = str(Path(lights).resolve())
        lights = read_lights(lights)
    elif isinstance(lights, LightCalibration):
        lights_source = lights.fit.get("source", "given")
    else:
        lights_source = "session rig description"
    light, choice = choose_light(session, lights, config)
    log.info("albedo light: %s (%s)", light, choice)
    if light == "projector":
        from slscan.albedo.projector_light import flat_frame_records, projector_light_of

        if session.calibration is None:
            raise SlscanError(
                f"{session.root / 'session.json'}: no calibration; the projector as the light needs the "
                "projector's centre (calibrate the rig, or decode with a calibration)"
            )
        light_model = projector_light_of(session, lights)
        if lights is None or lights.projector is None:
            lights_source = light_model.source
        if not light_model.calibrated:
            log.warning(
                "projector light not calibrated (no 'projector' block in the light calibration): albedo is "
                "relative to the projector's white at %.0f mm, not absolute", light_model.reference_distance
            )
        for view in session.views:  # fail before any work on a view that cannot be done
            flat_frame_records(session, view)
    else:
        if lights is None:
            log.warning(
                "no light calibration given: using the session's nominal lights (no ambient light)"
            )
            lights = LightCalibration.from_rig(session.calibration)
        light_model = lights
        for view in session.views:  # fail before any work on a view that cannot be done
            if len(view.lit_images()) < config.min_lights:
                raise SlscanError(
                    f"{session.root / view.name}: {len(view.lit_images())} lit image(s); albedo needs at least "
                    f"{config.min_lights} (or the projector as the light: --light projector)"
                )
            for r in view.lit_images():
                if r.light >= len(lights.lights):
                    raise SlscanError(
                        f"{session.root / view.name / r.file}: lit by light {r.light}, which the light "
                        f"calibration lacks (it has {len(lights.lights)} lights)"
                    )
    left_out = _left_out_by_decode(range_maps_dir)
    views = [view for view in session.views if view.name not in left_out]
    for name, why in left_out.items():
        log.warning("%s: left out (decode found the view unusable: %s)", name, why)
    if not views:
        raise SlscanError(f"{range_maps_dir}: no view has a range map (decode left every view out)")
    for view in views:  # a missing or mismatched range map fails before any work
        load_range_map(range_maps_dir, view)
    results = []
    entries = []
    unusable = {}
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        tasks = [
            (session, view.name, range_maps_dir, light_model, config, tmp, rec is not None) for view in views
        ]
        done = executor.map(_albedo_task, tasks)
        for index, (view, (summary, result, range_map, source)) in enumerate(zip(views, done)):
            if rec is not None:
                _log_view(rec, session, view, result, range_map, light_model, index)
            if progress:
                progress(view.name)
            why = summary.unusable
            if why:
                unusable[view.name] = why
                log.warning("%s: unusable view, left out: %s", view.name, why)
                for suffix in ("_albedo.png", "_valid.png", ".ply"):
                    (tmp / f"{view.name}{suffix}").unlink(missing_ok=True)
                continue
            entries.append(
                {
                    "view": view.name,
                    "image": f"{view.name}_albedo.png",
                    "valid": f"{view.name}_valid.png",
                    "mesh": f"{view.name}.ply",
                    "range_map": source,
                    "light": summary.light,
                    "lights_used": list(summary.light_ids),
                    "specular": summary.lobe.to_dict(),
                    "metrics": summary.metrics,
                    "seconds": summary.seconds,
                }
            )
            results.append(summary)
        if not entries:
            reasons = "; ".join(f"{name}: {why}" for name, why in unusable.items())
            raise SlscanError(f"{session.root}: no usable view for albedo ({reasons})")
        write_json(
            tmp / "albedo.json",
            {
                "format": ALBEDO_FORMAT,
                "version": ALBEDO_VERSION,
                "written_by": f"slscan {__version__}",
                "session": str(Path(session.root).resolve()),
                "range_maps": str(Path(range_maps_dir).resolve()),
                "encoding": "VIEW_albedo.png: 16-bit linear RGB reflectance x 65535 (not sRGB), 0 where "
                "VIEW_valid.png is 0; VIEW.ply: vertex colour 8-bit sRGB, albedo_* float linear",
                "light": light,
                "light_choice": choice,
                "lights_source": lights_source,
                **({"lights": light_model.to_dict()} if light == "ring" else {}),
                **({"projector_light": light_model.to_dict()} if light == "projector" else {}),
                "config": asdict(config),
                "views": entries,
            },
        )
    return results
