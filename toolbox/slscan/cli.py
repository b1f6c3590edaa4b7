"""The ``slscan`` command: one entry point, one subcommand per stage."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from slscan import __version__
from slscan.errors import SlscanError
from slscan.executor import add_executor_arguments, executor_from_args
from slscan.progress import ProgressBar as _ProgressBar
from slscan.progress import console as _console

EPILOG = """\
quick start:
  slscan demo --out demo-scan --save demo-scan.rrd   scan the built-in figurine on the virtual rig,
                                                      end to end: demo-scan/texture/model.glb
  rerun demo-scan.rrd                                 look at it in the Rerun viewer
  slscan info demo-scan/capture                       what a capture session holds
  slscan decode demo-scan/capture --out maps          capture session -> range maps (PLY)

Every command that logs takes --save FILE.rrd, --spawn (start a viewer) or
--connect [URL]; without them nothing is logged. Docs: docs/ in the repository.
"""


def _folder_size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


# --- capture / demo -------------------------------------------------------------------


def _add_capture_options(p: argparse.ArgumentParser) -> None:
    from slscan.patterns import add_pattern_arguments
    from slscan.viewer.recording import add_recording_arguments

    p.add_argument("--out", required=True, type=Path, help="capture-session folder to create")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument(
        "--scene", default="object",
        help='"object" (built-in figurine, default), "tile" (flat plane test), "concave" (cube corner: '
             'inter-reflection), "marble" (bust: subsurface), "bronze" (vessel: coloured highlights) or a '
             "mesh file (PLY/OBJ/glTF/GLB/OFF/STL)",
    )
    from slscan.capture.command import add_placement_arguments

    add_placement_arguments(p)
    add_pattern_arguments(p)
    p.add_argument("--levels", type=int, default=9, help="hybrid subdivision levels (default 9: 511 lines)")
    p.add_argument("--gray-rows", action="store_true", help="also project row Gray codes")
    p.add_argument("--no-lit", action="store_true", help="skip the 6 ring-light images")
    p.add_argument("--bit-depth", type=int, choices=(8, 16), default=8, help="PNG bit depth (default 8)")
    p.add_argument("--exposure", type=float, default=1.0, help="exposure factor (default 1; 4 saturates)")
    p.add_argument("--gain", type=float, default=1.0, help="sensor gain (default 1)")
    p.add_argument("--no-noise", action="store_true", help="noise-free images (still quantised)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--views", type=int, default=1, help="turntable views over 360 degrees (default 1)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="camera and projector resolution factor (default 1: the paper's 1440x960 "
                        "camera and 1024x768 projector)")
    p.add_argument("--cameras", type=int, default=1, metavar="N",
                   help="cameras (default 1); N > 1 writes a multi-camera folder (camK/ sessions and "
                        "cameras.json) and adds Gray-code columns and rows, which matching the cameras needs")
    p.add_argument("--camera-spacing", type=float, default=40.0, metavar="DEG",
                   help="with --cameras N: angle between neighbouring cameras about the object, degrees "
                        "(default 40: the projector halfway between cameras 0 and 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)


def _max_levels(scale: float) -> int:
    """Hybrid levels that keep two projector pixels per line on a projector ``scale`` x 1024 wide."""
    return int(math.log2(max(4, round(1024 * scale)))) - 1


def _check_scale(scale: float) -> None:
    if scale <= 0 or scale > 2:
        raise SlscanError(f"--scale must be in (0, 2], got {scale}")


def _cmd_capture(args: argparse.Namespace) -> int:
    from slscan.capture.command import placement_settings
    from slscan.patterns import pattern_options, set_families
    from slscan.viewer.layouts import capture_blueprint
    from slscan.viewer.recording import recording_from_args
    from slscan.virtual.device import VirtualCaptureConfig, capture_session, images_per_view
    from slscan.virtual.sensor import Sensor

    _check_scale(args.scale)
    config = VirtualCaptureConfig(
        scene=args.scene, views=args.views, patterns=args.patterns, levels=args.levels,
        pattern_options=pattern_options(args), gray_rows=args.gray_rows, lit_images=not args.no_lit, camera_scale=args.scale,
        projector_scale=args.scale, seed=args.seed,
        sensor=Sensor(bit_depth=args.bit_depth, exposure=args.exposure, gain=args.gain, noise=not args.no_noise),
        **placement_settings(args),
    )
    if "hybrid" in set_families(config.patterns):
        # keep two projector pixels per line on a smaller projector
        width = config.rig().projector.lens.width
        max_levels = int(math.log2(max(4, width))) - 1
        if args.levels > max_levels:
            logging.getLogger(__name__).warning("a %d px wide projector: using %d hybrid levels", width, max_levels)
            config = dataclasses.replace(config, levels=max_levels)
    if args.cameras < 1:
        raise SlscanError(f"--cameras must be at least 1, got {args.cameras}")
    if args.cameras > 1:
        config = _multicam_patterns(config)
    total = args.cameras * config.views * images_per_view(config)
    console = _console()
    t0 = time.perf_counter()
    if args.cameras > 1:
        from slscan.virtual.multicam import capture_multicam

        with (recording_from_args(args, recording_name=f"capture {args.out.name}", blueprint=capture_blueprint()) as rec,
              _ProgressBar(total, "capturing", args.quiet) as bar):
            multi = capture_multicam(config, args.out, cameras=args.cameras, spacing_deg=args.camera_spacing,
                                     overwrite=args.overwrite, rec=rec, progress=bar.step)
        from slscan.fsio import human_size

        console.print(
            f"[green]wrote[/] {args.out}: {len(multi.cameras)} cameras x {len(multi.view_names)} view(s), "
            f"{human_size(_folder_size(args.out))}, {time.perf_counter() - t0:.1f} s; "
            f"next: slscan decode {args.out} --out {args.out}-range-maps", highlight=False,
        )
        _say_recording(args)
        return 0
    with (recording_from_args(args, recording_name=f"capture {args.out.name}", blueprint=capture_blueprint()) as rec,
          _ProgressBar(total, "capturing", args.quiet) as bar):
        session = capture_session(config, args.out, overwrite=args.overwrite, rec=rec, progress=bar.step,
                                  executor=executor_from_args(args))
    from slscan.fsio import human_size

    n_images = sum(len(v.images) for v in session.views)
    console.print(
        f"[green]wrote[/] {args.out}: {len(session.views)} view(s), {n_images} images "
        f"{session.camera_size[0]}x{session.camera_size[1]}, {human_size(_folder_size(args.out))}, "
        f"{time.perf_counter() - t0:.1f} s"
    )
    _say_recording(args)
    return 0


def _multicam_patterns(config):
    """A multi-camera capture's pattern set: Gray-code columns and rows, to match the cameras."""
    from slscan.patterns import with_rows

    patterns = with_rows(config.patterns)
    if patterns != config.patterns or not config.gray_rows:
        logging.getLogger(__name__).info("multi-camera capture: adding Gray-code columns and rows")
    return dataclasses.replace(config, patterns=patterns, gray_rows=True)


def _say_recording(args: argparse.Namespace) -> None:
    if getattr(args, "save", None):
        from slscan.fsio import human_size

        _console().print(f"[green]recording[/] {args.save} ({human_size(Path(args.save).stat().st_size)}): "
                         f"open it with  rerun {args.save}")


# --- demo: the demo recipe ----------------------------------------------------------------


