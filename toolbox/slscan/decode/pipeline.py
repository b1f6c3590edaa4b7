"""The decode stage end to end: a capture session in, one range map (PLY) per view out.

Per view: decode the patterns (hybrid green lines or Gray-code edges) to
:class:`~slscan.decode.samples.StripeSamples`, intersect their camera rays with the
projector's light planes, mesh the points on their (row × stripe) grid. Writes
``VIEW.ply`` per view and ``range_maps.json`` (what was decoded, how, and per-view
metrics) into the output folder, atomically; with ``codes`` also the projector column/row
maps of Gray-code sets (:mod:`slscan.decode.codes`).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from slscan import __version__
from slscan.capture.session import SESSION_FILE, Session, ViewRecord, load_session
from slscan.decode.budget import fit_workers, warn_if_lossy
from slscan.decode.codes import (
    PNG_ENCODING,
    ProjectorCodes,
    ValidShare,
    decode_codes,
    require_codes,
    write_codes_manifest,
    write_view_codes,
)
from slscan.decode.family import DisplayMap
from slscan.decode.graycode import THRESHOLD_MODES
from slscan.decode.hybrid import (
    DEFAULT_ESTIMATOR,
    DEFAULT_MAX_LINE_SIGMA,
    DEFAULT_MIXING,
    DEFAULT_PAINT_EDGES,
    ESTIMATORS,
    MIXING_MODES,
    PAINT_EDGE_METRIC,
    PAINT_EDGE_SHIFT,
    paint_edge_mode,
)
from slscan.decode.rangemap import (
    MAX_EDGE_FACTOR,
    MAX_GAP_COLUMNS,
    MAX_VIEW_ANGLE_DEG,
    RangeMap,
    build_range_map,
    write_ply,
)
from slscan.decode.samples import LightPlanes, StripeSamples
from slscan.decode.triangulate import (
    AXES,
    RigPlanes,
    TriangulationReport,
    triangulate,
    triangulation_report,
)
from slscan.errors import SlscanError
from slscan.executor import LOCAL, Executor
from slscan.fsio import atomic_output_dir, write_json
from slscan.patterns import decodable, families_in, family

log = logging.getLogger(__name__)

METHODS = ("auto", *decodable())
RANGE_MAPS_FORMAT = "slscan.range-maps"
RANGE_MAPS_VERSION = 1


@dataclass(frozen=True)
class DecodeConfig:
    """How the decode stage turns captures into range maps."""

    method: str = "auto"
    """{"auto", "phase", "hybrid", "gray"} (:func:`slscan.patterns.decodable`): which
    patterns to decode; "auto" takes phase shifting when the session has it, else the
    hybrid pattern, else Gray code, and passes over the hybrid for lossy (JPEG) sessions
    that have another family (:func:`choose_method`)."""
    estimator: str = DEFAULT_ESTIMATOR
    """Sub-pixel medial-axis estimator of the hybrid green lines (see ``decode.hybrid``)."""
    max_edge_factor: float = MAX_EDGE_FACTOR
    """Mesh edges longer than this many times the expected spacing are cut (depth jumps)."""
    max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG
    """Triangles seen more obliquely than this are dropped (grazing angles)."""
    max_gap_columns: float = MAX_GAP_COLUMNS
    """Stripes missing in a row are bridged by the mesh up to this many projector columns
    (hybrid lines are 2 columns apart, Gray-code edges 1)."""
    trim_line_ends: int = 0
    """Samples dropped at either end of every line (and lone samples, from 1): line ends
    are 2-3x less accurate; trimming one row trades coverage for accuracy (see
    ``benchmarks/reconstruction.py``). 0 keeps them, at lower quality."""
    mixing: str = DEFAULT_MIXING
    """{"pixel", "global"}: hybrid colour unmixing per pixel from the session's own bands
    (holds on saturated paint under physical colour), or one crosstalk matrix per view
    (the decoder before 2026-11); see ``decode.hybrid.estimate_mixing``."""
    global_light: bool = False
    """Hybrid: estimate the global (indirect) light from the finest levels (Nayar et al.
    2006), take it out of the line signal and bands, drop samples with little direct light
    (needs ``mixing="pixel"``)."""
    paint_edges: bool | str = DEFAULT_PAINT_EDGES
    """Hybrid, with ``mixing="pixel"``: {"shift", "drop", "keep"}, the line samples beside a
    paint edge. "shift" (default) drops only those whose centre the paint moves by more than
    ``decode.hybrid.PAINT_EDGE_SHIFT`` px (the centre read pixel by pixel and in the centre
    pixel's paint disagree); "drop" (or true, the default before issue #35) drops every one,
    which punches a hole at every paint boundary; "keep" (or false) keeps all. The count
    dropped is each view's ``paint_edge_samples_dropped`` in ``range_maps.json`` and one log
    line. Demo at half size (``benchmarks/paint_edges.py --demo 0.5``): fused-mesh holes
    201 ("drop"), 107 ("shift"), 101 ("keep")."""
    paint_edge_shift: float = PAINT_EDGE_SHIFT
    """Hybrid, ``paint_edges="shift"``: camera px the paint may move a line's centre before
    the sample is dropped (``benchmarks/paint_edges.py --variant
    s=paint_edges:shift,paint_edge_shift:0.1``)."""
    max_line_sigma: float = DEFAULT_MAX_LINE_SIGMA
    """Hybrid: line samples whose expected axis standard deviation (camera px), from the
    line's contrast against the image noise, exceeds this are dropped ("weak line": e.g.
    the green line on saturated red or blue paint); 0 keeps all (``decode.hybrid``,
    ``line_axis_sigma``)."""
    gray_threshold: str = "adaptive"
    """{"adaptive", "opencv"}: Gray-code bit thresholds from the images' noise and contrast
    (in linear light), or OpenCV ``GrayCodePattern``'s fixed rule (40 DN white - black, 5 DN
    per bit, on the grey captures as stored; its mask is OpenCV's, so ``gray_robust`` does
    not apply); see ``decode.graycode``."""
    gray_robust: bool = True
    """Gray-code pixels whose code global light may have corrupted (a bit failing Gupta's
    direct/global rule) or that disagree with their neighbours are left out instead of
    giving wrong 3D points (``decode.graycode``, ``robust``); False: the decoder as before.
    Adaptive thresholds only."""

    @property
    def gray_robust_applied(self) -> bool:
        """``gray_robust`` as the Gray-code decoder gets it: off under OpenCV's rule."""
        return self.gray_robust and self.gray_threshold == "adaptive"
    gray_smooth: bool = True
    """Gray code: average each edge position with the same edge on the rows (columns)
    either side, ``[1, 2, 1] / 4`` (:meth:`StripeSamples.smoothed`), as the hybrid decoder
    filters its line signal across rows: each row's crossing is found from that row alone,
    and its noise (sensor, JPEG) drops to about 0.6 of itself. Mean error at full size
    (``benchmarks/light_transport.py --decoders robust,robust@gray_smooth=false``):
    concave corner 0.034 -> 0.023 mm, bronze 0.056 -> 0.052, figurine 0.051 -> 0.050;
    False: every edge from its own row, as before."""
    gray_drop_bits: int = 0
    """Gray code: a pixel whose finest bits are weak or unreliable (subsurface scattering
    washes out the finest stripes) keeps the coarser code of its leading run of good bits
    when at most this many are dropped (``decode.graycode``, ``drop_bits``); its edges come
    only between blocks of ``2**dropped`` columns, which the mesh bridges. 0: every bit or none."""
    projector_axes: str = "auto"
    """{"auto", "columns", "both"}: the projector coordinates triangulated with a calibrated
    inverse-camera projector. "both": each sample's column and row, least squares, each
    axis weighted by its measured noise (phase shifting with row fringes; Gray code with
    row codes, each column edge given its row interpolated from the row edges, which
    costs a second decode of the captures). "auto": both where the geometry makes the
    rows worth it (``decode.triangulate.choose_axes``: the median depth noise at least
    1.25x smaller than with the columns alone; a projector above or below the camera),
    else the columns. Light planes have only columns. The choice and the depth noise per
    projector pixel of each axis are reported per view (``range_maps.json``)."""
    phase_min_modulation: float = 0.15
    """Phase shifting: a pixel's fringe amplitude ``2 B`` must exceed this share of its white
    minus black (defocus, subsurface scattering and global light lower it; below, the phase
    is mostly noise); ``decode.phase``, ``MIN_MODULATION``."""
    projector_gamma: float | str | None = "auto"
    """Phase shifting: the projector's response exponent (emitted light = value ** gamma),
    measured by ``slscan response``: fringes pre-distorted for another value (their
    description's ``gamma``, 1 when not) have their phase corrected for the harmonics the
    mismatch leaves (``decode.phase_gamma``); "auto": estimated per view from the
    captures, used when they clearly show it (``decode.phase.GAMMA_EVIDENCE``); None or
    "none": no correction."""

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SlscanError(
                f"unknown decode method {self.method!r}: expected one of {', '.join(METHODS)}"
            )
        if self.estimator not in ESTIMATORS:
            raise SlscanError(
                f"unknown estimator {self.estimator!r}: expected one of {', '.join(ESTIMATORS)}"
            )
        if self.mixing not in MIXING_MODES:
            raise SlscanError(
                f"unknown mixing {self.mixing!r}: expected one of {', '.join(MIXING_MODES)}"
            )
        paint_edge_mode(self.paint_edges)  # raises naming the modes
        if not self.paint_edge_shift >= 0:
            raise SlscanError(f"paint_edge_shift must be >= 0 camera px, got {self.paint_edge_shift!r}")
        if self.gray_threshold not in THRESHOLD_MODES:
            raise SlscanError(
                f"unknown gray_threshold {self.gray_threshold!r}: expected one of "
                f"{', '.join(THRESHOLD_MODES)}"
            )
        if self.projector_axes not in AXES:
            raise SlscanError(
                f"unknown projector_axes {self.projector_axes!r}: expected one of {', '.join(AXES)}"
            )
        if isinstance(self.gray_drop_bits, bool) or not isinstance(self.gray_drop_bits, int) \
                or self.gray_drop_bits < 0:
            raise SlscanError(f"gray_drop_bits must be an integer >= 0, got {self.gray_drop_bits!r}")
        for name in ("max_edge_factor", "max_gap_columns"):
            if not getattr(self, name) > 0:
                raise SlscanError(f"{name} must be positive, got {getattr(self, name)!r}")
        if not (isinstance(self.phase_min_modulation, (int, float)) and 0 <= self.phase_min_modulation < 2):
            raise SlscanError(
                f"phase_min_modulation must be in [0, 2) (share of white - black), got {self.phase_min_modulation!r}"
            )
        if self.projector_gamma == "none":
            object.__setattr__(self, "projector_gamma", None)
        if self.projector_gamma not in (None, "auto") and (isinstance(self.projector_gamma, bool) or not (
                isinstance(self.projector_gamma, (int, float)) and 0.2 <= self.projector_gamma <= 5)):
            raise SlscanError(f"projector_gamma must be auto, none or in [0.2, 5], got {self.projector_gamma!r}")
        if not (isinstance(self.max_line_sigma, (int, float)) and self.max_line_sigma >= 0):
            raise SlscanError(
                f"max_line_sigma must be >= 0 camera px (0: off), got {self.max_line_sigma!r}"
            )
        if not 0 < self.max_view_angle_deg <= 90:
            raise SlscanError(
                f"max_view_angle_deg must be in (0, 90] degrees, got {self.max_view_angle_deg!r}"
            )
        if not (isinstance(self.trim_line_ends, int) and self.trim_line_ends >= 0):
            raise SlscanError(
                f"trim_line_ends must be a whole number of rows >= 0, got {self.trim_line_ends!r}"
            )


