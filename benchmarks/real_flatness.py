"""Flatness of the real kamino410 boards, each decoded with a calibration made without it.

    .venv/bin/python benchmarks/real_flatness.py [--data DIR] [--no-folds] [--views capture_0,capture_2]

The five kamino410/procam-calibration poses are flat printed chessboards 3.0-3.7 m from the
camera (9 x 7 inner corners, 75 mm squares). Each pose is decoded as ``slscan decode``
does (Gray code; with ``projector_axes`` "columns": the column edges; "both": the column
edges with their row interpolated from the row edges, those without one left out) and
triangulated with:

- our calibration made **without that pose** (leave one pose out: ``calibrate_session`` on
  the other four, ``--method both``), as light planes and as an inverse camera, the latter
  with the columns alone and with rows and columns (least squares, each axis weighted by
  its measured noise);
- the same, with the projector's principal point held at kamino410's value and the rest
  refitted on the same corners (``calibrate.diagnostics.refit_inverse_camera``): which of
  the two principal points reconstructs a flat board;
- kamino410's own ``calibration_result.xml`` (made from all five poses: not independent),
  projector pixels halved (``projector_scale=0.5``);
- our calibration from all five poses (not independent either).

Prints five tables:

1. flatness: per pose, RMS and 95th percentile (mm) of the points' distances to the plane
   fitted to those inside the board's outer corners, and the mean over poses; then the
   RMS left about a quadratic surface (what bending leaves), the RMS of the points more
   than 3 px from the print's edges (the squares' borders, where the albedo step moves the
   stripe edges) and the expected depth noise (``TriangulationReport``: the coordinate
   noise of the edges through each axis's depth per projector pixel).
2. per pose: the axes' depth change per projector pixel (columns, rows, both), the
   reprojection RMS of camera and projector in the five-pose calibration, and the RMS with
   which the calibration made without the pose predicts its corners in the projector
   (board pose from the camera's corners), for our calibration, ours with kamino410's
   principal point, and kamino410's file.
3. parameters: the five-pose value, its standard deviation from the Jacobian (each device
   calibrated alone, ``calibrateCameraExtended``), the spread over the five leave-one-out
   calibrations (standard deviation, min..max) and kamino410's value.
4. the projector principal point: ours against kamino410's, held on the same corners.
5. is the board bent? The leave-one-out points against the board's plane as the camera alone
   sees it (its pose from the corners), as a quadratic over the board (mm at the outer
   corners), per pose: the offset says whether the range map and the camera agree on where
   the board is; a bend of the board is the same quadratic in every pose (so is an error of
   the calibration common to these poses, which are all nearly facing the camera at
   3.0-3.7 m: the quadratic cannot tell the two apart here).

The data folder is ``slscan.data.shared_data_dir()`` (``$SLSCAN_DATA`` or ``../shared/data``)
unless ``--data`` is given. About 5 minutes on two cores (``--no-folds``: 1.5).
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from slscan.calibrate.diagnostics import held_out_errors, intrinsics_uncertainty, refit_inverse_camera
from slscan.calibrate.io import Calibration, calibration_planes, import_opencv_xml
from slscan.calibrate.pipeline import CalibrationConfig, CalibrationRun, calibrate_session
from slscan.calibrate.target import Board, board_image_id, board_pose
from slscan.capture.kamino410 import import_kamino410
from slscan.data import ENV_VAR, shared_data_dir
from slscan.decode.graycode import decode as gray_decode
from slscan.decode.pipeline import DecodeConfig
from slscan.decode.triangulate import RigPlanes, triangulate, triangulation_report

BOARD = Board(kind="chessboard", columns=9, rows=7, square=75.0)
LOO_HELD = "ours, kamino410's pp held (LOO)"
REFERENCE_SCALE = 0.5  # kamino410's projector pixels are half the patterns' (docs/calibration.md)


@dataclass(frozen=True)
class Flatness:
    """One pose triangulated one way: plane-fit RMS and p95 (mm), the RMS about a quadratic
    surface, the RMS of the points away from the print's edges (about the same plane), the
    points inside the board, the expected depth noise (mm), and the points and their pixels."""

    rms: float
    p95: float
    quadratic_rms: float
    away_rms: float
    points: int
    expected: float
    xyz: np.ndarray
    pixels: np.ndarray


def plane_flatness(points: np.ndarray, away: np.ndarray) -> tuple[float, float, float, float]:
    """RMS and 95th percentile of the distances (mm) of ``points`` (k, 3) to their
    least-squares plane, the RMS left about a quadratic surface over that plane, and the RMS
    of the distances of the points ``away`` (k,) bool."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    local = (points - centre) @ vt.T
    d = local[:, 2]
    x, y = local[:, 0] / 100.0, local[:, 1] / 100.0
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    coef, *_ = np.linalg.lstsq(design, d, rcond=None)
    return (float(np.sqrt(np.mean(d**2))), float(np.percentile(np.abs(d), 95)),
            float(np.sqrt(np.mean((d - design @ coef) ** 2))), float(np.sqrt(np.mean(d[away] ** 2))))


