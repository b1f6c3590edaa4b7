"""Entity paths of the Rerun recording: the one vocabulary the loggers and the layouts share.

Loggers (``log*.py``) write to these paths; blueprints (:mod:`slscan.viewer.layouts`)
address them. Both import this module and :mod:`slscan.viewer.recording` (the timelines),
and neither imports the other, so the viewer package has no import cycle.

Rig frame (camera frame, mm, x right / y down / z forward) under ``world``; the upright
object frame of the aligned set (mm, y up) under ``object``; scalars under ``plot``,
text logs under ``log``. A second session logged into the same recording (the matte
panel of the light calibration) keeps the same layout under a subtree of its own:
:func:`slscan.viewer.recording.session_stream`.
"""

from __future__ import annotations

WORLD_PATH = "world"

# --- capture (slscan.viewer.log) ---------------------------------------------------------------
CAMERA_PATH = "world/camera"
CAMERA_IMAGE_PATH = "world/camera/image"
PROJECTOR_PATH = "world/projector"
PROJECTOR_IMAGE_PATH = "world/projector/image"
CAPTURE_PATH = "world/camera/image/capture"
PATTERN_PATH = "world/projector/image/pattern"
TRUTH_PATH = "world/camera/image/truth"
LIGHTS_PATH = "world/lights"
MESH_PATH = "world/scene/mesh"
SCANS_WORLD_PATH = "world/scans"
CAPTURE_LOG_PATH = "log/capture"

# --- decode (slscan.viewer.log_decode) ---------------------------------------------------------
DECODE_PATH = "world/camera/image/decode"
DECODE_PLOT_PATH = "plot/decode"

# --- albedo (slscan.viewer.log_albedo) ---------------------------------------------------------
ALBEDO_PATH = "world/camera/image/albedo"
CALIBRATED_LIGHTS_PATH = "world/lights/calibrated"
ALBEDO_LOG_PATH = "log/albedo"
ALBEDO_PLOT_PATH = "plot/albedo"
ALBEDO_MESHES_PATH = "world/albedo"
"""The range maps coloured by albedo, one entity per view (``world/albedo/view_NNN``): a
subtree of their own, since a view's contents can only take whole subtrees (``a/**``;
Rerun supports no ``**`` inside a path)."""

# --- calibrate (slscan.viewer.log_calibrate) ---------------------------------------------------
CALIBRATE_CAMERA_PATH = "world/camera/image/calibrate"
CALIBRATE_PROJECTOR_PATH = "world/projector/image/calibrate"
BOARDS_PATH = "world/boards"
PLANES_PATH = "world/light_planes"
CALIBRATE_PLOT_PATH = "plot/calibrate"
CALIBRATE_LOG_PATH = "log/calibrate"

# --- live scan (slscan.viewer.log_scan) --------------------------------------------------------
HOLES_PATH = "world/camera/image/scan/holes"
SCAN_PLOT_PATH = "plot/scan"
COVERAGE_PATH = "plot/scan/coverage"
SCAN_LOG_PATH = "log/scan"

# --- live preview before a scan (slscan.viewer.log_preview) -----------------------------------
PREVIEW_IMAGE_PATH = "preview/camera"
PREVIEW_FOCUS_PATH = "preview/camera/focus"
PREVIEW_CLIPPED_PATH = "preview/camera/clipped"
PREVIEW_PLOT_PATH = "plot/preview"
PREVIEW_FOCUS_PLOT = "plot/preview/focus"
PREVIEW_CLIPPED_PLOT = "plot/preview/clipped_percent"
PREVIEW_OVERLAP_PLOT = "plot/preview/overlap_percent"
PREVIEW_TEXT_PATH = "log/preview"

# --- register, fuse, simplify (slscan.viewer.log_register) -------------------------------------
OBJECT_PATH = "object"
SCANS_PATH = "object/scans"
MODEL_PATH = "object/model"
REGISTER_PLOT_PATH = "plot/register"
REGISTER_LOG_PATH = "log/register"

# --- texture (slscan.viewer.log_texture) -------------------------------------------------------
VIEWS_PATH = "object/views"
ATLAS_PATH = "texture/atlas"
VIEW_COUNT_PATH = "texture/view_count"
TEXTURE_PLOT_PATH = "plot/texture"

# --- phase decode (slscan.decode.phase.display_maps) -------------------------------------------
PHASE_PATH = "decode/phase"
"""Where a phase decode's maps are, under ``world/camera/image`` (``decode.phase.display_maps``)."""

# --- sessions beside the scan ------------------------------------------------------------------
LIGHTS_PANEL = "lights_panel"
"""Name of the light-calibration panel session's subtree (``world/lights_panel/...``, on the
``lights_panel_view`` / ``lights_panel_frame`` timelines): see
:func:`slscan.viewer.recording.session_stream`."""


def scan_path(view_index: int) -> str:
    """Entity path of one view's scan data in the rig frame, ``world/scans/view_NNN``."""
    return f"{SCANS_WORLD_PATH}/view_{view_index:03d}"


def albedo_mesh_path(view_index: int) -> str:
    """Entity path of one view's range map coloured by albedo, ``world/albedo/view_NNN``."""
    return f"{ALBEDO_MESHES_PATH}/view_{view_index:03d}"


def board_path(view_index: int) -> str:
    """Entity path of one calibration view's board, ``world/boards/view_NNN``."""
    return f"{BOARDS_PATH}/view_{view_index:03d}"