@dataclass(frozen=True)
class ViewDecode:
    """Everything the decode stage found in one view.

    samples : decoded features; points : (k, 3) float64 mm rig frame (NaN: no intersection)
    range_map : the meshed range surface
    mask : (h, w) bool decodable pixels; codes : (h, w) int display map (hybrid region code
        or Gray-code column, -1 where invalid), up to ``code_max``
    saturated : (h, w) bool pixels clipped (white frame for hybrid; any image for Gray)
    white : the white-frame capture the range map's colours come from
    projector_codes : the projector column/row maps, when asked for (Gray-code sets)
    valid_share : what limited the decoded share (Gray-code decoding)
    maps : further per-pixel maps of the family's decoder
        (:class:`~slscan.decode.family.DisplayMap`), by entity path under
        ``world/camera/image/decode`` (streamed to the viewer; :func:`decode_session` keeps
        them only until then)
    stats : further per-view numbers of the family's decoder (in ``metrics``)
    features : the samples are features drawn as stripe axes (False: one per pixel)
    triangulation : the projector model and axes that triangulated the view, and how well
        each axis pins depth there (in ``metrics`` and ``range_maps.json``)
    """

    view: str
    method: str
    samples: StripeSamples
    points: np.ndarray
    range_map: RangeMap
    mask: np.ndarray
    codes: np.ndarray
    code_max: int
    saturated: np.ndarray
    white: np.ndarray
    seconds: dict[str, float] = field(default_factory=dict)
    projector_codes: ProjectorCodes | None = None
    valid_share: ValidShare | None = None
    maps: dict[str, DisplayMap] = field(default_factory=dict)
    stats: dict[str, float] = field(default_factory=dict)
    features: bool = True
    triangulation: TriangulationReport | None = None

    @property
    def metrics(self) -> dict[str, float]:
        n = len(self.samples)
        return {
            **self.stats,
            **({} if self.triangulation is None else self.triangulation.metrics()),
            "samples": float(n),
            "vertices": float(len(self.range_map.vertices)),
            "faces": float(len(self.range_map.faces)),
            "mask_share": float(self.mask.mean()),
            "saturated_sample_share": float(self.samples.saturated.mean()) if n else 0.0,
            "triangulated_share": float(np.isfinite(self.points[:, 0]).mean()) if n else 0.0,
        }


