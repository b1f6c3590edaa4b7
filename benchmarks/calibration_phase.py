"""Calibration with phase shifting next to Gray code, on the same virtual board poses.

    .venv/bin/python benchmarks/calibration_phase.py [--scale 1.0] [--poses 6]
        [--distortion K1,K2,P1,P2,K3] [--no-distorted] [--sessions DIR]

Two virtual rigs: the paper's (an undistorted projector), and the same with the
projector's lens distorted (``--distortion``, OpenCV order; the virtual rig renders the
patterns through it). For each, one board session (``--poses`` poses of a 9x7 chessboard
of 50 mm squares) carries Gray code **and** phase shifting, both with rows: the white
frames, hence the camera's corners and calibration, are the same for both, so what
differs is the projector correspondences alone. Two held-out scenes, the flat tile and
the figurine, are captured with the same patterns by the true rig. Full size unless
``--scale``; ``--sessions DIR`` keeps the captures there and reuses them on the next run.

Prints, per rig:

1. The projector as an inverse camera, from the Gray code's stripe edges (``gray
   edges``), from phase shifting's every decoded pixel as one-coordinate constraints
   (``phase edges``, the default for phase) and from its pixels with both coordinates,
   RANSAC (``phase pixels``): reprojection RMS of the camera (Zhang, the same for all),
   of the projector and of the stereo calibration (px); the projector's errors against
   the truth: fx, fy (%), cx, cy (px), "lens" (RMS and max over the projector image of
   the pixel the estimated lens gives to the true lens's rays: intrinsics and distortion
   together, px), rotation (deg) and centre (mm); and the board corners mapped into the
   projector against their true projections (RMS px): "corners" from the corners
   detected in the camera, "homog." from the true camera corners (the local homographies
   alone, without the camera's corner error). (1b): the same calibrations from the true
   camera corners (the camera calibrated from them, each projector corner mapped from
   them): what each kind of correspondence allows once the camera's corner detection,
   the same for all, is taken out.
2. The light planes (the paper's method) from the Gray-code edges and from phase
   shifting (one plane per whole projector column, where camera rows cross it): planes,
   points, point-to-plane RMS before and after the global fit (mm), the model's fx (%)
   and cx (px) errors, and the angle of the model's and of the raw planes' normals to the
   true column planes (deg; mean and max, the model over 64 columns across the projector).
3. Reconstruction: each held-out scene decoded with phase shifting (column and row, ray to
   ray) and with Gray code (columns), with the true calibration and with each estimated
   one; mean and 95th percentile of the range-map vertices' distance to the true surface
   (mm), the mean over the true calibration's, and "shape": the mean after the best
   similarity transform onto the true calibration's points (what is left once the
   calibration's small error of scale and pose is taken out) and that transform's scale
   error (parts per million; 100 ppm is 0.13 mm at 1.3 m).
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from slscan.calibrate.camera import calibrate_camera, detect_corners
from slscan.calibrate.io import Calibration, apply_calibration, calibration_planes
from slscan.calibrate.pipeline import CalibrationConfig, calibrate_session
from slscan.calibrate.procam import (
    calibrate_inverse_camera,
    default_half_window,
    projector_corners,
    projector_corners_from_edges,
)
from slscan.calibrate.target import Board, CornerDetection, board_image_id
from slscan.capture.session import load_session
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.patterns import family
from slscan.virtual.boards import capture_calibration_session
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.scenes import builtin_object, flat_tile

sys.path.insert(0, str(Path(__file__).parent))
from calibration import angle_errors, similarity
from reconstruction import true_surface_distance

PATTERNS = "gray+phase"
DISTORTION = (0.06, -0.04, 0.0005, -0.0005, 0.0)
"""Default projector lens distortion of the second rig: pincushion (the camera's is barrel),
3.7-4.6 px at the projector's corners, and a little decentring."""
INVERSE = (("gray edges", "gray", "edges"), ("phase edges", "phase", "edges"),
           ("phase pixels", "phase", "pixels"))


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (deg) of the rotation between two (3, 3) rotations."""
    r = a.T @ b
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))


def lens_error(lens, truth) -> tuple[float, float]:
    """RMS and max (px) over a grid of the projector image: the pixel ``lens`` gives to the
    ray ``truth`` sees through that pixel (intrinsics and distortion together)."""
    u, v = np.meshgrid(np.linspace(0, truth.width - 1, 33), np.linspace(0, truth.height - 1, 25))
    pix = np.stack([u, v], -1).reshape(-1, 2)
    err = np.linalg.norm(lens.project_local(truth.rays_local(pix)) - pix, axis=1)
    return float(np.sqrt(np.mean(err**2))), float(err.max())


def true_detections(session, board: Board) -> list[CornerDetection]:
    """Every view's board corners where the true camera sees them (no detection error)."""
    out = []
    for view in session.views:
        pose = view.rig_from_object
        points = board.object_points() @ pose[:3, :3].T + pose[:3, 3]
        out.append(CornerDetection(view.name, session.calibration.camera.project_local(points),
                                   np.arange(len(points))))
    return out


def true_corner_mapping(session, board: Board, name: str, correspondences: str, detections):
    """The true camera corners of every view mapped into the projector by the local
    homographies of ``name``'s codes: the :class:`ProjectorCorners` per view, and (k,) px
    their distance to the true projections (the homographies' own error)."""
    truth = session.calibration
    white = board_image_id(session)
    pcs, errors = [], []
    dec = family(name).decode_module()
    for view, det in zip(session.views, detections):
        pose = view.rig_from_object
        points = board.object_points() @ pose[:3, :3].T + pose[:3, 3]
        found = detect_corners(session.read_image(view, view.image_for(white)), board)
        half = default_half_window(found, board)  # the window the calibration uses
        if correspondences == "edges":
            pc = projector_corners_from_edges(dec.projector_constraints(session, view), det.corners,
                                              half_window=half)
        else:
            codes = dec.projector_codes(session, view)
            pc = projector_corners(codes.column, codes.row, codes.mask, det.corners, half_window=half)
        pcs.append(pc)
        errors.append(np.linalg.norm(pc.points - truth.projector.project(points), axis=1)[pc.ok])
    return pcs, np.concatenate(errors)


def corner_errors(session, board: Board, run) -> np.ndarray:
    """(k,) px: the detected corners mapped into the projector, against the truth."""
    out = []
    for view in session.views:
        pc = run.projector_corners.get(view.name)
        if pc is None:
            continue
        pose = view.rig_from_object
        points = board.object_points() @ pose[:3, :3].T + pose[:3, 3]
        out.append(np.linalg.norm(pc.points - session.calibration.projector.project(points), axis=1)[pc.ok])
    return np.concatenate(out)


def capture(root: Path, base: VirtualCaptureConfig, rig, board: Board, poses: int):
    """The rig's board session and held-out scenes under ``root`` (reused when there)."""
    t = time.perf_counter()
    done = (root / "board" / "session.json").is_file()
    board_session = (load_session(root / "board") if done else
                     capture_calibration_session(root / "board", board, patterns=PATTERNS, config=base,
                                                 n_poses=poses, rig=rig))
    scenes = {}
    for name, scene_name, truth in (("tile", "tile", flat_tile()), ("figurine", "object", builtin_object())):
        path = root / name
        if not (path / "session.json").is_file():
            capture_session(replace(base, scene=scene_name, patterns=PATTERNS), path, rig=rig)
        scenes[name] = (load_session(path), truth)
    return board_session, scenes, time.perf_counter() - t


def rig_tables(label: str, session, scenes, board: Board, elapsed: float) -> None:
    truth = session.calibration
    tl = truth.projector.lens
    print(f"\n=== {label}: camera {truth.camera.width}x{truth.camera.height}, projector {tl.width}x{tl.height}, "
          f"projector distortion {list(tl.dist)}; {board.describe()}, {len(session.views)} poses, "
          f"{PATTERNS} with rows (capture {elapsed:.0f} s)")

    # (1) the inverse camera
    runs, ideal = {}, {}
    head = (f"{'correspondences':<14}{'cam rms':>8}{'prj rms':>8}{'stereo':>8}{'fx %':>8}{'fy %':>8}{'cx px':>8}"
            f"{'cy px':>8}{'lens rms':>9}{'max':>7}{'rot deg':>9}{'ctr mm':>8}{'corners':>9}{'homog.':>8}{'s':>5}")

    def row(name, cam_rms, inv, corners, homog, elapsed):
        proj = inv.rig.projector
        lens = proj.lens
        lrms, lmax = lens_error(lens, tl)
        print(f"{name:<14}{cam_rms:>8.4f}{inv.projector_rms:>8.4f}{inv.stereo_rms:>8.4f}"
              f"{100 * (lens.fx / tl.fx - 1):>+8.3f}{100 * (lens.fy / tl.fy - 1):>+8.3f}{lens.cx - tl.cx:>+8.3f}"
              f"{lens.cy - tl.cy:>+8.3f}{lrms:>9.3f}{lmax:>7.3f}"
              f"{rotation_deg(proj.rig_from_projector[:3, :3], truth.projector.rig_from_projector[:3, :3]):>9.4f}"
              f"{np.linalg.norm(proj.center - truth.projector.center):>8.3f}"
              f"{np.sqrt(np.mean(corners**2)):>9.4f}{np.sqrt(np.mean(homog**2)):>8.4f}{elapsed:>5.0f}")

    print("\n(1) projector as an inverse camera, errors vs the true rig")
    print(head)
    print("-" * len(head))
    true_dets = true_detections(session, board)
    mapped = {}
    for name, fam, corr in INVERSE:
        t = time.perf_counter()
        run = calibrate_session(session, CalibrationConfig(board=board, method="inverse-camera",
                                                           inverse_pattern=fam, correspondences=corr))
        elapsed = time.perf_counter() - t
        runs[name] = run
        mapped[name] = true_corner_mapping(session, board, fam, corr, true_dets)
        row(name, run.camera.rms, run.inverse_camera, corner_errors(session, board, run), mapped[name][1], elapsed)

    print("\n(1b) the same with the true camera corners (the camera's corner detection left out: what the "
          "projector's correspondences alone allow)")
    print(head)
    print("-" * len(head))
    camera = calibrate_camera(true_dets, board, session.camera_size)
    for name, _, _ in INVERSE:
        pcs, homog = mapped[name]
        t = time.perf_counter()
        inv = calibrate_inverse_camera(camera.lens, [(d.source, d, pc) for d, pc in zip(true_dets, pcs)], board,
                                       session.projector_size)
        elapsed = time.perf_counter() - t
        ideal[name] = Calibration(camera=inv.rig.camera, projector_size=session.projector_size,
                                  projector=inv.rig.projector, board=board)
        row(name, camera.rms, inv, homog, homog, elapsed)

    # (2) the light planes
    print("\n(2) light planes (the paper's method), errors vs the true column planes")
    head = (f"{'features':<14}{'planes':>7}{'points':>9}{'rms mm':>8}{'global':>8}{'fx %':>8}{'cx px':>8}"
            f"{'model deg':>10}{'max':>7}{'raw deg':>9}{'max':>7}{'s':>5}")
    print(head)
    print("-" * len(head))
    u = np.linspace(0, tl.width - 1, 64)
    true_planes = truth.projector.column_planes(u)
    for fam in ("gray", "phase"):
        t = time.perf_counter()
        run = calibrate_session(session, CalibrationConfig(board=board, method="planes", planes_pattern=fam))
        elapsed = time.perf_counter() - t
        runs[f"{fam} planes"] = run
        lp, model = run.light_planes, run.calibration.light_planes
        m_err = angle_errors(model.planes(u), true_planes)
        raw = angle_errors(lp.lines.planes, truth.projector.column_planes(lp.lines.columns))
        name = "Gray edges" if fam == "gray" else "phase columns"
        print(f"{name:<14}{len(lp.lines):>7d}{int(lp.lines.counts.sum()):>9d}{lp.rms_before:>8.4f}{lp.rms_after:>8.4f}"
              f"{100 * (model.fx / tl.fx - 1):>+8.3f}{model.cx - tl.cx:>+8.3f}{m_err.mean():>10.4f}{m_err.max():>7.4f}"
              f"{raw.mean():>9.4f}{raw.max():>7.4f}{elapsed:>5.0f}")

    # (3) reconstruction of held-out scenes
    variants = [("true calibration", None, None)]
    variants += [(f"inverse cam, {name}", runs[name].calibration, "inverse-camera") for name, _, _ in INVERSE]
    variants += [(f"  true corners, {name}", ideal[name], "inverse-camera") for name, _, _ in INVERSE]
    variants += [("planes, Gray edges", runs["gray planes"].calibration, "planes"),
                 ("planes, phase", runs["phase planes"].calibration, "planes")]
    print("\n(3) reconstruction error vs the true surface (mm), held-out scenes captured by the true rig")
    head = (f"{'scene':<10}{'decode':<8}{'calibration':<28}{'vertices':>9}{'mean':>9}{'p95':>9}{'mean/true':>11}"
            f"{'shape mean':>12}{'scale ppm':>11}")
    print(head)
    print("-" * len(head))
    for scene_name, (sess, scene) in scenes.items():
        view = sess.views[0]
        for method in ("phase", "gray"):
            ref = ref_points = None
            for name, cal, source in variants:
                if cal is None:
                    result = decode_view(sess, view, DecodeConfig(method=method))
                else:
                    result = decode_view(apply_calibration(sess, cal), view, DecodeConfig(method=method),
                                         planes=calibration_planes(cal, source=source))
                vertices = result.range_map.vertices
                d = true_surface_distance(vertices, scene, view.rig_from_object)
                if ref is None:
                    ref, ref_points = d.mean(), result.points
                both = np.isfinite(result.points[:, 0]) & np.isfinite(ref_points[:, 0])
                scale, rot, t = similarity(result.points[both], ref_points[both])
                shape = true_surface_distance(scale * vertices @ rot.T + t, scene, view.rig_from_object)
                print(f"{scene_name:<10}{method:<8}{name:<28}{len(d):>9d}{d.mean():>9.4f}{np.percentile(d, 95):>9.4f}"
                      f"{d.mean() / ref:>11.3f}{shape.mean():>12.4f}{1e6 * (scale - 1):>+11.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=1.0, help="virtual rig resolution factor (1: 1440x960 camera)")
    parser.add_argument("--poses", type=int, default=6, help="board poses (default 6)")
    parser.add_argument("--distortion", default=",".join(f"{v:g}" for v in DISTORTION),
                        help="the second rig's projector distortion, OpenCV k1,k2,p1,p2,k3 (default %(default)s)")
    parser.add_argument("--no-distorted", action="store_true", help="only the rig with an undistorted projector")
    parser.add_argument("--sessions", type=Path, default=None,
                        help="keep the captured sessions in this folder and reuse them (default: a temporary one)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    distortion = tuple(float(v) for v in args.distortion.split(","))
    if len(distortion) != 5:
        parser.error("--distortion: expected 5 numbers k1,k2,p1,p2,k3")
    board = Board(columns=9, rows=7, square=50.0)
    base = VirtualCaptureConfig(gray_rows=True, lit_images=False, camera_scale=args.scale,
                                projector_scale=args.scale)
    rig = base.rig()
    rigs = [("undistorted projector", "undistorted", rig)]
    if not args.no_distorted:
        lens = replace(rig.projector.lens, dist=distortion)
        rigs.append(("distorted projector", "distorted", replace(rig, projector=replace(rig.projector, lens=lens))))
    with tempfile.TemporaryDirectory() as tmp:
        root = args.sessions or Path(tmp)
        for label, folder, r in rigs:
            session, scenes, elapsed = capture(root / f"{folder}-{args.scale:g}-{args.poses}", base, r, board,
                                               args.poses)
            rig_tables(label, session, scenes, board, elapsed)


if __name__ == "__main__":
    main()
