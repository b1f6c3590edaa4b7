"""Calibration accuracy: the virtual rig against its truth, the kamino410 captures against their tool.

    .venv/bin/python benchmarks/calibration.py [--scale 1.0] [--poses 6] [--board chessboard]
        [--data DIR] [--no-virtual] [--no-real]
    .venv/bin/python benchmarks/calibration.py --response [--against REV] [--scale 0.5]
        [--panel-scale 0.25]

Prints three tables (``--response``: the camera-response tables below instead).

1. Virtual rig (full size unless --scale): a board session (``--poses`` poses, white,
   hybrid and Gray code with row codes) calibrated by both methods. Errors against the
   true rig: camera and projector fx, fy, cx, cy (px), baseline (mm), and the light
   planes' normal angle error (degrees; mean and max over 64 columns across the
   projector, and for the raw planes over the measured features) — for the inverse
   camera, the light-plane model of the global fit, and the raw planes.
2. Virtual rig: a flat tile and the demo figurine captured with the true rig and decoded
   (hybrid and Gray code) with the true calibration and with each estimated one
   (``decode_view(..., planes=...)``); mean and 95th percentile of the range-map
   vertices' distance to the true surface (mm) and the ratio to the true calibration's.
   "shape" is the same after the best similarity transform (Umeyama) from the estimated
   calibration's points to the true calibration's (the same decoded samples): what is
   left once the calibration's small error of scale and pose is taken out (a 0.03 %
   error of focal length, about the best a few board poses give, is 0.4 mm at 1.3 m).
3. Real: the five kamino410/procam-calibration captures (9x7 chessboard, 75 mm squares)
   calibrated by both methods, next to the tool's ``calibration_result.xml``: stereo
   reprojection RMS (its 0.857 px), camera and projector fx, fy, cx, cy and baseline.
   That file's projector is in pixels half the size of the 1024x768 patterns (what the
   tool writes with ``graycode_step`` 2: triangulating our corner matches with it gives
   75 mm squares only with the projector coordinates doubled), so its projector
   intrinsics are compared after halving (``projector_scale=0.5``), and our stereo RMS is
   also given with the projector residuals in its units.

``--response``: does calibration undo the camera's tone curve (``camera.response``)? The
board session (Gray code with row codes, inverse-camera method) and the light panel
session are rendered twice, by a linear camera and by an sRGB one (the ``tone`` effect),
and calibrated by this tree and by ``--against REV`` (each in a child process with its
``toolbox/`` first on the path; the sessions are the same files): errors against the
true rig as above, the stereo and camera reprojection RMS, and the ring lights' position
error (mm) and intensity error (% of the true, max over RGB). Then the board corners found
in the white image as stored and with the curve undone, against their true projections
(the corner detector sees the stored image), and the kamino410 captures imported as
linear and as sRGB, calibrated by both trees. Last, a linearity check of the captures:
a pattern and its inverse add up to white plus black in linear light (``P + I = W + B``
whatever the blur and the global light), so on stripe-edge pixels (``|P - I|`` under a
quarter of ``W - B``) the median of ``(P + I - 2B) / (W - B)`` is 1 in the right response.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from slscan.calibrate.io import apply_calibration, calibration_planes, import_opencv_xml
from slscan.calibrate.pipeline import CalibrationConfig, calibrate_session
from slscan.calibrate.target import Board
from slscan.capture.kamino410 import import_kamino410
from slscan.capture.session import load_session
from slscan.data import shared_data_dir
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.decode.triangulate import RigPlanes
from slscan.virtual.boards import capture_calibration_session
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.scenes import builtin_object, flat_tile

sys.path.insert(0, str(Path(__file__).parent))
from measure import export_toolbox, run_json
from reconstruction import true_surface_distance

KAMINO_SQUARE_MM = 75.0
REFERENCE_RMS = 0.857


def angle_errors(planes_a: np.ndarray, planes_b: np.ndarray) -> np.ndarray:
    """Angles (n,) degrees between the normals of two plane sets (n, 4), sign ignored."""
    cos = np.abs(np.einsum("ij,ij->i", planes_a[:, :3], planes_b[:, :3]))
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale, rotation (3, 3), translation (3,) minimising |s R src + t - dst| (Umeyama 1991)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - ms, dst - md
    u, sig, vt = np.linalg.svd(b.T @ a / len(src))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / np.mean(np.sum(a**2, axis=1)))
    return scale, rot, md - scale * rot @ ms


def lens_row(name: str, lens, truth) -> str:
    if lens is None:
        return f"{name:<34}{'-':>9}{'-':>9}{'-':>9}{'-':>9}"
    d = [lens.fx - truth.fx, lens.fy - truth.fy, lens.cx - truth.cx, lens.cy - truth.cy]
    return (
        f"{name:<34}" + "".join(f"{v:>+9.3f}" for v in d) + f"   fx {100 * d[0] / truth.fx:+.3f} %"
    )


def virtual_tables(args) -> None:
    board = Board(kind=args.board, square=args.square)
    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    base = VirtualCaptureConfig(
        patterns="both",
        gray_rows=True,
        lit_images=False,
        levels=levels,
        camera_scale=args.scale,
        projector_scale=args.scale,
    )
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        session = capture_calibration_session(tmp / "board", board, config=base, n_poses=args.poses)
        t_capture = time.perf_counter() - t
        truth = session.calibration
        t = time.perf_counter()
        run = calibrate_session(session, CalibrationConfig(board=board, method="both"))
        t_cal = time.perf_counter() - t
        planes_only = calibrate_session(
            session, CalibrationConfig(board=board, method="planes", planes_pattern="gray")
        )
        cal = run.calibration
        print(
            f"(1) virtual rig: camera {truth.camera.width}x{truth.camera.height}, projector "
            f"{truth.projector.lens.width}x{truth.projector.lens.height}, {board.describe()}, "
            f"{len(session.views)} poses (capture {t_capture:.0f} s, calibration {t_cal:.1f} s)"
        )
        print(
            f"camera RMS {run.camera.rms:.3f} px; stereo RMS {run.inverse_camera.stereo_rms:.3f} px; "
            f"plane RMS {run.light_planes.rms_before:.4f} mm raw -> {run.light_planes.rms_after:.4f} mm "
            f"global fit ({len(run.light_planes.lines)} {run.light_planes.pattern} planes)"
        )
        head = f"{'error vs truth (px)':<34}{'fx':>9}{'fy':>9}{'cx':>9}{'cy':>9}"
        print(head)
        print("-" * len(head))
        print(lens_row("camera, Zhang (camera views only)", run.camera.lens, truth.camera))
        print(lens_row("camera, refined with projector", cal.camera, truth.camera))
        print(lens_row("projector, inverse camera", cal.projector.lens, truth.projector.lens))
        model = cal.light_planes
        print(
            f"{'projector, light-plane model':<34}{model.fx - truth.projector.lens.fx:>+9.3f}{'':>9}"
            f"{model.cx - truth.projector.lens.cx:>+9.3f}{'':>9}   fx {100 * (model.fx / truth.projector.lens.fx - 1):+.3f} %"
        )
        gm = planes_only.calibration.light_planes
        print(
            f"{'  (Gray-code edges, planes only)':<34}{gm.fx - truth.projector.lens.fx:>+9.3f}{'':>9}"
            f"{gm.cx - truth.projector.lens.cx:>+9.3f}"
        )
        true_centre = truth.projector.center
        print(
            f"baseline error: inverse camera {np.linalg.norm(cal.projector.center) - np.linalg.norm(true_centre):+.3f} mm "
            f"(centre off by {np.linalg.norm(cal.projector.center - true_centre):.3f} mm); light-plane model "
            f"centre off by {np.linalg.norm(model.center - true_centre):.3f} mm (its height along the axis is not observable)"
        )
        u = np.linspace(0, truth.projector.lens.width - 1, 64)
        true_planes = truth.projector.column_planes(u)
        rows = [
            ("inverse camera", angle_errors(RigPlanes(cal.projector).planes(u), true_planes)),
            ("light-plane model (hybrid lines)", angle_errors(model.planes(u), true_planes)),
            ("light-plane model (Gray edges)", angle_errors(gm.planes(u), true_planes)),
            (
                "raw planes (hybrid lines)",
                angle_errors(cal.raw_planes, truth.projector.column_planes(cal.raw_columns)),
            ),
        ]
        raw_g = planes_only.calibration
        rows.append(
            (
                "raw planes (Gray edges)",
                angle_errors(raw_g.raw_planes, truth.projector.column_planes(raw_g.raw_columns)),
            )
        )
        head = f"{'light-plane normals vs truth':<34}{'mean deg':>10}{'max deg':>10}"
        print(head)
        print("-" * len(head))
        for name, err in rows:
            print(f"{name:<34}{err.mean():>10.4f}{err.max():>10.4f}")

        # (2) reconstruction with the estimated calibrations
        scan = replace(base, gray_rows=False)
        scenes = {
            "tile": (capture_session(replace(scan, scene="tile"), tmp / "tile"), flat_tile()),
            "figurine": (capture_session(scan, tmp / "figurine"), builtin_object()),
        }
        variants = [
            ("true calibration", None, None),
            ("inverse camera", cal, "inverse-camera"),
            ("light-plane model", cal, "planes"),
            ("raw light planes", cal, "raw-planes"),
        ]
        print(
            "\n(2) reconstruction error vs the true surface (mm): estimated calibrations next to the true one"
        )
        head = (
            f"{'scene':<10}{'decode':<8}{'calibration':<20}{'vertices':>9}{'mean':>9}{'p95':>9}"
            f"{'mean/true':>11}{'shape mean':>12}{'shape/true':>12}"
        )
        print(head)
        print("-" * len(head))
        for name, (sess, scene) in scenes.items():
            sess = load_session(sess.root)
            view = sess.views[0]
            for method in ("hybrid", "gray"):
                ref = ref_points = None
                for label, c, source in variants:
                    if c is None:
                        result = decode_view(sess, view, DecodeConfig(method=method))
                    else:
                        result = decode_view(
                            apply_calibration(sess, c),
                            view,
                            DecodeConfig(method=method),
                            planes=calibration_planes(c, source=source),
                        )
                    vertices = result.range_map.vertices
                    d = true_surface_distance(vertices, scene, view.rig_from_object)
                    if ref is None:
                        ref, ref_points = d.mean(), result.points
                    both = np.isfinite(result.points[:, 0]) & np.isfinite(ref_points[:, 0])
                    scale, rot, t = similarity(result.points[both], ref_points[both])
                    shape = true_surface_distance(
                        scale * vertices @ rot.T + t, scene, view.rig_from_object
                    )
                    print(
                        f"{name:<10}{method:<8}{label:<20}{len(d):>9d}{d.mean():>9.4f}"
                        f"{np.percentile(d, 95):>9.4f}{d.mean() / ref:>11.3f}{shape.mean():>12.4f}"
                        f"{shape.mean() / ref:>12.3f}"
                    )


def real_table(data: Path) -> None:
    src = data / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        print(f"kamino410 captures not found at {src}: table skipped")
        return
    ref_path = src / "calibration_result.xml"
    with tempfile.TemporaryDirectory() as tmp:
        session = import_kamino410(src, Path(tmp) / "session")
        board = Board(kind="chessboard", columns=9, rows=7, square=KAMINO_SQUARE_MM)
        t = time.perf_counter()
        run = calibrate_session(
            session, CalibrationConfig(board=board, method="both", planes_pattern="gray")
        )
        elapsed = time.perf_counter() - t
        fixed = calibrate_session(
            session, CalibrationConfig(board=board, method="inverse-camera", refine_camera=False)
        )
    ref = import_opencv_xml(ref_path, projector_size=session.projector_size, projector_scale=0.5)
    ref_raw = import_opencv_xml(ref_path, projector_size=session.projector_size)
    cal = run.calibration
    inv = run.inverse_camera
    # stereo RMS with the projector residuals in the reference's (half-size) pixels
    e = inv.view_errors
    n = np.array([len(i) for i in inv.object_ids], float)
    rms_ref_units = float(np.sqrt(np.sum(n * (e[:, 0] ** 2 + 4 * e[:, 1] ** 2)) / (2 * n.sum())))
    print(
        f"\n(3) kamino410 captures ({len(session.views)} poses, {board.describe()}), {elapsed:.1f} s; "
        f"reference {ref_path.name}"
    )
    print(
        f"stereo RMS: ours {inv.stereo_rms:.3f} px (projector residuals in its half-size pixels: "
        f"{rms_ref_units:.3f} px; intrinsics fixed, as the tool: {fixed.inverse_camera.stereo_rms:.3f} px), "
        f"reference {ref.residuals['imported']['stereo_rms_px']:.3f} px; camera RMS {run.camera.rms:.3f} px"
    )
    head = f"{'':<36}{'ours':>11}{'reference':>11}{'diff':>10}{'diff %':>9}"
    print(head)
    print("-" * len(head))

    def row(name, a, b):
        print(f"{name:<36}{a:>11.2f}{b:>11.2f}{a - b:>+10.2f}{100 * (a - b) / b:>+9.2f}")

    for k in ("fx", "fy", "cx", "cy"):
        row(f"camera {k} px", getattr(cal.camera, k), getattr(ref.camera, k))
    for k in ("fx", "fy", "cx", "cy"):
        row(
            f"projector {k} px (reference / 2)",
            getattr(cal.projector.lens, k),
            getattr(ref.projector.lens, k),
        )
    row("projector fx px, light-plane model", cal.light_planes.fx, ref.projector.lens.fx)
    row("projector cx px, light-plane model", cal.light_planes.cx, ref.projector.lens.cx)
    row(
        "projector fx px, intrinsics fixed",
        fixed.calibration.projector.lens.fx,
        ref.projector.lens.fx,
    )
    row("baseline mm", np.linalg.norm(cal.projector.center), np.linalg.norm(ref.projector.center))
    print(
        f"(reference projector as written: fx {ref_raw.projector.lens.fx:.1f}, fy {ref_raw.projector.lens.fy:.1f}, "
        f"cx {ref_raw.projector.lens.cx:.1f}, cy {ref_raw.projector.lens.cy:.1f} px)"
    )
    print(
        f"light planes: {len(run.light_planes.lines)} Gray-code planes, RMS {run.light_planes.rms_before:.4f} mm raw, "
        f"{run.light_planes.rms_after:.4f} mm after the global fit"
    )


# --- camera response (--response) -------------------------------------------------------------


def response_child(paths: dict) -> dict:
    """Calibrate the sessions ``paths`` names with the toolbox on the path (one version)."""
    from slscan.albedo.lights import calibrate_lights

    board = Board(kind=paths["board_kind"], square=paths["square"])
    out: dict = {}
    for response in ("linear", "srgb"):
        session = load_session(paths[f"board-{response}"])
        truth = session.calibration
        run = calibrate_session(session, CalibrationConfig(board=board, method="inverse-camera"))
        cal = run.calibration
        out[f"board-{response}"] = {
            "camera": _lens_errors(cal.camera, truth.camera),
            "projector": _lens_errors(cal.projector.lens, truth.projector.lens),
            "baseline_mm": float(np.linalg.norm(cal.projector.center) - np.linalg.norm(truth.projector.center)),
            "centre_mm": float(np.linalg.norm(cal.projector.center - truth.projector.center)),
            "stereo_rms": run.inverse_camera.stereo_rms,
            "camera_rms": run.camera.rms,
        }
        panel = load_session(paths[f"panel-{response}"])
        true = np.array([light.position for light in panel.calibration.lights])
        true_i = np.array([light.intensity for light in panel.calibration.lights])
        rng = np.random.default_rng(3)  # started 40-80 mm off, as tests/albedo does
        start = true + rng.choice([-1, 1], true.shape) * rng.uniform(40, 80, true.shape)
        lights = calibrate_lights(panel, initial=start)
        out[f"panel-{response}"] = {
            "position_mm": np.linalg.norm(lights.positions - true, axis=1).tolist(),
            "intensity_pct": (100 * np.abs(lights.intensities / true_i - 1).max(axis=1)).tolist(),
        }
    if paths.get("kamino-linear"):
        board = Board(kind="chessboard", columns=9, rows=7, square=KAMINO_SQUARE_MM)
        for response in ("linear", "srgb"):
            run = calibrate_session(
                load_session(paths[f"kamino-{response}"]),
                CalibrationConfig(board=board, method="inverse-camera"),
            )
            cal = run.calibration
            out[f"kamino-{response}"] = {
                "stereo_rms": run.inverse_camera.stereo_rms,
                "camera_rms": run.camera.rms,
                **{f"camera {k}": float(getattr(cal.camera, k)) for k in ("fx", "fy", "cx", "cy")},
                **{f"projector {k}": float(getattr(cal.projector.lens, k)) for k in ("fx", "fy", "cx", "cy")},
                "baseline mm": float(np.linalg.norm(cal.projector.center)),
            }
    return out


def _lens_errors(lens, truth) -> list[float]:
    return [lens.fx - truth.fx, lens.fy - truth.fy, lens.cx - truth.cx, lens.cy - truth.cy]


def corner_errors(session, board: Board) -> tuple[float, float]:
    """RMS (px) of the board corners found in the white images against their true
    projections: in the image as stored, and with the camera's curve undone."""
    from slscan.calibrate.camera import detect_corners
    from slscan.calibrate.target import board_image_id
    from slscan.capture.session import linearise

    white = board_image_id(session)
    sq = [[], []]
    for view in session.views:
        image = session.read_image(view, view.image_for(white))
        true = session.calibration.camera.project_local(
            board.object_points() @ view.rig_from_object[:3, :3].T + view.rig_from_object[:3, 3])
        # a float image is read as fractions of full scale
        for k, img in enumerate((image, linearise(image, session.response))):
            det = detect_corners(img, board)
            if det:
                sq[k].append(np.sum((det.corners - true[det.ids]) ** 2, axis=1))
    return tuple(float(np.sqrt(np.mean(np.concatenate(s)))) if s else float("nan") for s in sq)