DEMO_DESCRIPTION = """\
Scan the built-in painted figurine on the virtual rig and carry it all the way to a
textured model: the demo recipe (recipes/demo.toml, shipped with slscan), run exactly as
`slscan run` runs it. Stages and what they write in OUT:

  capture/   8 turntable views: white, black, hybrid patterns and 6 ring-light images per
             view, with per-pixel ground truth (a capture session)
  decode/    one range map per view (PLY) and range_maps.json
  lights/    the ring lights calibrated on a matte panel (lights.json)
  albedo/    the un-shaded colour of every view
  register/  the range maps aligned (aligned.mlp for MeshLab, registration.json)
  fuse/      the fused mesh (mesh.ply; mesh.mlp opens it in MeshLab)
  simplify/  the simplified mesh (mesh.ply; mesh.mlp opens it in MeshLab)
  texture/   the textured model: model.glb, OBJ, PLY, model.mlp

plus OUT/<stage>.stage.json and OUT/recipe.resolved.toml (the recipe as run). At the
default half resolution (720x480 camera) it takes a few minutes; --reduced runs the
recipe's quarter-size version in about a minute.
"""

DEMO_EPILOG = """\
examples:
  slscan demo --out demo-scan --save demo-scan.rrd    then open demo-scan/texture/model.glb
  slscan demo --out quick --reduced --quiet
  slscan demo --out demo-scan --overwrite --views 12 --scale 1
  slscan demo --out demo-scan --set decode.estimator=centroid --spawn

--views, --scale and --set change the recipe's settings as `slscan run --set` does:
--scale S sets capture.camera_scale and capture.projector_scale to S, capture.levels to
what S leaves room for (two projector pixels per line), and fuse.voxel_size to 0.5/S mm.
"""


