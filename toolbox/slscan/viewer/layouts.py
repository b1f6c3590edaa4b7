"""Rerun blueprints that arrange the views of each pipeline stage; saved to ``viewer_layouts/``.

Open a recording with a layout: ``rerun scan.rrd viewer_layouts/capture.rbl``. Blueprints
are saved for application id ``"slscan"``, the id :func:`slscan.viewer.recording.open_recording`
uses by default.

Every stage's blueprint is here; it addresses the entity paths of :mod:`slscan.viewer.paths`
and the timelines of :mod:`slscan.viewer.recording`, and imports no logger (the loggers
import no layout either).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import rerun.blueprint as rrb

from slscan.viewer.paths import (
    ATLAS_PATH,
    CALIBRATE_PLOT_PATH,
    LIGHTS_PANEL,
    PHASE_PATH,
    PREVIEW_CLIPPED_PLOT,
    PREVIEW_FOCUS_PLOT,
    PREVIEW_IMAGE_PATH,
    PREVIEW_OVERLAP_PLOT,
    PREVIEW_PLOT_PATH,
    PREVIEW_TEXT_PATH,
    VIEW_COUNT_PATH,
)
from slscan.viewer.recording import STAGE_TIMELINE, VIEW_TIMELINE

APPLICATION_ID = "slscan"

TRUTH_LAYERS = (
    ("depth", "Depth (mm)"),
    ("normal", "Normal"),
    ("albedo", "Albedo"),
    ("projector_column", "Projector column"),
    ("visibility", "Visibility"),
)


def _image_view(origin: str, entity: str, name: str) -> rrb.Spatial2DView:
    """A 2D view of one image entity under the pinhole at ``origin``."""
    return rrb.Spatial2DView(origin=origin, contents=f"$origin/{entity}", name=name)


def capture_blueprint() -> rrb.Blueprint:
    """Capture stage: the rig in 3D beside the camera frame, the pattern and the truth layers.

    Left: 3D view of ``world`` — frusta, lights, scene mesh, true surface points and the
    current capture on the camera's image plane (truth images and the pattern are left out
    of 3D so they do not cut through the scene). Right: the capture and the projected
    pattern side by side; tabs with the truth layers; the frame log. Time panel on the
    view timeline.
    """
    scene = rrb.Spatial3DView(
        origin="world",
        contents=[
            "+ $origin/**",
            "- $origin/camera/image/truth/**",
            "- $origin/projector/image/pattern",
            f"- $origin/{LIGHTS_PANEL}/**",  # the light-calibration panel's own session
        ],
        name="Rig and scene",
    )
    frames = rrb.Horizontal(
        _image_view("world/camera/image", "capture", "Capture"),
        _image_view("world/projector/image", "pattern", "Pattern"),
    )
    truth = rrb.Tabs(
        *(
            _image_view("world/camera/image", f"truth/{layer}", name)
            for layer, name in TRUTH_LAYERS
        ),
        name="Ground truth",
    )
    log = rrb.TextLogView(origin="log", name="Frames")
    return stage_blueprint(
        rrb.Horizontal(
            scene,
            rrb.Vertical(frames, truth, log, row_shares=[3, 3, 1]),
            column_shares=[1, 1],
            name="Capture",
        )
    )


def stage_blueprint(root: rrb.Container, timeline: str = VIEW_TIMELINE) -> rrb.Blueprint:
    """A stage's layout: ``root`` with the time panel open on ``timeline`` and the
    selection panel closed."""
    return rrb.Blueprint(
        root,
        rrb.TimePanel(expanded=True, timeline=timeline),
        rrb.SelectionPanel(expanded=False),
        collapse_panels=False,
    )


def phase_map_views(*, compact: bool = False) -> list[rrb.View | rrb.Container]:
    """The 2D views of a phase decode: wrapped phase, unwrapped coordinate, modulation per
    axis, and the fringe-order corrections over the capture; ``compact``: the columns only."""
    image = "world/camera/image"

    def maps(kind: str, axis: str, name: str) -> rrb.Spatial2DView:
        return rrb.Spatial2DView(origin=image, contents=f"$origin/{PHASE_PATH}/{kind}/{axis}/**", name=name)

    # names short enough for the title bars at the default window size
    fixes = rrb.Spatial2DView(
        origin=image, contents=["+ $origin/capture", f"+ $origin/{PHASE_PATH}/order_fix/**"], name="Order fixes",
    )
    if compact:
        return [maps("wrapped", "columns", "Wrapped phase"), maps("unwrapped", "columns", "Projector column"),
                maps("modulation", "columns", "Modulation"), fixes]
    modulation = rrb.Tabs(maps("modulation", "columns", "Modulation"),
                          maps("modulation", "rows", "Modulation (rows)"), name="Modulation")
    return [
        maps("wrapped", "columns", "Wrapped (columns)"),
        maps("unwrapped", "columns", "Projector column"),
        modulation,
        maps("wrapped", "rows", "Wrapped (rows)"),
        maps("unwrapped", "rows", "Projector row"),
        fixes,
    ]


def phase_container(name: str = "Phase") -> rrb.Container:
    """A phase-shifting decode: its maps (left) beside the range map and its unwrapping
    counts (right).

    Left, per axis (projector columns, then rows): the wrapped phase of each period (cyclic
    colours, the finest period on top; hide it in the blueprint panel to see the coarser
    ones), the unwrapped projector coordinate (Turbo over the projector), and the
    modulation (the per-pixel quality; Viridis on [0, 1]) beside the fringe-order
    corrections marked over the capture (green: moved a period up, cyan: down, magenta:
    rejected). Right: the range maps in 3D and, per axis, the shares of lit pixels the
    unwrapping corrected, rejected or lost (``plot/decode/phase/<axis>``), a point per view.
    """
    views = phase_map_views()
    scans = rrb.Spatial3DView(
        origin="world",
        contents=["+ $origin/scans/**", "+ $origin/camera", "+ $origin/projector"],
        name="Range maps",
    )
    counts = rrb.Horizontal(
        *(rrb.TimeSeriesView(origin=f"plot/decode/phase/{axis}", name=f"{axis.capitalize()} (shares)")
          for axis in ("columns", "rows")),
    )
    return rrb.Horizontal(
        rrb.Horizontal(rrb.Vertical(*views[:3]), rrb.Vertical(*views[3:])),  # a column per axis
        rrb.Vertical(scans, counts, row_shares=[3, 2]),
        column_shares=[3, 2],
        name=name,
    )


def phase_blueprint() -> rrb.Blueprint:
    """A phase-shifting decode on its own (:func:`phase_container`), on the view timeline."""
    return stage_blueprint(phase_container())


FAMILY_TABS: dict[str, Callable[[], rrb.Container]] = {"phase": phase_container}
"""Pattern families whose decode has a tab of its own, beside the Decode tab."""


def decode_blueprint(*, codes: bool = True, family: str | None = None) -> rrb.Blueprint:
    """Decode stage: what was measured on the image beside the range map it gives.

    Left: the white capture with the stripe axes and the saturation overlay drawn over it
    (zoom in to see the sub-pixel line strips); below it tabs with the decoded code map
    and the validity mask, and with ``codes`` the projector column and row maps of a
    Gray-code set (``slscan decode --codes``). Right: 3D view of the range maps (and the
    true surface points on the virtual rig), and the per-view metrics.

    family : the pattern family decoded; one with a tab of its own (:data:`FAMILY_TABS`:
        phase shifting) gets it beside the Decode tab, and the viewer opens on it
    """
    overlay = rrb.Spatial2DView(
        origin="world/camera/image",
        contents=["+ $origin/capture", "+ $origin/decode/stripes", "+ $origin/decode/saturation"],
        name="Stripe axes over the capture",
    )
    maps = rrb.Tabs(
        _image_view("world/camera/image", "decode/codes", "Codes"),
        _image_view("world/camera/image", "decode/mask", "Mask"),
        *(
            (
                _image_view("world/camera/image", "decode/columns", "Projector columns"),
                _image_view("world/camera/image", "decode/rows", "Projector rows"),
            )
            if codes
            else ()
        ),
        name="Decoded maps",
    )
    scans = rrb.Spatial3DView(
        origin="world",
        contents=["+ $origin/scans/**", "+ $origin/camera", "+ $origin/projector"],
        name="Range maps",
    )
    metrics = rrb.TimeSeriesView(origin="plot/decode", name="Per-view metrics")
    root = rrb.Horizontal(
        rrb.Vertical(overlay, maps, row_shares=[3, 2]),
        rrb.Vertical(scans, metrics, row_shares=[3, 1]),
        column_shares=[1, 1],
        name="Decode",
    )
    if family in FAMILY_TABS:
        root = rrb.Tabs(root, FAMILY_TABS[family](), active_tab=1, name="Decode")
    return stage_blueprint(root)


# recipe stage -> the pipeline tab showing it (index into pipeline_blueprint's tabs)
_PIPELINE_TAB = {"capture": 0, "decode": 1, "lights": 2, "albedo": 2, "register": 3, "fuse": 3,
                 "simplify": 3, "texture": 4}


def pipeline_blueprint(stages: Sequence[str] = ()) -> rrb.Blueprint:
    """The whole pipeline: one tab per stage layout (capture, decode, albedo, register, texture).

    stages : the recipe's stages, in order; the viewer opens on the tab of the first one
        that has a tab (e.g. Register for a recipe that starts from range maps), on the
        ``view`` timeline when per-view stages run, else on the ``stage`` timeline
    """
    # recipes decode to range maps only: no projector-code views
    tabs = [capture_blueprint(), decode_blueprint(codes=False), albedo_blueprint(), register_blueprint(), texture_blueprint()]
    active = next((_PIPELINE_TAB[s] for s in stages if s in _PIPELINE_TAB), 0)
    timeline = VIEW_TIMELINE if active <= _PIPELINE_TAB["albedo"] else STAGE_TIMELINE
    return stage_blueprint(
        rrb.Tabs(*(b.root_container for b in tabs), active_tab=active, name="slscan pipeline"),
        timeline,
    )


def register_blueprint() -> rrb.Blueprint:
    """Register, fuse, simplify: the range maps at their poses (scrub the ``stage``
    timeline from initial to registered), the fused and simplified models, and the pair
    residuals."""
    scans = rrb.Spatial3DView(origin="object", contents=["+ $origin/scans/**"], name="Range maps at their poses")
    models = rrb.Tabs(
        rrb.Spatial3DView(origin="object", contents=["+ $origin/model/fused"], name="Fused"),
        rrb.Spatial3DView(origin="object", contents=["+ $origin/model/simplified"], name="Simplified"),
        name="Model",
    )
    residuals = rrb.Tabs(
        rrb.Vertical(
            rrb.TimeSeriesView(origin="plot/register/rmse", name="Pair RMS (mm)"),
            rrb.TimeSeriesView(origin="plot/register/overlap", name="Pair overlap"),
            name="Pairs",
        ),
        rrb.Vertical(
            rrb.TimeSeriesView(origin="plot/register/rejected", name="Rejected pairs"),
            rrb.TextLogView(origin="log/register", name="Registration log"),
            name="Rejected",
        ),
    )
    return stage_blueprint(
        rrb.Horizontal(scans, rrb.Vertical(models, residuals, row_shares=[2, 1]), column_shares=[3, 2],
                       name="Register"),
        STAGE_TIMELINE,
    )


def calibrate_blueprint() -> rrb.Blueprint:
    """Calibrate stage: the boards, rig and light planes in 3D beside the corners in 2D.

    Left: 3D view of ``world`` — board poses, camera and projector frusta, a sample of
    light planes (images left out). Right: the board image with detected (green) and
    reprojected (red) corners; the projector's image with the corners mapped into it;
    per-view reprojection errors and per-plane residuals; the calibration log. Time panel
    on the view timeline.
    """
    scene = rrb.Spatial3DView(
        origin="world",
        contents=[
            "+ $origin/**",
            "- $origin/camera/image/**",
            "- $origin/projector/image/calibrate/**",
            f"- $origin/{LIGHTS_PANEL}/**",
        ],
        name="Boards, rig and light planes",
    )
    camera = rrb.Spatial2DView(
        origin="world/camera/image",
        contents=["+ $origin/calibrate/**"],
        name="Board corners (camera)",
    )
    projector = rrb.Spatial2DView(
        origin="world/projector/image",
        contents=["+ $origin/calibrate/**"],
        name="Board corners (projector)",
    )
    errors = rrb.TimeSeriesView(
        origin=CALIBRATE_PLOT_PATH,
        contents=["+ $origin/camera_rms_px", "+ $origin/projector_rms_px"],
        name="Reprojection RMS per view (px)",
    )
    planes = rrb.Tabs(
        rrb.BarChartView(
            origin=f"{CALIBRATE_PLOT_PATH}/plane_rms_after_mm", name="Plane RMS after global fit (mm)"
        ),
        rrb.BarChartView(
            origin=f"{CALIBRATE_PLOT_PATH}/plane_rms_before_mm", name="Plane RMS, raw planes (mm)"
        ),
        name="Light-plane residuals",
    )
    log = rrb.TextLogView(origin="log/calibrate", name="Calibration log")
    return stage_blueprint(
        rrb.Horizontal(
            scene,
            rrb.Vertical(
                rrb.Horizontal(camera, projector),
                rrb.Horizontal(errors, planes),
                log,
                row_shares=[3, 2, 1],
            ),
            column_shares=[1, 1],
            name="Calibrate",
        ),
    )


def albedo_blueprint() -> rrb.Blueprint:
    """Albedo stage: each lit image with its masks beside the un-shaded result.

    Left: the lit image of the current frame with its light's shadow (blue) and rejected
    highlight (yellow) masks over it; below it tabs with the un-shaded image, the error
    against ground truth (virtual rig) and the normals used. Right: 3D view of the range
    maps coloured by albedo with the calibrated lights, and the per-view metrics.
    Scrub the frame timeline to step through the lights. In a recipe's recording, the
    "Light panel" tab shows the light calibration's own captures (``world/lights_panel``,
    on the ``lights_panel_view`` timeline).
    """
    image = "world/camera/image"
    lit = rrb.Spatial2DView(
        origin=image,
        contents=["+ $origin/albedo/lit", "+ $origin/albedo/shadow", "+ $origin/albedo/highlight"],
        name="Lit image, shadow and highlight masks",
    )
    results = rrb.Tabs(
        rrb.Spatial2DView(
            origin=image, contents="$origin/albedo/unshaded", name="Un-shaded (albedo)"
        ),
        rrb.Spatial2DView(origin=image, contents="$origin/albedo/error", name="Albedo error"),
        rrb.Spatial2DView(origin=image, contents="$origin/albedo/normal", name="Normals"),
        # a recipe's light calibration: its own session (pick the lights_panel_view timeline)
        rrb.Spatial2DView(origin=f"world/{LIGHTS_PANEL}/camera/image", contents="$origin/capture",
                          name="Light panel"),
        name="Albedo",
    )
    scans = rrb.Spatial3DView(
        origin="world",
        contents=["+ $origin/albedo/**", "+ $origin/lights/**", "+ $origin/camera"],
        name="Range maps with albedo",
    )
    metrics = rrb.TimeSeriesView(origin="plot/albedo", name="Per-view metrics")
    return stage_blueprint(
        rrb.Horizontal(
            rrb.Vertical(lit, results, row_shares=[1, 1]),
            rrb.Vertical(scans, metrics, row_shares=[3, 1]),
            column_shares=[1, 1],
            name="Albedo",
        ),
    )


def scan_blueprint() -> rrb.Blueprint:
    """Live scan: the frame arriving and the pattern on the projector (left); the last
    view's range map in 3D (or its code map, or with phase shifting its wrapped phase,
    projector column, modulation and fringe-order corrections) and its holes over the
    white frame (right); coverage per view and the scan log below."""
    live = rrb.Vertical(
        rrb.Spatial2DView(origin="world/camera/image", contents="$origin/capture", name="Camera (live)"),
        rrb.Spatial2DView(origin="world/projector/image", contents="$origin/pattern", name="Projector"),
        name="Live",
    )
    holes = rrb.Spatial2DView(
        origin="world/camera/image",
        contents=["+ $origin/capture", "+ $origin/scan/holes", "+ $origin/decode/saturation",
                  "+ $origin/corners"],
        name="Holes (magenta) and clipping (red)",
    )
    maps = rrb.Tabs(
        rrb.Spatial3DView(origin="world", contents=["+ $origin/scans/**", "+ $origin/camera",
                                                   "+ $origin/projector"], name="Range maps"),
        rrb.Spatial2DView(origin="world/camera/image", contents="$origin/decode/codes", name="Codes"),
        rrb.Grid(*phase_map_views(compact=True), grid_columns=2, name="Phase"),
        name="Quick decode",
    )
    bottom = rrb.Horizontal(
        rrb.TimeSeriesView(origin="plot/scan", name="Coverage per view"),
        rrb.TextLogView(origin="log", name="Scan log"),
    )
    return stage_blueprint(
        rrb.Vertical(
            rrb.Horizontal(live, rrb.Vertical(maps, holes), column_shares=[2, 3]),
            bottom,
            row_shares=[4, 1],
            name="Scan",
        )
    )


def texture_blueprint() -> rrb.Blueprint:
    """Texture stage: the textured model (and, in a second tab, among the view cameras);
    the atlas and the per-texel view count beside it; the metrics below."""
    model = rrb.Tabs(
        rrb.Spatial3DView(origin="object", contents=["+ $origin/model/textured"], name="Textured model"),
        rrb.Spatial3DView(origin="object", contents=["+ $origin/model/textured", "+ $origin/views/**"],
                          name="Model and views"),
        name="Model",
    )
    images = rrb.Tabs(
        rrb.Spatial2DView(origin=ATLAS_PATH, name="Atlas"),
        rrb.Spatial2DView(origin=VIEW_COUNT_PATH, name="Views per texel"),
        name="Texture",
    )
    metrics = rrb.TimeSeriesView(origin="plot/texture", name="Texture metrics")
    return stage_blueprint(
        rrb.Horizontal(model, rrb.Vertical(images, metrics, row_shares=[3, 1]), column_shares=[3, 2],
                       name="Texture"),
        STAGE_TIMELINE,
    )


def preview_blueprint() -> rrb.Blueprint:
    """The preview's layout: the camera with the focus tiles and clipped pixels over it
    (left), focus, clipped share and overlap plotted per refresh, and the lines (right)."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(origin=PREVIEW_IMAGE_PATH, contents="$origin/**",
                              name="Camera: focus (red blurred, green sharp), clipped (magenta)"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin=PREVIEW_FOCUS_PLOT, name="Focus (stripe contrast)"),
                rrb.TimeSeriesView(origin=PREVIEW_PLOT_PATH,
                                   contents=[f"+ {PREVIEW_CLIPPED_PLOT}", f"+ {PREVIEW_OVERLAP_PLOT}"],
                                   name="Clipped % and overlap %"),
                rrb.TextLogView(origin=PREVIEW_TEXT_PATH, name="Preview"),
            ),
            column_shares=[3, 2],
            name="Preview",
        ),
        rrb.TimePanel(state="collapsed"),
        collapse_panels=True,
    )


LAYOUTS: dict[str, Callable[[], rrb.Blueprint]] = {
    "capture": capture_blueprint,
    "calibrate": calibrate_blueprint,
    "decode": decode_blueprint,
    "phase": phase_blueprint,
    "albedo": albedo_blueprint,
    "register": register_blueprint,
    "texture": texture_blueprint,
    "pipeline": pipeline_blueprint,
    "scan": scan_blueprint,
}
"""Blueprint builders by stage name; :func:`save_layouts` writes ``<name>.rbl`` for each."""


def save_layouts(out_dir: str | os.PathLike) -> list[Path]:
    """Write every layout in :data:`LAYOUTS` as ``out_dir/<name>.rbl``; return the paths."""
    import tempfile

    from slscan.fsio import write_bytes

    out = Path(out_dir)
    paths = []
    # Rerun's Blueprint.save hangs when its write fails (a full disk): each layout is saved
    # in the system's temporary folder, then copied to ``out`` flushed and size-checked
    with tempfile.TemporaryDirectory(prefix="slscan-layouts-") as scratch:
        for name, build in LAYOUTS.items():
            path = out / f"{name}.rbl"
            build().save(APPLICATION_ID, Path(scratch) / path.name)
            write_bytes(path, (Path(scratch) / path.name).read_bytes())
            paths.append(path)
    return paths