LOSSY_HYBRID_ERROR = (
    "on the virtual rig, JPEG at quality 90 with 4:2:0 chroma, the hybrid pattern's mean error "
    "rose from 0.13 to 0.89 mm with 32 % of points more than 1 mm off (Gray code: 0.12 to 0.15 mm; "
    "benchmarks/light_transport.py --effects none,jpeg)"
)
"""What lossy captures measurably cost the hybrid decoder (``choose_method``'s reasons)."""

_told: set[tuple[str, str]] = set()  # (session root, message kind) already logged


def _once(session: Session, kind: str) -> bool:
    key = (str(session.root), kind)
    if key in _told:
        return False
    _told.add(key)
    return True


def choose_method(session: Session, method: str = "auto") -> str:
    """The pattern family to decode ``session`` with: the one asked, or with "auto" the
    family present with the highest priority (:func:`slscan.patterns.families`: phase
    shifting, then the hybrid pattern, then Gray code), except that a lossy (JPEG) session
    passes over a family that does not survive lossy compression (the hybrid pattern: its
    one-pixel green lines and thin bands smear in 4:2:0 chroma) when another one is present
    (logged once per session). A lossy session with only the hybrid pattern is decoded with
    it, with one warning naming the measured cost (:data:`LOSSY_HYBRID_ERROR`)."""
    present = families_in(session.patterns)
    if not present:
        found = sorted({p.family for p in session.patterns}) or ["none"]
        raise SlscanError(f"{session.root}: the session has no coded patterns to decode (families: {', '.join(found)})")
    if method == "auto":
        chosen = present[0]
        if session.lossy and not chosen.lossy:
            fallback = next((f for f in present if f.lossy), None)
            if fallback is not None:
                if _once(session, "auto"):
                    log.info("%s: decoding the %s patterns, not the %s: the captures are lossy (JPEG), and %s",
                             session.root, _name(fallback.name), _name(chosen.name), LOSSY_HYBRID_ERROR)
                chosen = fallback
        method = chosen.name
    if method not in {f.name for f in present}:
        raise SlscanError(f"{session.root}: the session has no {method} patterns to decode")
    if session.lossy and not family(method).lossy and all(not f.lossy for f in present) \
            and _once(session, "lossy " + method):
        log.warning("%s: decoding the %s pattern from lossy (JPEG) captures: expect large errors; %s. "
                    "Capture PNG, or add Gray-code patterns (auto then decodes those)",
                    session.root, method, LOSSY_HYBRID_ERROR)
    return method


