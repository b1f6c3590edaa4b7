"""Log a result folder from disk (capture session, range maps, recipe run) for ``slscan view``."""

from __future__ import annotations

import os
from pathlib import Path

import rerun as rr
import rerun.blueprint as rrb

from slscan.errors import SlscanError


def result_kind(path: Path) -> str:
    """{"recording", "session", "range_maps", "texture", "run"} for a path ``slscan view`` can open."""
    if path.is_file() and path.suffix == ".rrd":
        return "recording"
    if (path / "session.json").is_file():
        return "session"
    if (path / "range_maps.json").is_file():
        return "range_maps"
    if (path / "texture.json").is_file():
        return "texture"
    if (path / "recipe.resolved.toml").is_file():
        return "run"
    if path.exists():
        raise SlscanError(
            f"{path}: not something slscan can show (expected a .rrd file, a capture session, "
            "a range-maps folder, a texture result or a recipe run folder)"
        )
    raise SlscanError(f"{path}: not found")


def log_session(rec: rr.RecordingStream, path: Path) -> None:
    """The rig, every capture and (virtual rig) the ground truth of a capture session."""
    from slscan.capture.session import load_session
    from slscan.viewer.log import log_capture, log_ground_truth, log_rig

    session = load_session(path)
    if session.calibration is not None:
        log_rig(rec, session.calibration)
    for v, view in enumerate(session.views):
        for frame, image_rec in enumerate(view.images):
            label = image_rec.pattern or f"lit {image_rec.light}"
            log_capture(rec, session.read_image(view, image_rec), view_index=v, frame_index=frame, label=label)
        if view.ground_truth:
            log_ground_truth(rec, session.load_ground_truth(view), view_index=v,
                             projector_width=session.projector_size[0])


def log_range_maps(rec: rr.RecordingStream, path: Path) -> None:
    """Every range map of a decode output folder, as meshes in the rig frame."""
    from slscan.decode.rangemap import read_ply
    from slscan.fsio import read_json
    from slscan.viewer.log_decode import log_metrics, log_range_map

    summary = read_json(path / "range_maps.json", "range-maps summary")
    for v, entry in enumerate(summary.get("views", [])):
        rm = read_ply(path / entry["file"])
        log_range_map(rec, rm.vertices, rm.faces, rm.normals, rm.colors, view_index=v)
        log_metrics(rec, entry.get("metrics", {}), view_index=v)


def log_result(rec: rr.RecordingStream, path: str | os.PathLike) -> rrb.Blueprint:
    """Log what is stored at ``path`` to ``rec``; return the layout that fits it."""
    from slscan.viewer.layouts import capture_blueprint, decode_blueprint, pipeline_blueprint

    path = Path(path)
    kind = result_kind(path)
    if kind == "session":
        log_session(rec, path)
        return capture_blueprint()
    if kind == "range_maps":
        log_range_maps(rec, path)
        return decode_blueprint()
    if kind == "texture":
        from slscan.viewer.layouts import texture_blueprint
        from slscan.viewer.log_texture import log_texture_result

        log_texture_result(rec, path)
        return texture_blueprint()
    if kind == "run":
        from slscan.viewer.log_texture import log_texture_result

        for folder in sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith(".")):
            markers = ("session.json", "range_maps.json", "texture.json")
            sub = result_kind(folder) if any((folder / m).is_file() for m in markers) else None
            if sub == "session":
                log_session(rec, folder)
            elif sub == "range_maps":
                log_range_maps(rec, folder)
            elif sub == "texture":
                log_texture_result(rec, folder)
        return pipeline_blueprint()
    raise SlscanError(f"{path}: a recording is opened directly, not logged")