def _add_demo_options(p: argparse.ArgumentParser) -> None:
    from slscan.viewer.recording import add_recording_arguments

    p.add_argument("--out", required=True, type=Path, help="folder to create (one sub-folder per stage)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into an existing, non-empty --out: every stage runs again and replaces its folder")
    p.add_argument("--views", type=int, metavar="N", help="turntable views over 360 degrees (default: the recipe's, 8)")
    p.add_argument("--scale", type=float, metavar="S",
                   help="camera and projector resolution factor (default: the recipe's, 0.5; 1: the paper's "
                        "1440x960 camera and 1024x768 projector)")
    p.add_argument("--reduced", action="store_true", help="the recipe's quick reduced-size version (quarter size)")
    from slscan.patterns import pattern_set_name

    p.add_argument("--patterns", type=pattern_set_name, metavar="SET",
                   help="the coded patterns (default: the recipe's, hybrid); phase: 4-step phase shifting "
                        "with complementary Gray code (the phase recipe's set)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a setting of the recipe, e.g. capture.seed=3 (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_recording_arguments(p)
    add_executor_arguments(p)


def demo_overrides(*, views: int | None = None, scale: float | None = None,
                   patterns: str | None = None) -> list[str]:
    """``--set`` overrides of the demo recipe for ``slscan demo --views N --scale S --patterns P``."""
    overrides = []
    if patterns is not None:  # the family decoded is the one captured ("auto")
        overrides += [f"capture.patterns={patterns}", "decode.method=auto"]
    if views is not None:
        overrides.append(f"capture.views={views}")
    if scale is not None:
        _check_scale(scale)
        overrides += [f"capture.camera_scale={scale!r}", f"capture.projector_scale={scale!r}",
                      f"capture.levels={min(9, _max_levels(scale))}", f"fuse.voxel_size={0.5 / scale!r}"]
    return overrides


def _check_demo_folder(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise SlscanError(f"{out}: exists and is not a folder")
    if out.is_dir() and not overwrite and any(out.iterdir()):
        raise SlscanError(f"{out}: folder exists and is not empty (pass --overwrite to replace it)")


def _cmd_demo(args: argparse.Namespace) -> int:
    from slscan.recipe.runner import load_recipe, shipped_recipe

    overrides = demo_overrides(views=args.views, scale=args.scale, patterns=args.patterns) + (args.set or [])
    recipe = load_recipe(shipped_recipe("demo"), overrides=overrides, reduced=args.reduced)
    _check_demo_folder(args.out, args.overwrite)
    _run(args, recipe, args.out, force=args.overwrite)
    glb = args.out / "texture" / "model.glb"
    if glb.is_file():
        _console().print(f"[bold]the textured model:[/] {glb} (glTF; Blender, MeshLab, any glTF viewer)",
                         highlight=False)
    return 0


# --- decode -------------------------------------------------------------------------------


def _decode(session, out: Path, config, overwrite: bool, rec, quiet: bool, planes=None, executor=None,
            codes: bool = False, shown: Path | None = None) -> None:
    from slscan.decode.pipeline import decode_session, paint_edge_note
    from slscan.executor import LOCAL

    t0 = time.perf_counter()
    with _ProgressBar(len(session.views), "decoding", quiet) as bar:
        results = decode_session(session, out, config, overwrite=overwrite, rec=rec, progress=bar.step,
                                 planes=planes, executor=executor or LOCAL, codes=codes)
    elapsed = time.perf_counter() - t0
    _print_response(session, config.gray_threshold if results[0].method == "gray" else "adaptive")
    _print_valid_shares([(r.view, r.valid_share) for r in results])
    for r in results:  # what triangulated each view, and how well its geometry pins depth
        if r.triangulation is not None:
            _console().print(f"  {r.view}: triangulated with {r.triangulation.describe()}", highlight=False)
    if note := paint_edge_note(results):  # hybrid line samples left out at paint edges
        _console().print(f"  {note}", highlight=False)
    vertices = sum(len(r.range_map.vertices) for r in results)
    faces = sum(len(r.range_map.faces) for r in results)
    with_codes = " and projector codes (columns/rows/mask PNG per view, projector_codes.json)" if codes else ""
    _console().print(
        f"[green]wrote[/] {shown or out}: {len(results)} range map(s) ({results[0].method} decoding){with_codes}, "
        f"{vertices:,} vertices, {faces:,} faces, {elapsed:.1f} s"
    )


def _decode_codes(session, out: Path, overwrite: bool, rec, quiet: bool, executor=None,
                  threshold: str = "adaptive") -> None:
    """Projector codes only (a session without calibration)."""
    from slscan.decode.codes import decode_codes_session
    from slscan.executor import LOCAL

    t0 = time.perf_counter()
    with _ProgressBar(len(session.views), "decoding codes", quiet) as bar:
        results = decode_codes_session(session, out, overwrite=overwrite, rec=rec, progress=bar.step,
                                       executor=executor or LOCAL, threshold=threshold)
    elapsed = time.perf_counter() - t0
    _print_response(session, threshold)
    _print_valid_shares([(r.view, r.valid_share) for r in results])
    from slscan.decode.codes import FLOAT_ENCODING

    if results and results[0].encoding == FLOAT_ENCODING:
        maps = "VIEW/columns.tiff, rows.tiff: float32 sub-pixel, NaN = not decoded; mask.png"
    else:
        maps = "VIEW/columns.png, rows.png, mask.png; 65535 = not decoded"
    _console().print(
        f"[green]wrote[/] {out}: projector codes of {len(results)} view(s) ({maps}; projector_codes.json), "
        f"no range maps, {elapsed:.1f} s"
    )


def _print_response(session, threshold: str) -> None:
    """The decode summary's line on the camera response the captures were read through."""
    from slscan.capture.response import describe_session_response

    read = ("Gray-code thresholds on the captures as stored (OpenCV's rule)" if threshold == "opencv"
            else "decoded in linear light" if session.response != "linear" else "decoded as stored")
    _console().print(f"  camera response: {describe_session_response(session)}; {read}", highlight=False)


def _print_valid_shares(shares: list) -> None:
    """Per Gray-code view: the decoded share and what limited it (noise, contrast, weak bits)."""
    for view, share in shares:
        if share is not None:
            _console().print(f"  {view}: {share.describe()}", highlight=False)


def _cmd_decode(args: argparse.Namespace) -> int:
    from slscan.capture.multicam import is_multicam
    from slscan.capture.session import load_session

    if is_multicam(args.session):
        return _decode_multicam(args)
    if args.stereo == "only":
        raise SlscanError(f"{args.session}: --stereo only needs a multi-camera folder (with cameras.json)")
    from slscan.decode.pipeline import choose_method
    from slscan.viewer.layouts import decode_blueprint
    from slscan.viewer.recording import recording_from_args

    config = _decode_config(args)
    session = load_session(args.session)
    if args.response is not None:
        from slscan.capture.response import with_response

        session = with_response(session, args.response)
    codes = args.codes
    planes = None
    if args.calibration is not None:
        from slscan.calibrate.io import apply_calibration, calibration_planes, load_calibration

        calibration = load_calibration(args.calibration)
        session = apply_calibration(session, calibration)
        planes = calibration_planes(calibration, source=args.planes)
    codes_only = session.calibration is None and planes is None
    if codes_only:
        from slscan.decode.codes import require_codes

        require_codes(session)  # a hybrid set without calibration: nothing to write
        logging.getLogger(__name__).warning(
            "%s has no calibration: writing projector codes only, no range maps (for range maps, "
            "calibrate the rig with slscan calibrate, then pass --calibration CALIB.json)", args.session)
    # a family with a decode tab of its own (phase shifting) opens on it
    chosen = None if codes_only else choose_method(session, config.method)
    blueprint = decode_blueprint(codes=codes or codes_only, family=chosen)
    with recording_from_args(args, recording_name=f"decode {args.session.name}", blueprint=blueprint) as rec:
        if rec is not None:
            from slscan.viewer.log import log_rig

            if session.calibration is not None:
                log_rig(rec, session.calibration)
        if codes_only:
            _decode_codes(session, args.out, args.overwrite, rec, args.quiet, executor=executor_from_args(args),
                          threshold=args.gray_threshold)
        else:
            _decode(session, args.out, config, args.overwrite, rec, args.quiet, planes=planes,
                    executor=executor_from_args(args), codes=codes)
    return 0


def _decode_config(args: argparse.Namespace):
    """The :class:`~slscan.decode.pipeline.DecodeConfig` of ``slscan decode``'s options."""
    from slscan.decode.pipeline import DecodeConfig

    if args.gray_drop_bits < 0:
        raise SlscanError(f"--gray-drop-bits must be 0 or more, got {args.gray_drop_bits}")
    return DecodeConfig(method=args.method, estimator=args.estimator, trim_line_ends=args.trim_line_ends,
                        gray_threshold=args.gray_threshold, gray_drop_bits=args.gray_drop_bits,
                        gray_smooth=not args.no_gray_smooth, projector_gamma=args.projector_gamma,
                        projector_axes=getattr(args, "projector_axes", "auto"))


def _stereo_config(args: argparse.Namespace):
    """The :class:`~slscan.decode.stereo.StereoConfig` of ``slscan decode``'s options."""
    from slscan.decode.stereo import StereoConfig

    def auto_or(name: str, value: str, kind: type):
        if value == "auto":
            return value
        try:
            return kind(value)
        except ValueError:
            raise SlscanError(f"{name} must be auto or a {'number' if kind is float else 'whole number'}, "
                              f"got {value!r}") from None

    return StereoConfig(
        subpixel=args.stereo_refine == "plane",
        max_epipolar_px=auto_or("--stereo-epipolar", args.stereo_epipolar, float),
        max_ray_gap_mm=auto_or("--stereo-ray-gap", args.stereo_ray_gap, float),
        mesh_step=auto_or("--stereo-mesh-step", args.stereo_mesh_step, int),
        gray_threshold=args.gray_threshold,
        gray_drop_bits=args.gray_drop_bits,
    )


def _decode_multicam(args: argparse.Namespace) -> int:
    """``slscan decode`` on a multi-camera folder: camera 0 matched with each other camera
    through the projector codes, and each calibrated camera's own range maps."""
    from slscan.capture.multicam import load_multicam
    from slscan.decode.stereo import STEREO_FOLDER, reconstruct_multicam
    from slscan.fsio import atomic_output_dir
    from slscan.viewer.layouts import decode_blueprint
    from slscan.viewer.recording import recording_from_args

    for name, value in (("--calibration", args.calibration), ("--response", args.response)):
        if value is not None:
            raise SlscanError(f"{name} is for one camera's session; decode each camera folder on its own")
    multi = load_multicam(args.session)
    if args.stereo != "off":
        multi.require_calibrated()
    per_camera = [] if args.stereo == "only" else [
        (cam, s) for cam, s in zip(multi.cameras, multi.sessions) if s.calibration is not None]
    config = _decode_config(args)
    stereo_config = _stereo_config(args)
    pairs = [] if args.stereo == "off" else [(0, k) for k in range(1, len(multi.cameras))]
    if not pairs and not per_camera:
        raise SlscanError(f"{args.session}: no camera session has a projector calibration; decode with --stereo auto")
    console = _console()
    t0 = time.perf_counter()
    with (recording_from_args(args, recording_name=f"decode {args.session.name}", blueprint=decode_blueprint()) as rec,
          atomic_output_dir(args.out, overwrite=args.overwrite) as tmp):
        for a, b in pairs:
            folder = STEREO_FOLDER.format(a=multi.cameras[a].name, b=multi.cameras[b].name)
            with _ProgressBar(len(multi.view_names), f"matching {folder}", args.quiet) as bar:
                results = reconstruct_multicam(multi, tmp / folder, pair=(a, b), rec=rec, progress=bar.step,
                                               config=stereo_config)
            stats = [r.match.stats for r in results]
            limits = sorted(s["epipolar_limit_px"] for s in stats)
            limit = f"{limits[0]:.2f}" + (f"-{limits[-1]:.2f}" if limits[-1] > limits[0] + 0.005 else "")
            console.print(
                f"[green]{folder}[/]: {sum(s['matched'] for s in stats):,} points from "
                f"{sum(s['common'] for s in stats):,} cells both cameras see (rejected: "
                f"{sum(s['rejected_epipolar'] for s in stats):,} epipolar > {limit} px, "
                f"{sum(s['rejected_ray_gap'] for s in stats):,} ray gap, {sum(s['rejected_behind'] for s in stats):,} "
                f"behind), {sum(len(r.range_map.faces) for r in results):,} faces", highlight=False,
            )
        for cam, session in per_camera:
            _decode(session, tmp / cam.name, config, False, None, args.quiet, executor=executor_from_args(args),
                    shown=args.out / cam.name)
    skipped = [c.name for c, s in zip(multi.cameras, multi.sessions) if s.calibration is None]
    note = f" (no projector calibration, not decoded alone: {', '.join(skipped)})" if skipped and args.stereo != "only" else ""
    console.print(f"[green]wrote[/] {args.out} in {time.perf_counter() - t0:.1f} s{note}", highlight=False)
    return 0


# --- run (recipes) ---------------------------------------------------------------------


class _StageReporter:
    """Shows each recipe stage with its own progress bar, or says it was skipped."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.bar: _ProgressBar | None = None

    def stage_started(self, stage, total: int) -> None:
        self.bar = _ProgressBar(total, f"{stage.name:<9}", self.quiet).__enter__()

    def step(self, label: str) -> None:
        if self.bar:
            self.bar.step(label)

    def stage_finished(self, run) -> None:
        if self.bar:
            self.bar.__exit__(None, None, None)
            self.bar = None
        summary = ", ".join(f"{k} {v:,}" if isinstance(v, int) else f"{k} {v}" for k, v in run.summary.items())
        if run.ran:
            _console().print(f"[green]{run.stage:<9}[/] done in {run.seconds:.1f} s: {summary} -> {run.out}",
                             highlight=False)
        else:
            _console().print(f"[cyan]{run.stage:<9}[/] unchanged, not run again ({summary})")

    def note(self, text: str) -> None:
        """A stage runs again because its outputs changed; leftovers of a killed run were removed."""
        from rich.markup import escape

        _console().print(f"[yellow]{escape(text)}[/]", highlight=False)


def _cmd_run(args: argparse.Namespace) -> int:
    from slscan.recipe.runner import find_recipe, load_recipe

    recipe = load_recipe(find_recipe(args.recipe), overrides=args.set or [], reduced=args.reduced)
    _run(args, recipe, args.out or Path(recipe.out or f"{recipe.name}-run"), force=args.force)
    return 0


def _run(args: argparse.Namespace, recipe, out: Path, *, force: bool) -> None:
    """Run ``recipe`` into ``out`` with progress bars and the recording options of ``args``
    (``slscan run`` and ``slscan demo``)."""
    from slscan.recipe.runner import run_recipe
    from slscan.viewer.layouts import pipeline_blueprint
    from slscan.viewer.recording import recording_from_args

    t0 = time.perf_counter()
    reporter = _StageReporter(args.quiet)
    with recording_from_args(args, recording_name=f"recipe {recipe.name}", blueprint=pipeline_blueprint([st.name for st, _ in recipe.steps])) as rec:
        runs = run_recipe(recipe, out, force=force, rec=rec, reporter=reporter, executor=executor_from_args(args))
    ran = sum(r.ran for r in runs)
    _console().print(
        f"[bold]{recipe.name}[/]: {ran} of {len(runs)} stage(s) run in {time.perf_counter() - t0:.1f} s; "
        f"results and recipe.resolved.toml in {out}"
    )
    _say_recording(args)


def _cmd_baseline(args: argparse.Namespace) -> int:
    import shlex

    from slscan.recipe.regress import make_baseline
    from slscan.recipe.runner import find_recipe, load_recipe

    recipe = load_recipe(find_recipe(args.recipe), overrides=args.set or [], reduced=args.reduced)
    command = shlex.join(["slscan", "baseline", str(args.recipe), *(["--reduced"] if args.reduced else []),
                          *(f"--set={s}" for s in args.set or []), "--out", str(args.out), "--overwrite"])
    make_baseline(recipe, args.out, reporter=_StageReporter(args.quiet), overwrite=args.overwrite,
                  executor=executor_from_args(args), command=command)
    _console().print(f"[green]wrote[/] baseline {args.out}: check later with  slscan regress {args.out}")
    return 0


def _cmd_regress(args: argparse.Namespace) -> int:
    from rich.markup import escape

    from slscan.recipe.regress import failed_stages, format_table, regress

    checks = regress(args.baseline, work=args.keep, overrides=args.set or [], reporter=_StageReporter(args.quiet),
                     executor=executor_from_args(args))
    print(format_table(checks))
    failed = [c for c in checks if not c.ok]
    console = _console()
    if failed:
        console.print(f"[red]{len(failed)} of {len(checks)} checks regressed[/] against {escape(str(args.baseline))} "
                      f"in stage(s): [bold]{escape(', '.join(failed_stages(checks)))}[/]")
        return 1
    console.print(f"[green]all {len(checks)} checks pass[/] against {escape(str(args.baseline))}")
    return 0


# --- patterns ---------------------------------------------------------------------------


def _cmd_patterns(args: argparse.Namespace) -> int:
    from slscan.patterns import pattern_options, standard_set, write_pattern_set

    images = standard_set(args.family, width=args.width, height=args.height, levels=args.levels, rows=args.rows,
                          **pattern_options(args))
    write_pattern_set(args.out, images, overwrite=args.overwrite)
    _console().print(f"[green]wrote[/] {len(images)} pattern images and patterns.json to {args.out}")
    return 0


# --- import / info ------------------------------------------------------------------------


def _projector_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in projector pixels, e.g. 1024x768, got {text!r}") from None
    return w, h


def _import_format(args: argparse.Namespace) -> str:
    """--format when not given: phase for a phase preset or an order with fringe blocks,
    graycode for another preset or order, else kamino410."""
    from slscan.capture.phase_import import PRESETS as PHASE_PRESETS
    from slscan.capture.phase_import import is_phase_order

    if args.preset in PHASE_PRESETS or (args.order and is_phase_order(args.order)):
        return "phase"
    return "graycode" if args.preset or args.order else "kamino410"


def _projector_gamma(text: str) -> float | str | None:
    if text in ("auto", "none"):
        return None if text == "none" else text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, auto or none, got {text!r}") from None


def _cmd_import(args: argparse.Namespace) -> int:
    graycode_only = {"--preset": args.preset, "--order": args.order, "--pattern": args.pattern,
                     "--rotation": args.rotation, "--missing-bits": args.missing_bits}
    if args.format is None:
        args.format = _import_format(args)
    if args.format == "kamino410":
        given = [name for name, value in graycode_only.items() if value is not None]
        if given:
            raise SlscanError(f"{', '.join(given)}: only with --format graycode")
        from slscan.capture.kamino410 import import_kamino410

        with _ProgressBar(1, f"importing {args.format}", args.quiet) as bar:
            session = import_kamino410(args.src, args.out, projector_size=args.projector,
                                       overwrite=args.overwrite, progress=bar.set, response=args.response)
    else:  # graycode or phase: a preset or an order spec
        from slscan.capture import graycode_import, phase_import

        phase = args.format == "phase"
        if phase and args.missing_bits is not None:
            raise SlscanError("--missing-bits: only with --format graycode (a phase set has no bits to drop)")
        if (args.preset is None) == (args.order is None):
            raise SlscanError(f"--format {args.format}: give --preset NAME or --order SPEC (one of them)")
        module, other = (phase_import, "graycode") if phase else (graycode_import, "phase")
        if args.preset is not None and args.preset not in module.PRESETS:
            raise SlscanError(f"--preset {args.preset} is a {other} preset; --format {args.format} takes "
                              f"{', '.join(module.PRESETS)} (or --format {other})")
        importer = phase_import.import_phase if phase else graycode_import.import_graycode
        options = {} if phase else {"missing_bits": args.missing_bits or "error"}
        what = "phase-shifting" if phase else "Gray-code"
        with _ProgressBar(1, f"importing {what} captures", args.quiet) as bar:
            session = importer(
                args.src, args.out, preset=args.preset, order=args.order, projector_size=args.projector,
                rotation=args.rotation, pattern=args.pattern, overwrite=args.overwrite, progress=bar.set,
                response=args.response, **options,
            )
    from slscan.capture.response import describe_session_response

    lossy = ", lossy (JPEG) captures" if session.lossy else ""
    _console().print(f"[green]wrote[/] {args.out}: {len(session.views)} view(s) from {args.src}{lossy}")
    _console().print(f"camera response: {describe_session_response(session)}", highlight=False)
    return 0


def _cmd_response(args: argparse.Namespace) -> int:
    from slscan.capture.session import load_session
    from slscan.decode.phase_gamma import estimate_gamma
    from slscan.fsio import write_json

    if args.out and args.out.exists() and not args.overwrite:
        raise SlscanError(f"{args.out}: already exists (--overwrite replaces it)")
    session = load_session(args.session)
    found = estimate_gamma(session, args.view)
    _console().print(found.describe(), highlight=False)
    if found.spread > 0.05 * found.gamma:
        logging.getLogger(__name__).warning(
            "the pre-distorted sets disagree by %.3f (%.0f %% of gamma): the camera may not be linear (slscan info "
            "says what its response was measured as), or the fringes are clipped", found.spread,
            100 * found.spread / found.gamma)
    if args.out:
        write_json(args.out, {"format": "slscan.projector-response", "version": 1, "gamma": found.gamma,
                              "session": str(session.root.resolve()), "pixels": found.pixels,
                              "sets": [{"pre_distortion": gp, "effective": e, "gamma": g, "rms": r}
                                       for gp, e, g, r in found.per_set]})
        _console().print(f"[green]wrote[/] {args.out}; decode with --projector-gamma {found.gamma:.3f}, or capture "
                         f"with --phase-gamma {found.gamma:.3f}", highlight=False)
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from slscan.capture.multicam import is_multicam, load_multicam
    from slscan.capture.session import load_session

    if is_multicam(args.session):  # each camera's session in turn
        multi = load_multicam(args.session)
        Console().print(f"[bold]{multi.root}[/]: {len(multi.cameras)} cameras ("
                        + ", ".join(f"{c.name}: {'calibrated' if c.calibrated else 'not calibrated'}"
                                    for c in multi.cameras) + f"), common frame: {multi.frame}")
        for session in multi.sessions:
            _cmd_info(argparse.Namespace(session=session.root))
        return 0
    session = load_session(args.session)
    if not session.views:
        raise SlscanError(f"{session.root / 'session.json'}: the session has no views; expected at least one")
    console = Console()
    console.print(f"[bold]{session.root}[/]  ({session.device.get('kind', 'unknown device')})")
    console.print(
        f"camera {session.camera_size[0]}x{session.camera_size[1]}, {session.channels} channel(s), "
        f"{session.bit_depth}-bit; projector {session.projector_size[0]}x{session.projector_size[1]}; "
        f"calibration: {session.calibration_source or 'none'}"
    )
    from slscan.capture.response import describe_session_response

    console.print(f"camera response: {describe_session_response(session)}", highlight=False)
    if session.lossy or session.projector_rotation:
        console.print(
            ("captures are lossy (JPEG): decoding warns, and valid shares may drop; " if session.lossy else "")
            + (f"projector turned {session.projector_rotation} deg (its column stripes cross camera "
               f"{'columns' if session.camera_axis('columns') == 'y' else 'rows'})"
               if session.projector_rotation else ""), highlight=False,
        )
    missing = session.device.get("missing_bits")
    if missing:
        console.print("Gray-code bits dropped at import: " + "; ".join(
            f"{axis} {m['kept']} of {m['bits']} kept" for axis, m in missing.items()), highlight=False)
    families: dict[str, int] = {}
    for p in session.patterns:
        families[p.family] = families.get(p.family, 0) + 1
    console.print("patterns: " + ", ".join(f"{n} {f}" for f, n in families.items()))
    table = Table("view", "pattern images", "lit images", "pose", "ground truth")
    for v in session.views:
        table.add_row(
            v.name, str(len(v.pattern_images())), str(len(v.lit_images())),
            v.pose_source or "-", "yes" if v.ground_truth else "-",
        )
    console.print(table)
    return 0


VIEWER_START_S = 5.0
"""How long ``slscan view FILE.rrd`` watches the viewer start before leaving it running."""


def _cmd_view(args: argparse.Namespace) -> int:
    import shutil
    import subprocess
    import tempfile

    from slscan.viewer.recording import _rerun_executable, display_problem, open_recording
    from slscan.viewer.show import log_result, result_kind

    kind = result_kind(args.result)
    if kind == "recording" and args.save is None:
        exe = shutil.which("rerun") or _rerun_executable()
        if exe is None:
            raise SlscanError("the Rerun viewer (rerun) is not installed next to slscan")
        problem = display_problem()
        if problem is not None:
            raise SlscanError(f"{args.result}: cannot open the Rerun viewer: {problem}; open the file "
                              f"where there is a display, or serve it to a browser: rerun --serve-web {args.result}")
        # the viewer runs on its own; one that fails to start (no window) does so at once
        with tempfile.TemporaryFile() as errors:
            viewer = subprocess.Popen([exe, str(args.result)], start_new_session=True,
                                      stdout=subprocess.DEVNULL, stderr=errors)
            try:
                code = viewer.wait(timeout=VIEWER_START_S)
            except subprocess.TimeoutExpired:
                code = None  # still running: it opened
            if code:
                errors.seek(0)
                lines = [ln for ln in errors.read().decode(errors="replace").splitlines() if ln.strip()]
                reason = lines[-1].strip() if lines else f"exit status {code}"
                raise SlscanError(f"{args.result}: the Rerun viewer did not start ({reason})")
        _console().print(f"opening {args.result} in the Rerun viewer")
        return 0
    if kind == "recording":
        raise SlscanError(f"{args.result}: already a recording; copy it instead of --save")
    spawn = args.save is None
    with open_recording(save=args.save, spawn=spawn, recording_name=f"view {args.result.name}") as rec:
        blueprint = log_result(rec, args.result)
        rec.send_blueprint(blueprint)
    _console().print(f"{'sent' if spawn else 'saved'} {args.result} ({kind}) "
                     + ("to the Rerun viewer" if spawn else f"to {args.save}"))
    return 0


def _cmd_layouts(args: argparse.Namespace) -> int:
    from slscan.viewer.layouts import save_layouts

    paths = save_layouts(args.out)
    _console().print("[green]wrote[/] " + ", ".join(str(p) for p in paths))
    return 0


# --- entry point ------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="slscan",
        description="Structured-light 3D scanning: a projector and a camera (or the built-in "
                    "virtual rig) to range maps and textured models, streamed to Rerun.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"slscan {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="more log messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    from slscan.patterns import add_pattern_arguments, decodable

    p = sub.add_parser(
        "demo", help="scan the built-in figurine on the virtual rig, end to end to a textured model (start here)",
        description=DEMO_DESCRIPTION, epilog=DEMO_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_demo_options(p)
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser(
        "capture", help="capture a scene on the virtual rig (object, tile or your mesh)",
        description="Render a capture session of a scene on the virtual rig: the chosen patterns, "
                    "ring-light images and per-pixel ground truth for every view.",
        epilog="examples:\n  slscan capture --scene tile --out tile-scan\n"
               "  slscan capture --scene statue.glb --views 8 --patterns both --out statue-scan\n"
               "  slscan capture --cameras 2 --patterns gray --out two-cameras   (docs/stereo.md)\n"
               "  slscan capture --scene bust.ply --scene-units m --scene-pose 90,0,0,0,0,0 --out bust-scan\n"
               "  slscan capture --rig rig.json --scene tile --out tile-scan",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_capture_options(p)
    add_executor_arguments(p)
    p.set_defaults(func=_cmd_capture)

    from slscan.capture.command import add_command as add_scan_command

    add_scan_command(sub)

    from slscan.capture.stage_command import add_commands as add_stage_commands

    add_stage_commands(sub)

    from slscan.decode.options import DEFAULT_ESTIMATOR, ESTIMATORS
    from slscan.viewer.recording import add_recording_arguments

    p = sub.add_parser(
        "decode", help="decode a capture session into range maps (PLY)",
        description="Decode every view of a capture session: shadow masks, band codes and "
                    "sub-pixel green-line axes (hybrid) or stripe edges (Gray code), ray-plane "
                    "triangulation with the session's calibration, and meshing into one range "
                    "map per view (binary PLY with normals, colour and quality, for MeshLab). "
                    "Also writes range_maps.json with per-view metrics. With --codes, or "
                    "automatically when the session has no calibration, it writes each Gray-code "
                    "view's projector column and row maps (16-bit PNG, 65535 where not decoded) "
                    "and a mask.",
        epilog="examples:\n  slscan decode demo-scan/capture --out maps --save decode.rrd\n"
               "  slscan decode kamino --out kamino-codes   # no calibration: projector codes only\n"
               "  slscan decode two-cameras --out maps      a multi-camera folder (docs/stereo.md)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", type=Path, help="capture-session folder, or a multi-camera folder (cameras.json)")
    p.add_argument("--out", required=True, type=Path, help="folder for the range maps (and projector codes)")
    p.add_argument("--method", choices=("auto", *decodable()), default="auto",
                   help="which patterns to decode (default auto: phase shifting when captured, else hybrid, "
                        "else Gray code; Gray code rather than hybrid when the captures are lossy (JPEG))")
    p.add_argument("--estimator", choices=ESTIMATORS, default=DEFAULT_ESTIMATOR,
                   help=f"green-line sub-pixel estimator (default {DEFAULT_ESTIMATOR})")
    p.add_argument("--trim-line-ends", type=int, default=0, metavar="ROWS",
                   help="drop this many samples at either end of every line, and lone samples "
                        "(default 0: keep them at lower quality); 1 trades a few %% of coverage "
                        "for a smaller axis error")
    p.add_argument("--codes", action="store_true",
                   help="also write each view's projector column/row maps: VIEW/columns.png, rows.png "
                        "(16-bit, 65535 = not decoded; phase shifting: columns.tiff, rows.tiff, float32 "
                        "sub-pixel, NaN = not decoded), mask.png and projector_codes.json (Gray-code and "
                        "phase sets only; automatic, without range maps, when the session has no calibration)")
    p.add_argument("--gray-threshold", choices=("adaptive", "opencv"), default="adaptive",
                   help="Gray-code bit thresholds: adaptive (default: from the images' noise and "
                        "contrast, in linear light) or opencv (OpenCV GrayCodePattern's rule: 40 DN "
                        "white-black, 5 DN per bit, on the grey captures as stored; x257 at 16 bit)")
    p.add_argument("--response", choices=("measure", "linear", "srgb"),
                   help="read the captures through this camera tone curve instead of the session's "
                        "camera.response (nothing is written to the session); measure: measure it "
                        "from the captures now (pattern + inverse = white + black in linear light)")
    p.add_argument("--no-gray-smooth", action="store_true",
                   help="Gray code: keep each row's edge position as found instead of averaging it with the "
                        "same edge on the rows either side ([1, 2, 1] / 4; the default: mean error in the "
                        "virtual concave corner 0.034 -> 0.023 mm)")
    p.add_argument("--gray-drop-bits", type=int, default=0, metavar="N",
                   help="Gray code: a pixel whose finest bits are washed out (translucent material, "
                        "defocus) keeps the code of its leading reliable bits if at most N are missing "
                        "(default 0: it is dropped; 2 brings the virtual marble under subsurface "
                        "scattering from 12 %% to 95 %% coverage at 2x the direct-light error)")
    p.add_argument("--projector-gamma", type=_projector_gamma, metavar="G|auto|none", default="auto",
                   help="phase shifting: the projector's response exponent (slscan response): the phase of fringes "
                        "not pre-distorted for it is corrected (3-step fringes through gamma 2.2 on the virtual tile: "
                        "0.46 -> 0.08 px RMS); default auto: estimated per view from the fringes, used when they "
                        "clearly show it; none: no correction")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--calibration", type=Path, metavar="CALIB.json",
                   help="decode with this measured calibration (slscan calibrate) instead of the session's")
    p.add_argument("--planes", choices=("auto", "planes", "raw-planes", "inverse-camera"), default="auto",
                   help="with --calibration: which projector model triangulates (default auto: the light-plane "
                        "model when measured, else the inverse camera; the inverse camera when the projector "
                        "rows pin depth better than the columns, as with a projector above the camera)")
    p.add_argument("--projector-axes", choices=("auto", "columns", "both"), default="auto",
                   help="inverse-camera projector: triangulate the projector columns, or columns and rows "
                        "(least squares, each weighted by its noise; Gray code: a second decode for the row "
                        "edges); default auto: rows too where they make depth noise >= 1.25x smaller "
                        "(kamino410's boards, projector 624 mm below the camera: 0.40 mm RMS instead of 2.4)")
    p.add_argument("--stereo", choices=("auto", "only", "off"), default="auto",
                   help="on a multi-camera folder (cameras.json): auto (default) matches camera 0 with each "
                        "other camera through the projector codes (OUT/stereo_cam0_camK/) and decodes each camera "
                        "with a projector calibration alone (OUT/camK/); only: just the matching; off: just "
                        "each camera alone")
    p.add_argument("--stereo-refine", choices=("plane", "centroid"), default="plane",
                   help="multi-camera matching: where each camera sees a projector cell: plane (default: plane "
                        "fits of the decoded codes move every pixel onto its cell's centre; a cell covering a "
                        "block of pixels, whose fits are degenerate, takes its pixels' centroid) or centroid "
                        "(the centroid of every cell's pixels)")
    p.add_argument("--stereo-epipolar", default="auto", metavar="auto|PX",
                   help="multi-camera matching: largest symmetric epipolar distance of a match, camera px "
                        "(default auto: the view's median plus 4 robust deviations, at least 1 px, so the "
                        "calibration's own residual is measured; the limit used is printed)")
    p.add_argument("--stereo-ray-gap", default="auto", metavar="auto|MM",
                   help="multi-camera matching: largest distance between the two rays of a match, mm "
                        "(default auto: the same rule on the view's ray gaps, at least 2 mm)")
    p.add_argument("--stereo-mesh-step", default="auto", metavar="auto|N",
                   help="multi-camera matching: the mesh's grid step, projector px (default auto: follows the "
                        "codes' real step, 2 or 4 where Gray-code bits are dropped (--gray-drop-bits) or "
                        "missing; N: link codes exactly N apart)")
    add_recording_arguments(p)
    add_executor_arguments(p)
    p.set_defaults(func=_cmd_decode)

    from slscan.calibrate.command import add_command as add_calibrate_command

    add_calibrate_command(sub)

    from slscan.albedo.command import add_command as add_albedo_command

    add_albedo_command(sub)

    from slscan.register.command import add_command as add_register_commands

    add_register_commands(sub)

    from slscan.texture.command import add_command as add_texture_command

    add_texture_command(sub)

    from slscan.recipe.runner import describe_stages

    p = sub.add_parser(
        "run", help="run a recipe (a named pipeline in TOML), resuming where it can",
        description="Run the stages of a recipe in order into one folder (OUT/<stage>/). A stage "
                    "whose settings and inputs are unchanged since the last run, and whose files are "
                    "still the ones it wrote (OUT/<stage>.stage.json lists them: size, time, SHA-256), "
                    "is not run again; one whose files were changed, truncated, deleted or added to "
                    "runs again, with a line naming the file. Temporaries left by a killed run "
                    "(.NAME.partial-PID-...) are removed. "
                    "The recipe with every default filled in is written to OUT/recipe.resolved.toml.",
        epilog="stages:\n" + describe_stages() + "\n\nexamples:\n"
               "  slscan run demo --out demo-run        # a recipe shipped with slscan, by name\n"
               "  slscan run recipes/demo.toml --out demo-run\n"
               "  slscan run recipes/paper.toml --set capture.views=4 --set decode.estimator=centroid",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recipe", type=Path,
                   help="recipe file (TOML), or the name of one shipped with slscan, e.g. demo "
                        "(recipes/NAME.toml finds it from any folder too)")
    p.add_argument("--out", type=Path, help="output folder (default: the recipe's, or NAME-run)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a setting, e.g. capture.views=4 (repeatable)")
    p.add_argument("--reduced", action="store_true", help="the recipe's quick reduced-size version")
    p.add_argument("--force", action="store_true", help="run every stage even if unchanged")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_recording_arguments(p)
    add_executor_arguments(p)
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser(
        "baseline", help="record a regression baseline: recorded inputs and every stage's results",
        description="Run a recipe into a new baseline folder for later `slscan regress` checks: "
                    "its recorded capture session (and ring-light calibration), what is compared "
                    "of every later stage (range maps, albedo images, poses, fused and simplified "
                    "meshes, the textured model and its atlas), and baseline.json with the "
                    "metrics, the tolerances and this command (run it again to regenerate).",
        epilog="examples:\n  slscan baseline recipes/demo.toml --reduced --out baselines/demo\n"
               "  the stored demo baseline: see tests/data/baselines/README.md",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("recipe", type=Path, help="recipe file (TOML), or the name of one shipped with slscan")
    p.add_argument("--out", required=True, type=Path, help="baseline folder to create")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out if it exists (once the new baseline is complete)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a setting (repeatable)")
    p.add_argument("--reduced", action="store_true", help="the recipe's quick reduced-size version")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_executor_arguments(p)
    p.set_defaults(func=_cmd_baseline)

    p = sub.add_parser(
        "regress", help="re-run a baseline's recorded session and compare (exit 1 on regression)",
        description="Re-run every stage of a baseline's recipe on its recorded capture session "
                    "(and ring-light calibration), then compare stage by stage with the "
                    "tolerances in its baseline.json: range maps, fused, simplified and textured "
                    "models by surface distance (mm), registration poses (degrees, mm), albedo "
                    "images and the texture by PSNR (dB), the stages' metrics, and the entities "
                    "of the Rerun recording. Prints a table (stage, metric, baseline, now, "
                    "tolerance, ok); exits 1 naming the stages that regressed. The baseline is "
                    "never written.",
        epilog="examples:\n  slscan regress tests/data/baselines/demo\n"
               "  slscan regress tests/data/baselines/demo --set simplify.method=quadric   # what would this change?",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("baseline", type=Path, help="baseline folder (from slscan baseline)")
    p.add_argument("--keep", type=Path, help="keep the re-run in this (new) folder")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="change a setting of the re-run (repeatable), e.g. fuse.voxel_size=4")
    add_executor_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_regress)

    p = sub.add_parser(
        "patterns", help="write pattern images for a real projector",
        description="Write the pattern images (PNG, shown full-screen on the projector, in file "
                    "order) and patterns.json describing each one.",
    )
    p.add_argument("--out", required=True, type=Path, help="folder to create")
    add_pattern_arguments(p, flag="--family")
    p.add_argument("--width", type=int, default=1024, help="projector width, px (default 1024)")
    p.add_argument("--height", type=int, default=768, help="projector height, px (default 768)")
    p.add_argument("--levels", type=int, default=9, help="hybrid levels (default 9: 511 lines)")
    p.add_argument("--rows", action="store_true", help="Gray code and phase shifting: also row patterns")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=_cmd_patterns)

    from slscan.capture.graycode_import import MISSING_BITS, PRESETS
    from slscan.capture.phase_import import PRESETS as PHASE_PRESETS
    from slscan.capture.session import RESPONSES

    p = sub.add_parser(
        "import", help="turn another tool's captures into a capture session",
        description="Import captures made by another tool; images (PNG, JPEG, TIFF) are copied as they are "
                    "(BMP converted to PNG). "
                    "graycode: any folder of Gray-code captures, the image order given by a preset or an "
                    "order spec (see docs/capture-session.md), one folder = one view or one sub-folder per "
                    "view. phase: phase-shifting fringes with Gray code (kamino410/phase-shifting, OpenCV's "
                    "SinusoidalPattern, or an order spec with cols:sine / cols:gray / cols:comp blocks). "
                    "kamino410: procam-calibration's 42 Gray-code images per pose (a folder of "
                    "capture_N folders, or one), projector size from its graycode_pattern folder.",
        epilog="examples:\n"
               "  slscan import sample_data --out kamino\n"
               "  slscan import sample_data --format graycode --preset kamino410 --out kamino\n"
               "  slscan import leftCam/dataset1 --format graycode --preset 3dunderworld --out left\n"
               "  slscan import shots --format graycode --order white,black,cols:11:pairs,rows:pairs "
               "--projector 1920x1080 --rotation 90 --out scan\n"
               "  slscan import phaseshift/object1 --preset kamino410-phase --out o1\n"
               "  slscan import fringes --order white,black,cols:sine:period=16:steps=4,cols:gray:cell=16:pairs,"
               "cols:comp:pairs --projector 1280x800 --out scan\n\n"
               "Gray-code order spec: comma-separated items in file order: white, black, skip, "
               "cols[:BITS][:pairs|split|plain][:msb|lsb], rows[...]; BITS defaults to ceil(log2(size)).\n"
               "phase order spec: white, black, skip, cols:sine:period=P|count=N:steps=N[:shift=DEG]"
               "[:shifts=D/D/D][:origin=PX][:decreasing][:sin][:gamma=G], cols:gray[:cell=PX][:BITS]"
               "[:pairs|split|plain][:msb|lsb][:origin=PX], cols:comp[:pairs|plain], rows:...",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("src", type=Path, help="folder with the other tool's captures")
    p.add_argument("--format", choices=("kamino410", "graycode", "phase"),
                   help="default: phase for a phase preset or an order with sine blocks, graycode for another "
                        "--preset or --order, else kamino410")
    p.add_argument("--preset", choices=tuple(PRESETS) + tuple(PHASE_PRESETS),
                   help=f"a known tool's layout: Gray code {', '.join(PRESETS)}; phase shifting "
                        f"{', '.join(PHASE_PRESETS)} (kamino410-*: sizes from the folder's config.xml)")
    p.add_argument("--order", metavar="SPEC",
                   help="the image order, e.g. white,black,cols:10:pairs,rows:10:pairs (graycode) or "
                        "white,black,cols:sine:period=16:steps=4,cols:gray:pairs (phase)")
    p.add_argument("--projector", type=_projector_size, metavar="WxH",
                   help="projector size in pixels (default: the preset's, else 1024x768; kamino410: "
                        "read from graycode_pattern/)")
    p.add_argument("--rotation", type=int, choices=(0, 90, 180, 270),
                   help="graycode, phase: degrees the projector is mounted turned (90, 270: its column stripes "
                        "appear horizontal); default: the preset's, else 0")
    p.add_argument("--pattern", metavar="GLOB",
                   help="graycode, phase: which files are captures (default: the preset's, else every "
                        "PNG/JPEG/TIFF/BMP), taken in natural sort order")
    p.add_argument("--missing-bits", choices=MISSING_BITS,
                   help="graycode: images missing from a numbered set are an error (default), or drop: "
                        "import the most significant bits that are complete")
    p.add_argument("--response", choices=("auto", *RESPONSES), default="auto",
                   help="the camera's tone curve, recorded as camera.response (decoding undoes srgb); "
                        "default auto: measured from the captures (pattern + inverse = white + black "
                        "holds in linear light only), linear when they do not tell; the import "
                        "prints what was chosen and why")
    p.add_argument("--out", required=True, type=Path, help="capture-session folder to create")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_import)

    p = sub.add_parser(
        "response", help="measure the projector's gamma from a phase-response capture",
        description="Measure the projector's response exponent (emitted light = pattern value ** gamma) from a "
                    "capture of the phase-response set (slscan patterns --family phase-response, slscan scan "
                    "--patterns phase-response, or another tool's gamma set imported, e.g. kamino410's): "
                    "fringes pre-distorted for two exponents and a fine Gray code that gives every pixel's "
                    "projector coordinate (Hoang et al. 2010). Use the result to pre-distort the fringes "
                    "(--phase-gamma G when capturing) or to correct the phase (slscan decode --projector-gamma G).",
        epilog="example:\n  slscan scan --patterns phase-response --out resp && slscan response resp --out gamma.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", type=Path, help="capture session of the phase-response set")
    p.add_argument("--view", help="the view to measure (default: the first)")
    p.add_argument("--out", type=Path, metavar="FILE.json", help="also write the estimate as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=_cmd_response)

    from slscan.simplify_bricks import extend_simplify_parser

    extend_simplify_parser(sub.choices["simplify"])

    p = sub.add_parser("info", help="check a capture session and summarise it",
                       description="Validate every image of a capture session against its metadata and summarise it.")
    p.add_argument("session", type=Path, help="capture-session folder, or a multi-camera folder (cameras.json)")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser(
        "view", help="open a result in the Rerun viewer with the layout that fits it",
        description="Open a recording (.rrd), a capture session, a range-maps folder or a recipe "
                    "run folder in the Rerun viewer, arranged with the matching layout.",
        epilog="examples:\n  slscan view demo-scan.rrd\n  slscan view demo-scan/decode\n"
               "  slscan view demo-scan --save demo-scan-again.rrd   (write a recording instead)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("result", type=Path, help="a .rrd file or a result folder")
    p.add_argument("--save", type=Path, metavar="FILE.rrd", help="write a recording instead of opening the viewer")
    p.set_defaults(func=_cmd_view)

    p = sub.add_parser("layouts", help="write the Rerun viewer layouts (.rbl)",
                       description="Write the Rerun blueprints that arrange each stage's views.")
    p.add_argument("--out", type=Path, default=Path("viewer_layouts"), help="default: viewer_layouts")
    p.set_defaults(func=_cmd_layouts)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    from rich.logging import RichHandler

    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s",
        handlers=[RichHandler(console=_console(), show_path=False, show_time=False)],
    )
    try:
        with _output_held(args, argv):
            return int(args.func(args) or 0)
    except SlscanError as exc:
        _print_error(str(exc))
        return 2
    except KeyboardInterrupt:
        _console().print("[red]slscan: interrupted[/]")
        return 130
    except Exception as exc:  # noqa: BLE001 - the one place where every error becomes one line
        known = _known_error(exc)
        if args.verbose:
            _console().print_exception()
        if known is not None:
            _print_error(known)
            return 2
        _print_error(f"internal error, a bug in slscan: {type(exc).__name__}: {_first_line(exc)} "
                     f"(re-run with -v for the traceback and please report it)")
        return EXIT_BUG


def _output_held(args: argparse.Namespace, argv: Sequence[str] | None) -> contextlib.AbstractContextManager:
    """The lock on the command's ``--out`` (:func:`slscan.fsio.output_lock`): a second
    ``slscan`` writing the same output at the same time fails instead of replacing it."""
    out = getattr(args, "out", None)
    if not isinstance(out, Path):
        return contextlib.nullcontext()
    from slscan.fsio import output_lock

    words = list(sys.argv[1:] if argv is None else argv)
    return output_lock(out, command=" ".join(["slscan", *map(str, words)]))


EXIT_BUG = 70
"""Exit status for a bug (an unexpected exception), as sysexits' EX_SOFTWARE; 2 is a bad input."""


def _print_error(message: str) -> None:
    from rich.markup import escape

    message = " ".join(message.split())  # one line, however the library worded it
    _console().print(f"[red]slscan: error:[/] {escape(message)}", highlight=False, soft_wrap=True)


def _first_line(exc: BaseException) -> str:
    return next((line.strip() for line in str(exc).splitlines() if line.strip()), "")


def _known_error(exc: Exception) -> str | None:
    """The one-line message for an error caused by the input or the machine, not by slscan:
    a file that cannot be read or written (``OSError``, naming it; a full disk with the
    space left), memory, and what OpenCV and the file parsers raise on bad files.
    None for anything else (a bug)."""
    import json
    import tomllib

    if isinstance(exc, OSError):
        from slscan.fsio import WRITE_ERRNOS, write_error

        if exc.errno in WRITE_ERRNOS and exc.filename:
            return str(write_error(exc.filename, exc, kept=False))
        reason = (exc.strerror or _first_line(exc) or type(exc).__name__).lower()
        names = [str(n) for n in (exc.filename, exc.filename2) if n]
        return f"{' -> '.join(names)}: {reason}" if names else reason
    if isinstance(exc, MemoryError):
        return "out of memory: the inputs are too large for this machine (try fewer views or a reduced size)"
    if isinstance(exc, json.JSONDecodeError):
        return f"not valid JSON ({exc.msg} at line {exc.lineno}): {_first_line(exc)}"
    if isinstance(exc, tomllib.TOMLDecodeError):
        return f"not valid TOML: {_first_line(exc)}"
    if isinstance(exc, UnicodeDecodeError):
        return f"a file is not text where text was expected ({exc.reason} at byte {exc.start})"
    cv2 = sys.modules.get("cv2")
    if cv2 is not None and isinstance(exc, cv2.error):
        detail = _first_line(exc)
        detail = detail.split(" error: ", 1)[-1]  # drop OpenCV's source path and line
        return f"OpenCV could not process an input ({detail})"
    return None


if __name__ == "__main__":
    sys.exit(main())