def _name(family_name: str) -> str:
    """A family's name in a sentence."""
    return {"gray": "Gray-code", "phase": "phase-shifting"}.get(family_name, family_name)


def decode_view(
    session: Session,
    view: ViewRecord | str,
    config: DecodeConfig = DecodeConfig(),
    *,
    planes: LightPlanes | None = None,
    with_codes: bool = False,
) -> ViewDecode:
    """Decode one view of ``session`` to a range map (rig frame, mm).

    planes : the projector's light planes; default: from the session's calibration
    with_codes : also keep the projector column/row maps (``projector_codes``); the session
        needs patterns that give them (Gray code, phase shifting; decoded apart when the
        range map comes from another family)
    """
    view = session.view(view) if isinstance(view, str) else view
    rig = session.calibration
    if rig is None:
        raise SlscanError(
            f"{session.root}: the session has no calibration, so its light planes are unknown "
            "(calibrate the rig first; `slscan decode --codes` or slscan.decode.codes.decode_codes_session "
            "writes the projector column/row maps of a Gray-code set without one)"
        )
    planes = planes or RigPlanes(rig.projector)
    method = choose_method(session, config.method)
    seconds = {}
    t = time.perf_counter()
    # light planes have no rows: the decoder need not find them
    fam_config = config if isinstance(planes, RigPlanes) else replace(config, projector_axes="columns")
    res = family(method).decode_module().decode(session, view, fam_config)
    samples = res.samples
    if fam_config.projector_axes == "columns" and samples.projector_row is not None:
        samples = replace(samples, projector_row=None)  # rows decoded (phase shifting) but not wanted
    if config.trim_line_ends:
        samples = samples.trim_line_ends(config.trim_line_ends)
    seconds["decode"] = time.perf_counter() - t
    projector_codes, share = res.projector_codes if with_codes else None, res.valid_share
    if with_codes and projector_codes is None:
        projector_codes = decode_codes(session, view, config)
        share = projector_codes.valid_share
    t = time.perf_counter()
    noise = (res.stats.get("column_noise_px", float("nan")), res.stats.get("row_noise_px", float("nan")))
    # each axis weighted by its measured noise (equal weights where not measured)
    sigma = tuple(float(n) if np.isfinite(n) and n > 0 else 1.0 for n in noise)
    points = triangulate(samples, rig.camera, planes, sigma=sigma)
    seconds["triangulate"] = time.perf_counter() - t
    report = triangulation_report(samples, points, rig.camera, rig.projector, planes, sigma=noise,
                                  rows_missing=float(res.stats.get("rows_missing_share", 0.0)))
    t = time.perf_counter()
    range_map = build_range_map(
        samples,
        points,
        white_image=res.white,
        camera=rig.camera,
        view=view.name,
        max_edge_factor=config.max_edge_factor,
        max_view_angle_deg=config.max_view_angle_deg,
        max_gap_columns=res.max_gap_columns or config.max_gap_columns,
    )
    seconds["mesh"] = time.perf_counter() - t
    if len(range_map.faces) == 0:
        log.info("%s: the range map has no faces (%d samples)", view.name, len(samples))
    return ViewDecode(
        view=view.name, method=method, samples=samples, points=points, range_map=range_map,
        mask=res.mask, codes=res.codes, code_max=res.code_max, saturated=res.saturated, white=res.white,
        seconds=seconds, projector_codes=projector_codes, valid_share=share, maps=dict(res.maps),
        features=res.features, stats=dict(res.stats), triangulation=report,
    )