def edge_sum_ratio(session, view, response: str) -> float:
    """Median ``(P + I - 2B) / (W - B)`` on stripe-edge pixels of the column bits, the
    captures read as ``response``: 1 in linear light (see ``--response``)."""
    from slscan.capture.session import linearise
    from slscan.decode.graycode import gray_pairs
    from slscan.decode.masks import channel_mean

    def read(pid: str) -> np.ndarray:
        image = session.read_image(view, view.image_for(pid))
        top = float(np.iinfo(image.dtype).max)
        return channel_mean(linearise(image, response) if response != "linear" else image / np.float32(top))

    white_id, black_id = session.flat_frame_ids()
    w, b = read(white_id), read(black_id)
    span = w - b
    lit = span > 0.2
    ratios = []
    for pid, inv in gray_pairs(session.patterns, "columns"):
        p, q = read(pid), read(inv)
        edge = lit & (np.abs(p - q) < 0.25 * span)
        ratios.append(((p + q - 2 * b) / np.where(edge, span, 1))[edge])
    return float(np.median(np.concatenate(ratios)))


def response_tables(args) -> None:
    from slscan.virtual.panels import (
        LightPanelConfig,
        capture_light_calibration,
        light_calibration_poses,
    )

    board = Board(kind=args.board, square=args.square)
    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    base = VirtualCaptureConfig(patterns="gray", gray_rows=True, lit_images=False, levels=levels,
                                camera_scale=args.scale, projector_scale=args.scale)
    panel_config = LightPanelConfig(scale=args.panel_scale).capture_config()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        paths: dict = {"board_kind": args.board, "square": args.square}
        t = time.perf_counter()
        sessions = {}
        for response, effects in (("linear", ()), ("srgb", ("tone",))):
            sessions[response] = capture_calibration_session(
                tmp / f"board-{response}", board, config=replace(base, effects=effects), n_poses=args.poses)
            paths[f"board-{response}"] = str(tmp / f"board-{response}")
            config = replace(panel_config, effects=effects)
            capture_light_calibration(tmp / f"panel-{response}", config=config,
                                      poses=light_calibration_poses(config.rig()))
            paths[f"panel-{response}"] = str(tmp / f"panel-{response}")
        t_capture = time.perf_counter() - t
        data = None if args.no_real else (args.data or shared_data_dir())
        src = None if data is None else data / "procam_graycode_kamino410" / "sample_data"
        kamino = {}
        if src is not None and src.is_dir():
            for response in ("linear", "srgb"):
                kamino[response] = import_kamino410(src, tmp / f"kamino-{response}", response=response)
                paths[f"kamino-{response}"] = str(tmp / f"kamino-{response}")
        versions = []
        if args.against:
            versions.append((args.against, export_toolbox(args.against, tmp / "against")))
        versions.append(("this tree", None))
        results = {}
        for label, toolbox in versions:
            t = time.perf_counter()
            results[label] = run_json(
                [sys.executable, __file__, "--response-child", json.dumps(paths)], f"{label} calibration", toolbox)
            print(f"({label}: calibrations {time.perf_counter() - t:.0f} s)", file=sys.stderr)

        truth = sessions["linear"].calibration
        print(
            f"(R1) virtual rig: camera {truth.camera.width}x{truth.camera.height}, {board.describe()}, "
            f"{args.poses} poses, Gray code with row codes, inverse-camera method; light panel at scale "
            f"{args.panel_scale}, {len(panel_config.rig().lights)} lights (capture {t_capture:.0f} s). "
            "Camera: linear, or sRGB (effect 'tone')"
        )
        head = (f"{'camera':<8}{'code':<12}{'cam fx':>8}{'cam fy':>8}{'cam cx':>8}{'cam cy':>8}"
                f"{'prj fx':>8}{'prj fy':>8}{'prj cx':>8}{'prj cy':>8}{'base mm':>9}{'ctr mm':>8}"
                f"{'stereo':>8}{'cam rms':>8}{'light mm':>9}{'max mm':>8}{'int %':>7}{'max %':>7}")
        print("errors vs truth (px unless named); RMS px; lights: mean and max over the lights")
        print(head)
        print("-" * len(head))
        for response in ("linear", "srgb"):
            for label, _ in versions:
                r, lt = results[label][f"board-{response}"], results[label][f"panel-{response}"]
                print(
                    f"{response:<8}{label[:11]:<12}" + "".join(f"{v:>+8.3f}" for v in r["camera"] + r["projector"])
                    + f"{r['baseline_mm']:>+9.3f}{r['centre_mm']:>8.3f}{r['stereo_rms']:>8.3f}{r['camera_rms']:>8.3f}"
                    f"{np.mean(lt['position_mm']):>9.2f}{np.max(lt['position_mm']):>8.2f}"
                    f"{np.mean(lt['intensity_pct']):>7.2f}{np.max(lt['intensity_pct']):>7.2f}"
                )
        print("\n(R2) board corners found in the white image vs their true projections (RMS px)")
        head = f"{'camera':<8}{'as stored':>11}{'curve undone':>14}"
        print(head)
        print("-" * len(head))
        for response, session in sessions.items():
            stored, undone = corner_errors(session, board)
            print(f"{response:<8}{stored:>11.4f}{undone:>14.4f}")
        print("\n(R3) linearity check: median (P + I - 2B) / (W - B) on stripe-edge pixels (1 in linear light)")
        head = f"{'captures':<28}{'read as linear':>16}{'read as sRGB':>14}"
        print(head)
        print("-" * len(head))
        checks = [(f"virtual, {r} camera", s, s.views[0]) for r, s in sessions.items()]
        checks += [(f"kamino410 {v.name}", kamino["linear"], v) for v in kamino["linear"].views] if kamino else []
        for name, session, view in checks:
            print(f"{name:<28}{edge_sum_ratio(session, view, 'linear'):>16.3f}"
                  f"{edge_sum_ratio(session, view, 'srgb'):>14.3f}")
        if kamino:
            print("\n(R4) kamino410 captures, inverse-camera method, imported as linear and as sRGB")
            keys = list(results[versions[-1][0]]["kamino-linear"])
            head = f"{'':<20}" + "".join(f"{r + ' ' + label[:9]:>20}" for r in ("linear", "srgb") for label, _ in versions)
            print(head)
            print("-" * len(head))
            for k in keys:
                print(f"{k:<20}" + "".join(f"{results[label][f'kamino-{r}'][k]:>20.3f}"
                                         for r in ("linear", "srgb") for label, _ in versions))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="virtual rig resolution factor (1: 1440x960 camera)",
    )
    parser.add_argument(
        "--poses", type=int, default=6, help="board poses on the virtual rig (default 6)"
    )
    parser.add_argument("--board", choices=("chessboard", "charuco"), default="chessboard")
    parser.add_argument(
        "--square", type=float, default=50.0, help="virtual board square, mm (default 50)"
    )
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="shared data folder (default: $SLSCAN_DATA or ../shared/data)",
    )
    parser.add_argument("--no-virtual", action="store_true")
    parser.add_argument("--no-real", action="store_true")
    parser.add_argument("--response", action="store_true",
                        help="the camera-response tables (linear vs sRGB camera) instead")
    parser.add_argument("--against", metavar="REV",
                        help="with --response: git revision calibrated side by side with this tree")
    parser.add_argument("--panel-scale", type=float, default=0.25,
                        help="with --response: light panel session scale (default 0.25)")
    parser.add_argument("--response-child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    if args.response_child:
        print(json.dumps(response_child(json.loads(args.response_child))))
        return
    if args.response:
        response_tables(args)
        return
    if not args.no_virtual:
        virtual_tables(args)
    if not args.no_real:
        data = args.data or shared_data_dir()
        if data is None:
            print("shared data not found (set SLSCAN_DATA or pass --data): real table skipped")
        else:
            real_table(data)


if __name__ == "__main__":
    main()
