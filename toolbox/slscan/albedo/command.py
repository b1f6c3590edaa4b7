"""The albedo stage's commands: ``capture-lights``, ``calibrate-lights`` and ``albedo``.

``cli.py`` calls :func:`add_command` with its subparsers.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from slscan.errors import SlscanError
from slscan.progress import ProgressBar, console

ALBEDO_EPILOG = """\
examples:
  slscan capture-lights --out lights-session          # virtual rig: a matte panel at 6 poses
  slscan calibrate-lights lights-session --out lights.json
  slscan albedo demo-scan/capture --range-maps demo-scan/decode --lights lights.json \\
      --out albedo --save albedo.rrd
  slscan albedo scan --range-maps decode --light projector --lights lights.json --out albedo
      # no ring lights: the projector's white frame, LIGHTS.json's "projector" block

outputs (per view): VIEW_albedo.png (16-bit LINEAR RGB reflectance x 65535, not sRGB;
0 where invalid), VIEW_valid.png (255 where the albedo is valid), VIEW.ply (the range
map with per-vertex albedo: 8-bit sRGB colour and float linear albedo_red/green/blue),
and albedo.json (lights, settings, per-view metrics).
"""


def add_command(subparsers) -> None:
    """Add ``capture-lights``, ``calibrate-lights`` and ``albedo`` to ``slscan``'s subparsers."""
    from slscan.albedo.photometric import LIGHT_SOURCES, NORMALS, SPECULAR, AlbedoConfig
    from slscan.viewer.recording import add_recording_arguments

    p = subparsers.add_parser(
        "capture-lights",
        help="virtual rig: capture a matte panel for light calibration",
        description="Capture a light-calibration session on the virtual rig: a flat matte panel "
        "of known reflectance at several known poses (near, far, tilted), each under "
        "every ring light. Writes the session and light_panel.json into OUT.",
        epilog="example:\n  slscan capture-lights --out lights-session\n"
        "  slscan calibrate-lights lights-session --out lights.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, type=Path, help="capture-session folder to create")
    p.add_argument("--poses", type=int, default=6, help="panel poses, 2 to 6 (default 6)")
    p.add_argument(
        "--scale",
        type=float,
        default=0.5,
        help="camera and projector resolution factor (default 0.5; the calibration "
        "is in mm and does not depend on it)",
    )
    p.add_argument(
        "--panel-albedo",
        type=float,
        nargs=3,
        metavar=("R", "G", "B"),
        default=(0.8, 0.8, 0.8),
        help="linear reflectance of the panel (default 0.8 0.8 0.8)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    p.set_defaults(func=_cmd_capture_lights)

    p = subparsers.add_parser(
        "calibrate-lights",
        help="fit ring-light positions and intensities to a panel session",
        description="Calibrate the ring lights once per rig: fit each light's position (mm, rig "
        "frame) and RGB intensity, and the ambient light, to the irradiance a matte "
        "panel of known reflectance shows at known poses (nonlinear least squares). "
        "The panel's pose comes from the session (the virtual rig records it) or, on a real "
        "rig, from a plane fitted to each view's range map (--range-maps); the panel is "
        "described by SESSION/light_panel.json or --panel-* options.",
        epilog="example:\n  slscan calibrate-lights lights-session --out lights.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", type=Path, help="light-calibration session folder")
    p.add_argument(
        "--out", required=True, type=Path, metavar="LIGHTS.json", help="light calibration to write"
    )
    p.add_argument(
        "--panel-albedo",
        type=float,
        nargs=3,
        metavar=("R", "G", "B"),
        default=None,
        help="panel reflectance (default: from SESSION/light_panel.json)",
    )
    p.add_argument(
        "--panel-size",
        type=float,
        nargs=3,
        metavar=("W", "H", "T"),
        default=None,
        help="panel width, height, thickness in mm (default: from light_panel.json)",
    )
    p.add_argument(
        "--range-maps",
        type=Path,
        default=None,
        metavar="DIR",
        help="the panel session's range maps (slscan decode --out): a real rig's panel session records "
        "no panel pose, so the panel's plane is fitted to each view's range map",
    )
    p.add_argument("--no-ambient", action="store_true", help="assume no ambient light")
    p.add_argument(
        "--no-projector",
        action="store_true",
        help="do not calibrate the projector as a light (by default its white is measured on the "
        "panel's white and black frames, for slscan albedo --light projector)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    p.set_defaults(func=_cmd_calibrate_lights)

    defaults = AlbedoConfig()
    p = subparsers.add_parser(
        "albedo",
        help="un-shade the lit images into albedo (colour) per view",
        description="Compute the illumination-invariant RGB albedo of every view from its lit "
        "images (one per ring light), its range map and the calibrated lights: "
        "per pixel a Lambertian model with a fitted specular lobe is inverted, cast "
        "shadows (shadow rays against the range map) and outliers left out, and "
        "pixels with too few usable lights marked invalid. A scan without ring lights "
        "(or --light projector) takes its colour from the white frame instead, the "
        "projector being the calibrated point light (black frame subtracted, inverse "
        "square and cosine from the range map, projector shadows left out).",
        epilog=ALBEDO_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", type=Path, help="capture-session folder")
    p.add_argument(
        "--range-maps",
        required=True,
        type=Path,
        metavar="DIR",
        help="the session's range maps (slscan decode --out)",
    )
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="DIR",
        help="folder for the albedo images and meshes",
    )
    p.add_argument(
        "--lights",
        type=Path,
        default=None,
        metavar="LIGHTS.json",
        help="light calibration (slscan calibrate-lights); default: the session's nominal lights",
    )
    p.add_argument(
        "--light",
        choices=LIGHT_SOURCES,
        default=defaults.light,
        help="ring: un-shade the ring lights' images (paper); projector: the white frame with the "
        "projector as the calibrated light (rigs without ring lights); auto (default): the ring when "
        "every view has lit images and the lights are known, else the projector",
    )
    p.add_argument(
        "--normals",
        choices=NORMALS,
        default=defaults.normals,
        help="photometric: fine normals from the images (default); range: the range map's",
    )
    p.add_argument(
        "--specular",
        choices=SPECULAR,
        default=defaults.specular,
        help="fit a specular lobe per view (default) or assume a matte surface",
    )
    p.add_argument(
        "--min-lights",
        type=int,
        default=defaults.min_lights,
        help=f"pixels with fewer usable lights are invalid (default {defaults.min_lights})",
    )
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    from slscan.executor import add_executor_arguments

    add_executor_arguments(p)
    p.set_defaults(func=_cmd_albedo)


def _cmd_capture_lights(args: argparse.Namespace) -> int:
    from slscan.albedo.lights import MattePanel
    from slscan.viewer.layouts import capture_blueprint
    from slscan.viewer.recording import recording_from_args
    from slscan.virtual.device import images_per_view
    from slscan.virtual.panels import (
        LightPanelConfig,
        capture_light_calibration,
        light_calibration_poses,
    )

    config = LightPanelConfig(scale=args.scale).capture_config()
    panel = MattePanel(albedo=tuple(args.panel_albedo))
    poses = light_calibration_poses(config.rig(), count=args.poses)
    total = len(poses) * images_per_view(config)
    t0 = time.perf_counter()
    with (
        recording_from_args(
            args, recording_name=f"capture-lights {args.out.name}", blueprint=capture_blueprint()
        ) as rec,
        ProgressBar(total, "capturing panel", args.quiet) as bar,
    ):
        session = capture_light_calibration(
            args.out,
            config=config,
            panel=panel,
            poses=poses,
            overwrite=args.overwrite,
            rec=rec,
            progress=bar.step,
        )
    console().print(
        f"[green]wrote[/] {args.out}: {len(session.views)} panel poses, "
        f"{sum(len(v.lit_images()) for v in session.views)} lit images, {time.perf_counter() - t0:.1f} s; "
        f"next: slscan calibrate-lights {args.out} --out lights.json"
    )
    return 0


def _cmd_calibrate_lights(args: argparse.Namespace) -> int:
    from rich.table import Table

    from slscan.albedo.lights import MattePanel, calibrate_lights, read_panel, write_lights
    from slscan.capture.session import load_session
    from slscan.viewer.layouts import albedo_blueprint
    from slscan.viewer.recording import recording_from_args

    if args.out.exists() and not args.overwrite:
        raise SlscanError(f"{args.out}: exists (pass --overwrite to replace it)")
    session = load_session(args.session)
    panel = None
    if args.panel_albedo is not None or args.panel_size is not None:
        try:
            base = read_panel(session.root)
        except SlscanError:
            base = MattePanel()
        w, h, t = (
            args.panel_size
            if args.panel_size is not None
            else (base.width, base.height, base.thickness)
        )
        albedo = tuple(args.panel_albedo) if args.panel_albedo is not None else base.albedo
        panel = MattePanel(width=w, height=h, thickness=t, albedo=albedo, margin=base.margin)
    t0 = time.perf_counter()
    with (
        recording_from_args(
            args, recording_name=f"calibrate-lights {args.session.name}", blueprint=albedo_blueprint()
        ) as rec,
        ProgressBar(len(session.views), "reading the panel", args.quiet) as bar,
    ):
        cal = calibrate_lights(
            session,
            panel=panel,
            fit_ambient=not args.no_ambient,
            projector=not args.no_projector,
            range_maps=args.range_maps,
            progress=bar.step,
        )
        if rec is not None:
            from slscan.viewer.log import log_rig
            from slscan.viewer.log_albedo import log_lights

            if session.calibration is not None:
                log_rig(rec, session.calibration)
            if cal.lights:
                log_lights(rec, cal)
    write_lights(args.out, cal)
    out = console()
    truth = (
        session.calibration.lights
        if session.calibration_source == "virtual-rig ground truth"
        else ()
    )
    table = Table(
        "light",
        "position (mm)",
        "± (mm)",
        "intensity RGB",
        *(("error (mm)", "intensity error") if truth else ()),
    )
    for k, (light, sigma) in enumerate(zip(cal.lights, cal.position_sigma)):
        row = [
            str(k),
            " ".join(f"{x:8.1f}" for x in light.position),
            f"{sigma:.2f}",
            " ".join(f"{x:.4f}" for x in light.intensity),
        ]
        if truth and k < len(truth):
            err = math.dist(light.position, truth[k].position)
            rel = max(abs(a / b - 1) for a, b in zip(light.intensity, truth[k].intensity))
            row += [f"{err:.2f}", f"{100 * rel:.2f} %"]
        table.add_row(*row)
    if cal.lights:
        out.print(table)
        out.print(
            f"ambient {' '.join(f'{a:.4f}' for a in cal.ambient)}; residual RMS {cal.fit['rms']:.5f} "
            f"over {cal.fit['samples']} panel pixels; {time.perf_counter() - t0:.1f} s"
        )
    if cal.projector is not None:
        flat = cal.projector.flat_field
        spread = (
            f", flat field {min(map(min, flat)):.3f}..{max(map(max, flat)):.3f}" if flat is not None else ""
        )
        out.print(
            f"projector light: intensity {' '.join(f'{x:.4f}' for x in cal.projector.intensity)} at "
            f"{cal.projector.reference_distance:.0f} mm{spread}"
        )
    out.print(f"[green]wrote[/] {args.out}")
    return 0


def _cmd_albedo(args: argparse.Namespace) -> int:
    from slscan.albedo.photometric import AlbedoConfig
    from slscan.capture.session import load_session
    from slscan.executor import Executor
    from slscan.viewer.layouts import albedo_blueprint
    from slscan.viewer.recording import recording_from_args

    config = AlbedoConfig(
        light=args.light, normals=args.normals, specular=args.specular, min_lights=args.min_lights
    )
    session = load_session(args.session)
    with recording_from_args(
        args, recording_name=f"albedo {args.session.name}", blueprint=albedo_blueprint()
    ) as rec:
        if rec is not None and session.calibration is not None:
            from slscan.viewer.log import log_rig

            log_rig(rec, session.calibration)
        run_albedo(
            session,
            args.range_maps,
            args.out,
            lights=args.lights,
            config=config,
            overwrite=args.overwrite,
            rec=rec,
            quiet=args.quiet,
            executor=Executor(scheduler=args.scheduler, workers=args.workers),
        )
    return 0


def run_albedo(
    session,
    range_maps: Path,
    out: Path,
    *,
    lights=None,
    config=None,
    overwrite: bool = False,
    rec=None,
    quiet: bool = False,
    executor=None,
) -> list:
    """:func:`~slscan.albedo.unshade.albedo_session` with a progress bar and a summary line."""
    from slscan.albedo.photometric import AlbedoConfig
    from slscan.albedo.unshade import albedo_session
    from slscan.executor import LOCAL

    t0 = time.perf_counter()
    with ProgressBar(len(session.views), "un-shading", quiet) as bar:
        results = albedo_session(
            session,
            range_maps,
            out,
            lights=lights,
            config=config or AlbedoConfig(),
            overwrite=overwrite,
            rec=rec,
            progress=bar.step,
            executor=executor or LOCAL,
        )
    valid = sum(r.valid_pixels for r in results)
    seen = sum(r.seen_pixels for r in results)
    light = "the projector as the light" if results and results[0].light == "projector" else "the ring lights"
    console().print(
        f"[green]wrote[/] {out}: {len(results)} albedo image(s) and mesh(es) from {light}, {valid:,} valid pixels "
        f"({100 * valid / max(seen, 1):.1f} % of the range maps'), {time.perf_counter() - t0:.1f} s"
    )
    return results
