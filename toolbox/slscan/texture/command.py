"""``slscan texture``: a model and its registered views → a textured model (glb, OBJ, PLY, .mlp)."""

from __future__ import annotations

import argparse
from pathlib import Path

from slscan.progress import ProgressBar, console

TEXTURE_EPILOG = """\
examples:
  slscan texture demo-run/simplify/mesh.ply --views demo-run/albedo --poses demo-run/register --out textured
  slscan texture model.ply --views albedo --out textured --size 4096 --save texture.rrd

--views is the folder `slscan albedo` wrote (un-shaded images + albedo.json, which names
the capture session for the camera model); --poses the registration (`slscan register`'s
folder, its registration.json or aligned.mlp); without it the session's recorded poses
are used. Outputs in --out: model.glb (glTF, metres, Y up), model.obj/.mtl +
model_albedo.png (mm), model.ply (texture coordinates per face corner, as MeshLab writes
them), model_vertex_colors.ply, model.mlp (MeshLab: model.ply and the views as registered
rasters), views/VIEW.png, view_count.png (coloured; raw counts: view_count_raw.png), texture.json, and
preview.png when Blender is found (bash .ci/setup installs it in .venv-blender).

--workers N / --scheduler tcp://HOST:PORT bake groups of 8 views per task on local
processes or a Dask cluster (the same atlas as in one process); each task reads its views'
images from --views and shared arrays from a folder beside --out: Dask workers need both
at the same paths.
"""


def _cmd_texture(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from slscan.errors import SlscanError
    from slscan.executor import executor_from_args
    from slscan.texture.atlas import MAX_SIZE, MIN_SIZE
    from slscan.texture.pipeline import TextureConfig, texture_model
    from slscan.viewer.layouts import texture_blueprint
    from slscan.viewer.recording import recording_from_args

    if args.size is not None and not MIN_SIZE <= args.size <= MAX_SIZE:
        raise SlscanError(
            f"--size must be {MIN_SIZE} to {MAX_SIZE} texels, got {args.size} "
            "(leave it out to size the atlas from the face count)"
        )
    config = TextureConfig(size=args.size or 0, preview=not args.no_preview)
    if args.padding is not None:
        config = replace(config, bake=replace(config.bake, padding=args.padding))
    with (recording_from_args(args, recording_name=f"texture {args.model.name}", blueprint=texture_blueprint()) as rec,
          ProgressBar(16, "texturing", args.quiet) as bar):
        result = texture_model(args.model, args.views, args.out, poses=args.poses, session=args.session,
                               config=config, overwrite=args.overwrite, rec=rec, progress=bar.step,
                               executor=executor_from_args(args))
    m = result.metrics
    console().print(
        f"[green]textured[/] {result.faces:,} faces: atlas {result.size}x{result.size}, {result.charts:,} charts, "
        f"utilisation {m['utilisation']:.2f}, {m['observed_share']:.1%} of texels seen, seam error "
        f"{m['seam_error_mean']:.2f} levels in {result.seconds.get('total', 0):.1f} s -> {result.out / 'model.glb'} "
        f"(colour from {'the projector as the light' if result.light == 'projector' else 'the ring lights'})",
        highlight=False,
    )
    return 0


def add_command(subparsers: argparse._SubParsersAction) -> None:
    """Add ``texture`` to the ``slscan`` subcommands."""
    from slscan.executor import add_executor_arguments
    from slscan.viewer.recording import add_recording_arguments

    p = subparsers.add_parser(
        "texture", help="bake the views' un-shaded colour into a texture atlas; write glb/OBJ/PLY/.mlp",
        description="Texture a model from its registered views: parametrise it into an atlas (xatlas "
                    "on pre-segmented patches), bake every view's un-shaded colour into it with "
                    "visibility from each view's depth and weights for viewing angle, depth "
                    "discontinuities and image borders, fill unseen texels from the per-vertex "
                    "colours and pad across seams. Writes the model as glTF binary, OBJ and "
                    "vertex-coloured PLY, and a MeshLab project with the views as rasters.",
        epilog=TEXTURE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", type=Path, help="the model (PLY/OBJ; e.g. slscan simplify's output)")
    p.add_argument("--views", required=True, type=Path, metavar="DIR", help="slscan albedo's output folder")
    p.add_argument("--poses", type=Path, metavar="REGISTRATION",
                   help="registration.json, aligned.mlp or their folder (default: recorded poses)")
    p.add_argument("--session", type=Path, help="capture session (default: the one albedo.json names)")
    p.add_argument("--out", required=True, type=Path, help="folder to write")
    p.add_argument("--size", type=int, default=None,
                   help="atlas size in texels, 64 to 16384 (default: from the face count)")
    p.add_argument("--padding", type=int, default=None, help="texels of padding around charts (default 4)")
    p.add_argument("--no-preview", action="store_true", help="do not render preview.png with Blender")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_executor_arguments(p)
    add_recording_arguments(p)
    p.set_defaults(func=_cmd_texture)