def _why_unusable(result: ViewDecode) -> str:
    """Why a view gave an empty range map, in words (for the warning naming it)."""
    clipped = float(result.saturated.mean()) if result.saturated.size else 0.0
    if clipped > 0.5:
        return f"{clipped:.0%} of its pixels are saturated (clipped); lower the exposure"
    if not result.mask.any():
        return "no lit pixels (nothing decodable: is the projector on and the object in view?)"
    return f"its {len(result.samples)} decoded samples give no range-map faces"


def _decode_task(task: tuple) -> ViewDecode:
    """Decode one view and write its PLY, and its codes when asked (runs in a worker process);
    the decoder's display maps come back only when they are ``shown`` (streamed)."""
    session, view_name, config, planes, folder, codes, shown = task
    result = decode_view(session, session.view(view_name), config, planes=planes, with_codes=codes)
    write_ply(result.range_map, Path(folder) / f"{view_name}.ply")
    if result.projector_codes is not None:
        write_view_codes(result.projector_codes, Path(folder) / view_name)
    return result if shown else replace(result, maps={})


def decode_session(
    session: Session | str | os.PathLike,
    out: str | os.PathLike,
    config: DecodeConfig = DecodeConfig(),
    *,
    overwrite: bool = False,
    rec=None,
    progress: Callable[[str], None] | None = None,
    planes: LightPlanes | None = None,
    executor: Executor = LOCAL,
    codes: bool = False,
) -> list[ViewDecode]:
    """Decode every view of a capture session into ``out/VIEW.ply`` and ``out/range_maps.json``.

    With ``codes``, also the projector column/row maps ``out/VIEW/{columns,rows,mask}.png``
    and ``out/projector_codes.json`` (:mod:`slscan.decode.codes`; Gray-code sets only).

    The session is validated (every image against its metadata) before anything is written.
    rec : an ``rr.RecordingStream`` for masks, codes, stripe axes, range maps and metrics
    planes : the projector's light planes (a measured calibration); default: the session's
    executor : where the views are decoded: local processes (default), or a Dask cluster
        whose workers can read the session's folder
    """
    from slscan.viewer import log_decode as rlog
    from slscan.viewer.log import log_capture

    if not isinstance(session, Session):
        session = load_session(session)
    if not session.views:
        raise SlscanError(f"{session.root / SESSION_FILE}: the session has no views; expected at least one")
    if codes:
        require_codes(session)
    executor = fit_workers(executor, session)
    warn_if_lossy(session)
    # the method chosen (and why, said) once here, not in every worker
    chosen = replace(config, method=choose_method(session, config.method))
    executor.start(len(session.views), [__name__])  # helper processes import while we set up
    results = []
    unusable = {}
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        entries = []
        code_entries = []  # every view's, usable or not: codes do not need a range map
        encoding = PNG_ENCODING  # how the code maps are stored (phase shifting: float TIFF)
        tasks = [(session, view.name, chosen, planes, tmp, codes, rec is not None) for view in session.views]
        for index, (view, result) in enumerate(zip(session.views, executor.map(_decode_task, tasks))):
            if rec is not None:
                rm = result.range_map
                rlog.log_decode_maps(rec, view_index=index, mask=result.mask, codes=result.codes,
                                     code_max=result.code_max, saturated=result.saturated)
                log_capture(rec, result.white, view_index=index, frame_index=0, label="white")
                if result.features:  # per-pixel samples are shown as maps, not as stripe axes
                    rlog.log_stripes(rec, result.samples, view_index=index)
                rlog.log_range_map(rec, rm.vertices, rm.faces, rm.normals, rm.colors, view_index=index)
                rlog.log_display_maps(rec, result.maps, view_index=index)
                rlog.log_metrics(rec, result.metrics, view_index=index, marked=result.stats)
                _log_codes(rec, result, index)
                result = replace(result, maps={})  # streamed: not kept for every view
            if progress:
                progress(view.name)
            if result.projector_codes is not None:
                code_entries.append(_codes_entry(result))
                encoding = result.projector_codes.encoding
            if len(result.range_map.faces) == 0:
                unusable[view.name] = _why_unusable(result)
                log.warning("%s: unusable view, left out: %s", view.name, unusable[view.name])
                (tmp / f"{view.name}.ply").unlink(missing_ok=True)
                continue
            entries.append({
                "view": view.name, "file": f"{view.name}.ply", "method": result.method,
                "rig_from_object": None if view.rig_from_object is None else view.rig_from_object.tolist(),
                "metrics": result.metrics, "seconds": result.seconds,
                **({} if result.triangulation is None else {"triangulation": result.triangulation.to_dict()}),
            })
            results.append(result)
        if codes:
            write_codes_manifest(tmp, session, code_entries, encoding=encoding)
        if not entries:
            reasons = "; ".join(f"{name}: {why}" for name, why in unusable.items())
            raise SlscanError(f"{session.root}: no usable view ({reasons})")
        notes = [note] if (note := paint_edge_note(results)) else []
        for line in notes:
            log.info("%s: %s", session.root, line)
        write_json(tmp / "range_maps.json", {
            "format": RANGE_MAPS_FORMAT, "version": RANGE_MAPS_VERSION, "written_by": f"slscan {__version__}",
            "session": str(Path(session.root).resolve()), "frame": "rig (camera) frame, mm",
            "light_planes": repr(planes) if planes is not None else "session calibration",
            "config": asdict(config), "views": entries,
            **({"left_out": unusable} if unusable else {}),
            **({"notes": notes} if notes else {}),
        })
    _hint_drop_bits(results, config)
    _hint_washed_lines(results, session)
    return results