def print_edges(white: np.ndarray, reach: int = 3) -> np.ndarray:
    """(h, w) bool: pixels within ``reach`` px of an edge of the print (the chessboard's
    squares): the white frame's gradient over its local level above 5 %. Stripe edges there
    are found where the albedo changes within the blur, which moves them."""
    import cv2

    img = np.asarray(white, np.float64)
    img = img.mean(axis=2) if img.ndim == 3 else img
    level = np.maximum(cv2.blur(img, (5, 5)), 1e-6)
    grad = np.hypot(cv2.Sobel(img, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(img, cv2.CV_64F, 0, 1, ksize=3)) / 8
    edge = (grad / level > 0.05).astype(np.uint8)
    return cv2.dilate(edge, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)).astype(bool)


def bends(xyz: np.ndarray, camera_from_board: np.ndarray) -> tuple[np.ndarray, float]:
    """The points' departure from the board's plane as the camera alone sees it (the pose from
    its corners), as a quadratic over the board: ``(offset, tilt x, tilt y, xx, xy, yy)`` mm,
    x and y normalised to +-1 at the outer corners, and the RMS about it (mm)."""
    inv = np.linalg.inv(camera_from_board)
    b = xyz @ inv[:3, :3].T + inv[:3, 3]
    b = b[np.abs(b[:, 2]) < 30]  # on the board
    half = np.array([(BOARD.columns - 1) * BOARD.square / 2, (BOARD.rows - 1) * BOARD.square / 2])
    centre = half + BOARD.square
    x, y = (b[:, 0] - centre[0]) / half[0], (b[:, 1] - centre[1]) / half[1]
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1)
    coef, *_ = np.linalg.lstsq(design, b[:, 2], rcond=None)
    return coef, float(np.sqrt(np.mean((b[:, 2] - design @ coef) ** 2)))


