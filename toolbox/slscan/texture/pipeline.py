"""The texture stage end to end: model + registered views → textured model in open formats.

:func:`texture_model` parametrises the model (:mod:`slscan.texture.atlas`), bakes the
views' un-shaded colour into the atlas and onto the vertices (:mod:`slscan.texture.bake`)
and writes the output folder atomically:

==============================  ===============================================================
``model.glb``                   glTF 2.0 binary with the baked texture (metres, Y up)
``model.obj/.mtl``, ``model_albedo.png``  the same as OBJ (mm, slscan frame)
``model.ply``                   the model with texture coordinates per face corner (MeshLab's way)
``model_vertex_colors.ply``     the model with per-vertex colour (the fallback)
``model.mlp``                   MeshLab project: ``model.ply`` and every view as a registered raster
``views/VIEW.png``              each view's un-shaded image (sRGB, undistorted)
``view_count.png``              views blended per texel as colours (legend in ``texture.json``:
                                black outside the charts, grey 0 = filled from the vertices,
                                blue 1 view ... red every view)
``view_count_raw.png``          the counts themselves (16-bit grey; 0: filled or outside)
``preview.png``                 Cycles render of the model (when Blender is found)
``texture.json``                manifest: files, views (intrinsics, poses), atlas, metrics
==============================  ===============================================================
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slscan import __version__
from slscan.errors import SlscanError
from slscan.texture.bake import BakeOptions

log = logging.getLogger(__name__)

MIN_SEEN_SHARE = 0.5
"""Below this share of the atlas texels seen by some view, ``slscan texture`` warns that the
rest is filled from the vertex colours. Measured (``benchmarks/texture_seen.py``, the
figurine, camera scale 0.25 and the demo's 0.5): the right model seen by all 8 turntable
views 78-84 % (the demo baseline 74 %); a model moved 200 mm / 2 m, turned 90 degrees,
scaled 1.5, another object (the bunny, a sphere) in its place 5-53 % (the sphere's 53 % is
caught by :data:`MIN_MODEL_SHARE`); the right model from 4, 2, 1 views 47-54, 26-30,
15-18 % (a partial scan: the warning is true there too)."""

MIN_MODEL_SHARE = 0.75
"""``slscan texture`` warns when, for some view, the model lies on less than this share of
the pixels where the view saw the object (known albedo): the model is not the object the
views saw, or not where they saw it. Measured as above: the right model 86-90 % (5 mm voxels,
3,000 faces) to 99 % (1-2 mm, 20,000-100,000 faces) for every view, partial scans too; a model
moved 200 mm or more, turned, or another object: the lowest view 0-72 %; scaled 1.5: 55-86 %
(its seen share, 25-35 %, warns); a 20 mm shift: 78-90 % (not caught)."""

TEXTURE_FORMAT = "slscan-texture"
TEXTURE_VERSION = 1


@dataclass(frozen=True)
class TextureConfig:
    """Options of the texture stage."""

    size: int = 0
    """Atlas width = height in texels; 0: from the face count (see ``texels_per_face``)."""
    texels_per_face: float = 8.0
    """With ``size = 0``: texels per face the atlas aims at (rounded up to a power of two,
    512 to 8192)."""
    bake: BakeOptions = field(default_factory=BakeOptions)
    preview: bool = True
    """Render ``preview.png`` with Blender's Cycles (CPU) when Blender is found."""
    preview_size: tuple[int, int] = (640, 480)
    preview_samples: int = 16


@dataclass(frozen=True)
class TextureResult:
    out: Path
    faces: int
    charts: int
    size: int
    metrics: dict
    seconds: dict
    light: str = "ring"
    """What lit the views' albedo: "ring" (the ring lights un-shaded) or "projector"."""


def auto_size(faces: int, texels_per_face: float = 8.0, utilisation: float = 0.7) -> int:
    """Power-of-two atlas size giving about ``texels_per_face`` texels to each face."""
    side = math.sqrt(max(faces, 1) * texels_per_face / utilisation)
    return int(min(8192, max(512, 2 ** math.ceil(math.log2(side)))))


def texture_model(
    model: str | os.PathLike,
    albedo_dir: str | os.PathLike,
    out: str | os.PathLike,
    *,
    poses=None,
    session: str | os.PathLike | None = None,
    config: TextureConfig | None = None,
    overwrite: bool = False,
    rec=None,
    progress: Callable[[str], None] | None = None,
    executor=None,
) -> TextureResult:
    """Texture ``model`` (PLY/OBJ mesh, world frame) from the views of ``albedo_dir``.

    poses : the registration (``registration.json``, ``aligned.mlp``, their folder, or a
        dict name → world_from_camera); see :func:`slscan.texture.views.view_files`
    session : the capture session, when not the one ``albedo.json`` names
    executor : :class:`slscan.executor.Executor` on which groups of views are baked
        (:func:`slscan.texture.bake.bake`; default: this process). Its processes read the
        views' images from ``albedo_dir`` and shared arrays from a folder beside ``out``:
        Dask workers need both at the caller's paths.
    """
    from slscan.colour import srgb8
    from slscan.fsio import _partial_prefix, atomic_output_dir, write_json, write_png
    from slscan.fuse import read_mesh
    from slscan.meshes import vertex_normals
    from slscan.register.meshlab import Raster, write_mlp
    from slscan.texture import export
    from slscan.texture.atlas import AtlasOptions, build_atlas
    from slscan.texture.bake import bake, check_texture_memory
    from slscan.texture.metrics import seam_error
    from slscan.texture.views import view_files
    from slscan.colour import view_count_image, view_count_legend
    from slscan.viewer.log_texture import log_texture_views, log_textured_model

    config = config or TextureConfig()
    progress = progress or (lambda label: None)
    out = Path(out)
    if out.exists() and not overwrite:
        raise SlscanError(f"{out}: already exists (pass --overwrite to replace it)")
    t_start = time.perf_counter()
    mesh = read_mesh(model)
    if len(mesh.faces) == 0:
        raise SlscanError(f"{model}: the model has no faces")
    size = config.size or auto_size(len(mesh.faces), config.texels_per_face)
    check_texture_memory(size)
    views = view_files(albedo_dir, poses, session=session)
    light = albedo_light(albedo_dir)
    log.info("texturing from %d view(s) whose albedo came from %s", len(views),
             "the projector as the light" if light == "projector" else "the ring lights")
    progress(f"{len(views)} views")

    atlas = build_atlas(mesh.vertices, mesh.faces, AtlasOptions(size=size, padding=config.bake.padding))
    progress(f"atlas: {atlas.n_charts} charts")
    normals = vertex_normals(mesh.vertices, mesh.faces).astype(np.float32)
    baked = bake(mesh.vertices, mesh.faces, atlas, views, config.bake, normals=normals, progress=progress,
                 executor=executor, scratch=_scratch_folder(out), scratch_prefix=_partial_prefix(out))
    check_seen(baked, model, albedo_dir)
    texture = srgb8(baked.linear)
    seams = seam_error(texture, mesh.faces, atlas)
    covered = int(baked.covered.sum())
    metrics = {
        "charts": atlas.n_charts,
        "utilisation": round(float(atlas.utilisation), 4),
        "texels_covered": covered,
        "observed_share": round(float(baked.observed.sum() / max(covered, 1)), 4),
        "mean_views_per_texel": round(float(baked.view_count[baked.covered].mean()) if covered else 0.0, 3),
        "vertices_observed_share": round(float(baked.vertex_observed.mean()), 4),
        "seam_edges": seams.edges,
        "seam_error_mean": round(seams.mean, 3),
        "seam_error_p95": round(seams.p95, 3),
    }
    seconds = {"atlas": round(float(atlas.seconds.get("total", 0.0)), 2),
               **{k: round(float(v), 2) for k, v in baked.seconds.items()}}
    progress("baked")

    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        t0 = time.perf_counter()
        atlas_normals = normals[atlas.source_vertex]
        export.write_glb(tmp / "model.glb", atlas, texture, atlas_normals, name=model_name(out))
        export.write_obj(tmp / "model.obj", atlas, texture, atlas_normals)
        export.write_wedge_uv_ply(tmp / "model.ply", mesh.vertices, mesh.faces, atlas, "model_albedo.png",
                                  normals)
        export.write_vertex_color_ply(tmp / "model_vertex_colors.ply", mesh.vertices, mesh.faces,
                                      srgb8(baked.vertex_colors), normals)
        # the counts (0-3 in a typical texel) as colours one can see, and as numbers
        write_png(tmp / "view_count.png", view_count_image(baked.view_count, baked.covered, len(views)))
        write_png(tmp / "view_count_raw.png", baked.view_count.astype(np.uint16))
        images = []  # kept for the recording only: 4 MB a view at 1440 x 960
        (tmp / "views").mkdir()
        for view in views:
            image = export.undistorted_view_image(view.load())
            write_png(tmp / "views" / f"{view.name}.png", image)
            if rec is not None:
                images.append(image)
            del image
        entries = export.view_entries(views)
        rasters = [Raster(e["name"], e["image"], e["width"], e["height"], e["fx"], e["fy"], e["cx"], e["cy"],
                          np.asarray(e["world_from_camera"])) for e in entries]
        # the mesh beside the project, by name: ``tmp`` may be relative to the current folder.
        # The PLY with wedge texture coordinates, not the OBJ, which MeshLab 2020.09 aborts on.
        write_mlp(tmp / "model.mlp", [(Path("model.ply"), np.eye(4))], rasters=rasters)
        seconds["export"] = round(time.perf_counter() - t0, 2)
        progress("exported")
        manifest = {
            "format": TEXTURE_FORMAT, "version": TEXTURE_VERSION, "written_by": f"slscan {__version__}",
            "units": "mm",
            "source": {"model": str(Path(model).resolve()), "albedo": str(Path(albedo_dir).resolve()),
                       "light": light},
            "model": {"glb": "model.glb", "obj": "model.obj", "ply": "model_vertex_colors.ply",
                      "textured_ply": "model.ply",
                      "texture": "model_albedo.png", "mlp": "model.mlp", "view_count": "view_count_raw.png",
                      "view_count_image": "view_count.png", "view_count_legend": view_count_legend(len(views)),
                      "faces": len(mesh.faces), "vertices": len(mesh.vertices)},
            "gltf_from_world": export.GLTF_FROM_WORLD.tolist(),
            "atlas": {"size": atlas.size, "charts": atlas.n_charts, "utilisation": atlas.utilisation,
                      "vertices": len(atlas.vertices)},
            "bake": asdict(config.bake),
            "views": entries,
            "metrics": metrics,
            "seconds": seconds,
        }
        write_json(tmp / "texture.json", manifest)
        if config.preview:
            _preview(tmp, config, manifest, seconds, progress)
        seconds["total"] = round(time.perf_counter() - t_start, 2)
        manifest["seconds"] = seconds
        write_json(tmp / "texture.json", manifest)
    log_texture_views(rec, entries, images)
    log_textured_model(rec, atlas, texture, atlas_normals, baked.view_count, metrics,
                       covered=baked.covered, max_views=len(views))
    return TextureResult(out, len(mesh.faces), atlas.n_charts, atlas.size, metrics, seconds, light)


def _scratch_folder(out: Path) -> Path:
    """Where the bake's tasks share their arrays: beside ``out`` (on the campaign's disk,
    which Dask workers see at the same path), named as a temporary of ``out`` (so one left by
    a killed run is removed by the next)."""
    parent = out.resolve().parent
    parent.mkdir(parents=True, exist_ok=True)
    return parent


def albedo_light(albedo_dir: str | os.PathLike) -> str:
    """What lit an albedo folder's views: "ring" or "projector" (``albedo.json``'s
    ``light``; folders written before it existed are the ring lights')."""
    from slscan.fsio import read_json

    meta = read_json(Path(albedo_dir) / "albedo.json", "albedo index")
    light = meta.get("light", "ring") if isinstance(meta, dict) else "ring"
    return light if light in ("ring", "projector") else "ring"


def check_seen(baked, model: str | os.PathLike, albedo_dir: str | os.PathLike) -> None:
    """Refuse a model no view sees; warn about one that is mostly unseen, or that misses
    much of what some view saw (:data:`MIN_SEEN_SHARE`, :data:`MIN_MODEL_SHARE`).

    Raises
    ------
    SlscanError
        No texel of the model is seen by any view of ``albedo_dir``.
    """
    covered = int(baked.covered.sum())
    seen = int(baked.observed.sum())
    if seen == 0:
        raise SlscanError(
            f"{model}: no view of {albedo_dir} sees the model; expected the model of the object the "
            "views saw, where they saw it (check --poses: the registration of the same scans)"
        )
    share = seen / max(covered, 1)
    if share < MIN_SEEN_SHARE:
        log.warning("%s: only %.0f %% of the model's texture is seen by a view of %s (below %.0f %%; a "
                    "whole-object scan sees about 75 %%); the rest is filled from the vertex colours",
                    model, 100 * share, albedo_dir, 100 * MIN_SEEN_SHARE)
    shares = {k: v for k, v in getattr(baked, "view_model_share", {}).items() if np.isfinite(v)}
    if shares:
        worst = min(shares, key=shares.get)
        if shares[worst] < MIN_MODEL_SHARE:
            log.warning("%s: the model covers only %.0f %% of what view %s of %s saw (below %.0f %%): "
                        "another object, or not where the views saw it (poses of another registration?)",
                        model, 100 * shares[worst], worst, albedo_dir, 100 * MIN_MODEL_SHARE)


def model_name(out: Path) -> str:
    """The name a model carries inside its files (glTF node, Blender object): the output
    folder's, or its parent's when the folder is named for the stage (``bust/texture`` →
    ``bust``)."""
    resolved = Path(os.path.abspath(out))
    name = resolved.name
    if name.lower() in {"texture", "textured", "model"} and resolved.parent.name:
        name = resolved.parent.name
    return name or "model"


def _preview(folder: Path, config: TextureConfig, manifest: dict, seconds: dict, progress) -> None:
    """Render ``preview.png`` with Blender when one is found; a warning when it fails."""
    from slscan.texture.blender import find_blender, render_preview

    if find_blender() is None:
        log.info("no Blender found: no preview.png (run `bash .ci/setup` to install bpy in .venv-blender)")
        return
    t0 = time.perf_counter()
    try:
        render_preview(folder, folder / "preview.png", size=tuple(config.preview_size),
                       samples=config.preview_samples)
    except SlscanError as exc:
        log.warning("Blender preview failed: %s", exc)
        return
    manifest["preview"] = "preview.png"
    seconds["preview"] = round(time.perf_counter() - t0, 2)
    progress("preview")