def paint_edge_note(results: Sequence[ViewDecode]) -> str:
    """"paint edges: N line samples dropped ..." when the hybrid decoder left line samples out
    at paint edges (``DecodeConfig.paint_edges``; each view's count is its
    ``paint_edge_samples_dropped`` metric), else ""."""
    dropped = {r.view: int(r.stats.get(PAINT_EDGE_METRIC, 0)) for r in results}
    total = sum(dropped.values())
    if total == 0:
        return ""
    kept = sum(len(r.samples) for r in results)
    return (f"paint edges: {total} line samples dropped ({100.0 * total / max(total + kept, 1):.1f} % of those "
            f"found) in {sum(n > 0 for n in dropped.values())} of {len(results)} views, where a paint edge "
            "crosses the green line's profile and moves its centre")


def _few(names: Sequence[str], shown: int = 5) -> str:
    """The first ``shown`` view names for a warning, "..." for the rest."""
    return ", ".join(names[:shown]) + (", ..." if len(names) > shown else "")


THIN_SAMPLES_SHARE = 0.5
"""A hybrid view whose line samples reach less than this share of its lit pixels
(:meth:`StripeSamples.sampled_share`) gets the :func:`_hint_washed_lines` warning: 0.11 on
the virtual marble bust under subsurface scattering, 0.95 under direct light."""