def inside(quad: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(k,) bool: camera ``pixels`` (k, 2) inside the quadrilateral ``quad`` (4, 2)."""
    path = np.asarray(quad, np.float64)
    x, y = pixels[:, 0], pixels[:, 1]
    sign = []
    for i in range(4):
        (x0, y0), (x1, y1) = path[i], path[(i + 1) % 4]
        sign.append((x1 - x0) * (y - y0) - (y1 - y0) * (x - x0) > 0)
    sign = np.stack(sign)
    return sign.all(axis=0) | (~sign).all(axis=0)


def flatness(decoded, quad: np.ndarray, edges: np.ndarray, calibration: Calibration, source: str,
             axes: str) -> Flatness:
    """Triangulate a view's samples as ``decode_view`` does (``decoded``: the Gray-code
    decode with ``projector_axes`` = ``axes``), with ``calibration``'s ``source`` model, and
    fit a plane inside the board (``edges``: the print's edges, :func:`print_edges`)."""
    planes = calibration_planes(calibration, source=source)
    samples = decoded.samples
    noise = (decoded.stats.get("column_noise_px", np.nan), decoded.stats.get("row_noise_px", np.nan))
    sigma = tuple(float(n) if np.isfinite(n) and n > 0 else 1.0 for n in noise)
    points = triangulate(samples, calibration.camera, planes, sigma=sigma)
    report = triangulation_report(samples, points, calibration.camera, calibration.rig().projector, planes,
                                  sigma=noise)
    pixels = samples.pixels()
    keep = np.isfinite(points[:, 2]) & inside(quad, pixels)
    h, w = edges.shape
    at = np.clip(np.rint(pixels[keep]).astype(np.int64), 0, [w - 1, h - 1])
    rms, p95, quad_rms, away_rms = plane_flatness(points[keep], ~edges[at[:, 1], at[:, 0]])
    return Flatness(rms, p95, quad_rms, away_rms, int(keep.sum()), report.depth_noise_mm, points[keep],
                    pixels[keep])


def held_out_calibration(run: CalibrationRun, pp: tuple[float, float] | None) -> Calibration:
    """The inverse-camera calibration of ``run``, with the projector principal point held at
    ``pp`` and the rest refitted (None: as it is)."""
    if pp is None:
        return run.calibration
    rig = refit_inverse_camera(run.inverse_camera, BOARD, projector_principal_point=pp).rig
    return Calibration(camera=rig.camera, projector_size=run.calibration.projector_size, projector=rig.projector)


def corners_of(run: CalibrationRun, name: str):
    """Object points, camera corners and projector corners of view ``name`` in ``run``."""
    inv = run.inverse_camera
    i = inv.views.index(name)
    return BOARD.object_points(inv.object_ids[i]), inv.camera_points[i], inv.projector_points[i]


def fmt(values, spec=".2f") -> str:
    return "".join(f"{format(v, spec):>12}" for v in values)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=None, help=f"shared data folder (default ${ENV_VAR} or ../shared/data)")
    parser.add_argument("--no-folds", action="store_true", help="skip the leave-one-out calibrations")
    parser.add_argument("--views", default="", help="comma-separated poses to evaluate (default all)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    data = args.data or shared_data_dir()
    src = None if data is None else data / "procam_graycode_kamino410" / "sample_data"
    if src is None or not src.is_dir():
        print(f"kamino410 captures not found (set {ENV_VAR} or --data): nothing to measure")
        return
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        session = import_kamino410(src, Path(tmp) / "session")
        names = [v.name for v in session.views]
        shown = [n for n in names if not args.views or n in args.views.split(",")]
        config = CalibrationConfig(board=BOARD, method="both", planes_pattern="gray")
        full = calibrate_session(session, config)
        folds = {} if args.no_folds else {
            n: calibrate_session(replace(session, views=tuple(v for v in session.views if v.name != n)), config)
            for n in shown}
        t_cal = time.perf_counter() - t0
        reference = import_opencv_xml(src / "calibration_result.xml", projector_size=session.projector_size,
                                      projector_scale=REFERENCE_SCALE)
        ref_pp = (reference.projector.lens.cx, reference.projector.lens.cy)
        # the board's outer corners (its first and last inner corners of the first and last row)
        quads = {v.name: d.corners.reshape(-1, 2)[[0, BOARD.columns - 1, -1, -BOARD.columns]]
                 for v, d in zip(session.views, full.detections)}
        decoded = {(n, axes): gray_decode(session, n, DecodeConfig(projector_axes=axes))
                   for n in shown for axes in ("columns", "both")}
        t_dec = time.perf_counter() - t0 - t_cal

        rows = []  # (label, calibration per view, source, axes)
        if folds:
            rows += [
                ("ours, light planes (LOO)", {n: folds[n].calibration for n in shown}, "planes", "columns"),
                ("ours, inverse camera, columns (LOO)", {n: folds[n].calibration for n in shown},
                 "inverse-camera", "columns"),
                ("ours, inverse camera, rows+cols (LOO)", {n: folds[n].calibration for n in shown},
                 "inverse-camera", "both"),
                (LOO_HELD, {n: held_out_calibration(folds[n], ref_pp) for n in shown},
                 "inverse-camera", "both"),
            ]
        rows += [
            ("kamino410 XML, columns", {n: reference for n in shown}, "inverse-camera", "columns"),
            ("kamino410 XML, rows+cols", {n: reference for n in shown}, "inverse-camera", "both"),
            ("ours, 5 poses, light planes", {n: full.calibration for n in shown}, "planes", "columns"),
            ("ours, 5 poses, columns", {n: full.calibration for n in shown}, "inverse-camera", "columns"),
            ("ours, 5 poses, rows+cols", {n: full.calibration for n in shown}, "inverse-camera", "both"),
            ("ours, 5 poses, kamino410's pp held", {n: held_out_calibration(full, ref_pp) for n in shown},
             "inverse-camera", "both"),
        ]
        white_id = board_image_id(session)
        edges = {n: print_edges(session.read_image(session.view(n), session.view(n).image_for(white_id)))
                 for n in shown}
        results = {label: {n: flatness(decoded[n, axes], quads[n], edges[n], cals[n], source, axes) for n in shown}
                   for label, cals, source, axes in rows}
    elapsed = time.perf_counter() - t0

    print(f"kamino410 boards ({len(names)} poses, {BOARD.describe()}): calibrations {t_cal:.0f} s, "
          f"decoding {t_dec:.0f} s, total {elapsed:.0f} s")
    print("\n(1) flatness inside the board: plane-fit RMS / p95 mm per pose; means of the RMS, the p95, "
          "the RMS about a quadratic, the RMS away from the print's edges (3 px), the expected depth noise")
    head = f"{'calibration, projector model':<40}" + "".join(f"{n:>13}" for n in shown) + \
        f"{'RMS':>7}{'p95':>7}{'quad':>7}{'away':>7}{'exp.':>7}"
    print(head)
    print("-" * len(head))
    for label, per_view in results.items():
        cells = "".join(f"{f'{f.rms:.2f} / {f.p95:.2f}':>13}" for f in per_view.values())
        v = list(per_view.values())
        print(f"{label:<40}{cells}{np.mean([f.rms for f in v]):>7.2f}{np.mean([f.p95 for f in v]):>7.2f}"
              f"{np.mean([f.quadratic_rms for f in v]):>7.2f}{np.mean([f.away_rms for f in v]):>7.2f}"
              f"{np.nanmean([f.expected for f in v]):>7.2f}")

    print("\n(2) per pose: depth mm per projector px (columns / rows / both); five-pose calibration's "
          "reprojection RMS px (camera, projector); projector RMS px of the pose predicted without it "
          "(ours; ours with kamino410's pp) and by kamino410's file")
    head = f"{'pose':<11}{'mm/px col':>10}{'row':>7}{'both':>7}{'cam px':>8}{'proj px':>8}" \
           f"{'LOO proj':>10}{'LOO k-pp':>10}{'kamino':>9}{'corners':>9}"
    print(head)
    print("-" * len(head))
    inv = full.inverse_camera
    ref_rig = reference.rig()
    for n in shown:
        d = decoded[n, "both"]
        planes = RigPlanes(full.calibration.projector)
        pts = triangulate(d.samples, full.calibration.camera, planes)
        rep = triangulation_report(d.samples, pts, full.calibration.camera, full.calibration.projector, planes)
        c = rep.conditioning
        i = inv.views.index(n)
        obj, cam_pts, proj_pts = corners_of(full, n)
        loo = held_out_errors(folds[n].calibration.rig(), obj, cam_pts, proj_pts)[1] if folds else np.nan
        loo_k = held_out_errors(refit_inverse_camera(folds[n].inverse_camera, BOARD, projector_principal_point=ref_pp)
                                .rig, obj, cam_pts, proj_pts)[1] if folds else np.nan
        kam = held_out_errors(ref_rig, obj, cam_pts, proj_pts)[1]
        print(f"{n:<11}{c.columns:>10.1f}{c.rows:>7.1f}{c.both:>7.1f}{inv.view_errors[i, 0]:>8.3f}"
              f"{inv.view_errors[i, 1]:>8.3f}{loo:>10.3f}{loo_k:>10.3f}{kam:>9.3f}{len(obj):>9}")

    print("\n(3) parameters: five poses, Jacobian std (each device alone), leave-one-out std and range, kamino410")
    obj_all = [BOARD.object_points(ids) for ids in inv.object_ids]
    cam_u = intrinsics_uncertainty(obj_all, inv.camera_points, session.camera_size)
    proj_u = intrinsics_uncertainty(obj_all, inv.projector_points, session.projector_size)
    head = f"{'parameter':<26}{'5 poses':>10}{'Jacobian':>10}{'LOO std':>10}{'LOO range':>20}{'kamino410':>11}"
    print(head)
    print("-" * len(head))
    cal = full.calibration
    fold_cals = [f.calibration for f in folds.values()]

    def param(label, get, std, ref):
        values = [get(c) for c in fold_cals]
        spread = f"{min(values):.1f}..{max(values):.1f}" if values else "-"
        loo_std = np.std(values, ddof=1) if len(values) > 1 else np.nan
        print(f"{label:<26}{get(cal):>10.1f}{std:>10.1f}{loo_std:>10.1f}{spread:>20}{get(ref):>11.1f}")

    for k in ("fx", "fy", "cx", "cy"):
        param(f"camera {k} px", lambda c, k=k: getattr(c.camera, k), cam_u.std[k], reference)
    for k in ("fx", "fy", "cx", "cy"):
        param(f"projector {k} px", lambda c, k=k: getattr(c.projector.lens, k), proj_u.std[k], reference)
    for i, axis in enumerate("xyz"):
        param(f"projector centre {axis} mm", lambda c, i=i: c.projector.center[i], np.nan, reference)
    param("baseline mm", lambda c: float(np.linalg.norm(c.projector.center)), np.nan, reference)

    def angle(c) -> float:
        r = c.projector.rig_from_projector[:3, :3].T @ cal.projector.rig_from_projector[:3, :3]
        return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))

    param("projector turn vs 5-pose deg", angle, np.nan, reference)
    print(f"(camera alone: RMS {cam_u.rms:.3f} px; projector alone: RMS {proj_u.rms:.3f} px, "
          f"k1 {proj_u.lens.dist[0]:+.3f} +- {proj_u.std['k1']:.3f}, k2 {proj_u.lens.dist[1]:+.3f} +- "
          f"{proj_u.std['k2']:.3f}; stereo RMS {inv.stereo_rms:.3f} px)")

    print("\n(4) projector principal point: ours against kamino410's, on the same corners")
    held = refit_inverse_camera(inv, BOARD, projector_principal_point=ref_pp)
    ours_pp = (cal.projector.lens.cx, cal.projector.lens.cy)
    dist = np.hypot(ours_pp[0] - ref_pp[0], ours_pp[1] - ref_pp[1])
    print(f"ours ({ours_pp[0]:.1f}, {ours_pp[1]:.1f}) px, kamino410's ({ref_pp[0]:.1f}, {ref_pp[1]:.1f}) px: "
          f"{dist:.0f} px apart, {abs(ours_pp[0] - ref_pp[0]) / proj_u.std['cx']:.0f} and "
          f"{abs(ours_pp[1] - ref_pp[1]) / proj_u.std['cy']:.0f} Jacobian std in x and y")
    print(f"stereo RMS on our corners: free {inv.stereo_rms:.3f} px, kamino410's held {held.stereo_rms:.3f} px "
          f"(projector per pose {np.array2string(held.view_errors[:, 1], precision=3)} against "
          f"{np.array2string(inv.view_errors[:, 1], precision=3)})")
    if folds:
        mean = {label: np.mean([f.rms for f in results[label].values()]) for label in results}
        loo = "ours, inverse camera, rows+cols (LOO)"
        print(f"leave-one-out flatness, mean RMS: ours {mean[loo]:.2f} mm, "
              f"kamino410's pp held {mean[LOO_HELD]:.2f} mm")

    label = "ours, inverse camera, rows+cols (LOO)" if folds else "ours, 5 poses, rows+cols"
    print(f"\n(5) is the board bent? {label}: the points against the board's plane as the camera alone "
          "sees it (pose from its corners), as a quadratic over the board (mm at the outer corners)")
    head = f"{'pose':<11}{'offset':>8}{'tilt x':>8}{'tilt y':>8}{'xx':>7}{'xy':>7}{'yy':>7}{'RMS':>7}"
    print(head)
    print("-" * len(head))
    board_q = []
    for n, det in zip(names, full.detections):
        if n not in shown:
            continue
        cal_n = folds[n].calibration if folds else full.calibration
        coef, rms = bends(results[label][n].xyz, board_pose(cal_n.camera, det, BOARD))
        board_q.append(coef[3:])
        print(f"{n:<11}" + "".join(f"{c:>8.2f}" for c in coef[:3]) + "".join(f"{c:>7.2f}" for c in coef[3:])
              + f"{rms:>7.2f}")
    if len(board_q) > 1:
        bq = np.array(board_q)
        print(f"{'mean, std':<35}" + "".join(f"{m:>+7.2f}" for m in bq.mean(axis=0)) + "\n" + " " * 35
              + "".join(f"{v:>7.2f}" for v in bq.std(axis=0, ddof=1)))


if __name__ == "__main__":
    sys.exit(main())
