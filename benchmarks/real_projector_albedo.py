"""The projector as the light on real captures: how flat is the albedo of a flat print?

    nice .venv/bin/python benchmarks/real_projector_albedo.py [--data DIR]

The five kamino410/procam-calibration poses are a printed chessboard 3.0-3.7 m from the
camera, each with an all-white and an all-black frame (1280 x 1024, linear grey camera).
Each pose is imported, decoded (Gray code, columns) with kamino410's own calibration
(``calibration_result.xml``, projector pixels halved as in ``benchmarks/real_flatness.py``)
into a range map, and coloured with the projector as the light
(:func:`slscan.albedo.projector_light.projector_albedo_view`, uncalibrated: relative
albedo, which a coefficient of variation does not see).

A white square's paper is one albedo, so its albedo should be one value across the board
whatever the light's distance and angle. Scored inside the board's inner corners, on the
white squares only (the brighter class of an Otsu split of the white frame, 5 px away from
every square's border and from invalid pixels), per pose: the coefficient of variation
(std / mean, %) of the raw white frame, of white minus black, and of the albedo; and the
same after dividing out a plane fitted over the board (what is left besides a smooth
gradient). Where the white frame is not flat the albedo removes the projector's
inverse-square falloff and cosine; what it cannot remove is the projector's own hot
spot and the camera's vignetting (no flat-field map is known for this rig) and the paper's
own sheen.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from slscan.albedo.lights import ProjectorLight
from slscan.albedo.photometric import AlbedoConfig
from slscan.albedo.projector_light import projector_albedo_view, read_flat_frames
from slscan.calibrate.io import import_opencv_xml
from slscan.capture.kamino410 import import_kamino410
from slscan.data import ENV_VAR, shared_data_dir
from slscan.decode.pipeline import DecodeConfig, decode_view

REFERENCE_SCALE = 0.5  # kamino410's projector pixels are half the patterns' (docs/calibration.md)
CORNERS = (9, 7)
AWAY_PX = 5


def board_mask(white: np.ndarray) -> np.ndarray | None:
    """(h, w) bool inside the board's inner corners, or None when they are not found."""
    grey = np.clip(white / max(np.percentile(white, 99.5), 1e-9) * 255, 0, 255).astype(np.uint8)
    found, corners = cv2.findChessboardCorners(grey, CORNERS)
    if not found:
        return None
    hull = cv2.convexHull(corners.reshape(-1, 2).astype(np.float32)).astype(np.int32)
    mask = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool)


def cv(values: np.ndarray) -> float:
    return float(100 * values.std() / values.mean())


def detrended_cv(values: np.ndarray, pixels: np.ndarray) -> float:
    """CV after dividing by the plane a + b x + c y fitted to ``values`` over ``pixels`` (n, 2)."""
    design = np.column_stack([np.ones(len(values)), pixels.astype(np.float64)])
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    return cv(values / (design @ coef))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--windows", default="0,9,21,41",
                        help="projector_normal_window_px values to compare (0: the range map's vertex normals; "
                        "the default 21)")
    parser.add_argument("--data", type=Path, default=None,
                        help=f"shared data folder (default ${ENV_VAR} or ../shared/data)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    data = args.data or shared_data_dir()
    src = data / "procam_graycode_kamino410" / "sample_data" if data else None
    if src is None or not src.is_dir():
        print(f"kamino410 captures not found (set {ENV_VAR} or --data): nothing to measure")
        return 0
    t0 = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        session = import_kamino410(src, Path(tmp) / "session")
        reference = import_opencv_xml(src / "calibration_result.xml", projector_size=session.projector_size,
                                      projector_scale=REFERENCE_SCALE)
        rig = reference.rig(working_distance=3300.0)
        session = replace(session, calibration=rig, calibration_source="kamino410 calibration_result.xml")
        light = ProjectorLight(reference_distance=rig.working_distance)
        windows = [int(w) for w in args.windows.split(",")]
        for view in session.views:
            range_map = decode_view(session, view, DecodeConfig(projector_axes="columns")).range_map
            results = {w: projector_albedo_view(session, view, range_map, light,
                                                AlbedoConfig(projector_normal_window_px=w)) for w in windows}
            result = results[windows[0]]
            frames = read_flat_frames(session, view)
            white = frames.white[..., 0].astype(np.float64)
            signal = white - frames.black[..., 0]
            board = board_mask(white)
            if board is None:
                print(f"{view.name}: the chessboard's corners are not found; left out")
                continue
            bright = np.zeros(white.shape, np.uint8)
            inside = board & np.logical_and.reduce([r.valid for r in results.values()])
            scaled = np.clip(white / np.percentile(white[board], 99.5) * 255, 0, 255).astype(np.uint8)
            level, _ = cv2.threshold(scaled[inside], 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
            bright[inside & (scaled > level)] = 1
            kernel = np.ones((2 * AWAY_PX + 1,) * 2, np.uint8)
            paper = cv2.erode(bright, kernel).astype(bool)
            ys, xs = np.nonzero(paper)
            pixels = np.column_stack([xs, ys])
            values = {"white frame": white[paper], "white - black": signal[paper]}
            for w, r in results.items():
                values[f"albedo, normals {'of the range map' if w == 0 else f'up to {w} px'}"] = (
                    r.albedo[..., 0].astype(np.float64)[paper])
            depth = result.surface.points[..., 2][paper]
            rows.append((view.name, int(paper.sum()), float(np.median(depth)),
                         {k: (cv(v), detrended_cv(v, pixels)) for k, v in values.items()},
                         float(100 * result.valid[board].mean())))
    print(f"\nkamino410 chessboard, white squares only ({time.perf_counter() - t0:.0f} s): coefficient of "
          "variation % (raw / after a fitted plane)")
    names = list(rows[0][3]) if rows else []
    print("| pose | pixels | depth (mm) | albedo valid on board % | " + " | ".join(names) + " |")
    print("|---" * (4 + len(names)) + "|")
    for name, n, depth, cvs, share in rows:
        cells = " | ".join(f"{a:.2f} / {b:.2f}" for a, b in cvs.values())
        print(f"| {name} | {n:,} | {depth:.0f} | {share:.1f} | {cells} |")
    if rows:
        means = [(np.mean([r[3][k][0] for r in rows]), np.mean([r[3][k][1] for r in rows])) for k in names]
        print("| mean | | | | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in means) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