def _hint_washed_lines(results: Sequence[ViewDecode], session: Session) -> None:
    """One warning when hybrid views' green lines reach little of the lit surface: lines
    one projector pixel wide wash out under subsurface scattering (marble, alabaster, wax)
    or strong defocus, where Gray code with bit dropping still decodes."""
    thin = [(r.view, share) for r in results if r.method == "hybrid"
            for share in [r.samples.sampled_share(r.mask)] if share < THIN_SAMPLES_SHARE]
    if not thin:
        return
    has_gray = any(p.family == "gray" for p in session.patterns)
    remedy = ("decode the session's Gray-code patterns instead (--method gray --gray-drop-bits 2; "
              "[decode] method = \"gray\", gray_drop_bits = 2)" if has_gray else
              "capture Gray-code patterns too (slscan capture --patterns both) and decode those "
              "with --method gray --gray-drop-bits 2")
    log.warning(
        "%d of %d views (%s) have hybrid line samples near only %s of their lit pixels: the one-pixel green "
        "lines wash out (subsurface scattering in marble, alabaster or wax; strong defocus). To cover such "
        "surfaces, %s: on the virtual marble bust under subsurface scattering, coverage 0.11 with the hybrid "
        "pattern, 0.95 with Gray code at 0.10 mm mean error.",
        len(thin), len(results), _few([v for v, _ in thin]),
        "/".join(f"{share:.0%}" for _, share in thin[:5]), remedy)


WASHED_OUT_SHARE = 0.5
"""A Gray-code view losing more than this share of its lit pixels to weak bits gets the
``gray_drop_bits`` hint (:func:`_hint_drop_bits`): 88.6 % on the marble bust under
subsurface scattering, 19.5 % in the concave corner and 23.7 % on the figurine under direct
light (``benchmarks/light_transport.py``); 55-67 % on kamino410's real captures, whose far
background the finest stripes do not reach (``benchmarks/graycode_real.py --drop-bits 0,2``)."""


def _hint_drop_bits(results: Sequence[ViewDecode], config: DecodeConfig) -> None:
    """One warning when Gray-code views lost most of their lit pixels to weak bits while
    per-pixel bit dropping is off: the finest stripes did not reach the camera."""
    if config.gray_drop_bits:
        return
    washed = [r.view for r in results
              if r.valid_share is not None and r.method == "gray" and r.valid_share.weak_bits > WASHED_OUT_SHARE]
    if washed:
        log.warning(
            "%d of %d views (%s) lost more than %.0f%% of their lit pixels to weak Gray-code bits: the finest "
            "stripes do not reach the camera (subsurface scattering, defocus, or a camera that resolves less "
            "than the projector). Decoding with --gray-drop-bits 2 ([decode] gray_drop_bits = 2) keeps those "
            "pixels' coarser codes, with fewer, less accurate samples and a few more wrong codes (virtual marble "
            "bust under subsurface scattering: coverage 0.12 -> 0.95 at twice the mean error; kamino410's real "
            "captures: 15-20 %% more pixels decode, 0.04-0.35 %% of neighbouring pixels out of order instead "
            "of <= 0.01 %%).",
            len(washed), len(results), _few(washed),
            100 * WASHED_OUT_SHARE)


def _log_codes(rec, result: ViewDecode, index: int) -> None:
    """Stream a view's projector column/row maps, when it has them."""
    from slscan.viewer import log_decode as rlog

    found = result.projector_codes
    if found is not None:
        rlog.log_projector_codes(rec, view_index=index, column=found.column, row=found.row,
                                 projector_size=found.projector_size)


def _codes_entry(result: ViewDecode) -> dict:
    """A view's line in ``projector_codes.json`` (its codes written by ``_decode_task``)."""
    share = result.projector_codes.valid_share
    return {"view": result.view, "folder": result.view, "valid_share": share.decoded,
            "noise_dn": share.noise_dn, "seconds": result.seconds.get("decode")}
