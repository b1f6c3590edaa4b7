"""Albedo accuracy on the virtual rig, against its ground truth.

    .venv/bin/python benchmarks/albedo.py [--scale 1.0] [--panel-scale 0.5]

The built-in figurine at full size (specular lobe 0.12, shininess 30, self-shadowing,
saturated paint), one view: captured, decoded into a range map, and un-shaded with

- the lights **estimated** by ``calibrate-lights`` from a matte-panel session captured on
  the same virtual rig (6 poses), and with the **true** lights (and true ambient);
- photometric normals (default) and, for comparison, the range map's own normals;

next to the naive colour images: the **white frame** and the **mean of the lit images**,
each scaled by the one global factor that best fits the truth (so only shading is
measured, not exposure). Albedo from the estimated lights is absolute (no scale fitted);
the factor that would best fit it is printed as "scale".

Pixels scored: on the range map and valid in the albedo image (the "coverage" column is
the share of scored-eligible pixels that are valid), **lit** (at least 3 ring lights
reach the surface; and separately lit by all of them) and **non-grazing** (true normal
within 75° of the viewing ray). Errors per channel are relative RMS,
``RMS(estimate - truth) / RMS(truth)``; "within 5 %" is the share of pixels whose RGB
error ``|estimate - truth| / |truth|`` is under 5 %. Truth is the simulator's albedo at
the pixel centre, and the same blurred by the camera's optical blur (σ = 0.5 px; no
un-shading can be sharper than the images it comes from).
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from slscan.albedo.lights import LightCalibration, calibrate_lights
from slscan.albedo.photometric import AlbedoConfig
from slscan.albedo.radiometry import exposure_factor, read_lit_images
from slscan.albedo.unshade import albedo_view
from slscan.decode.pipeline import decode_view
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.panels import capture_light_calibration
from slscan.virtual.render import trace_view
from slscan.virtual.scenes import builtin_object


def scores(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, float]:
    """Relative RMS per channel (3,) and share of pixels within 5 % (RGB norm)."""
    e, t = estimate[mask].astype(np.float64), truth[mask].astype(np.float64)
    rel = np.sqrt(((e - t) ** 2).mean(0)) / np.sqrt((t**2).mean(0))
    pix = np.linalg.norm(e - t, axis=1) / np.linalg.norm(t, axis=1)
    return rel, float((pix < 0.05).mean())


def best_scale(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    e, t = estimate[mask].ravel().astype(np.float64), truth[mask].ravel().astype(np.float64)
    return float((e @ t) / (e @ e))


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--scale", type=float, default=1.0, help="figurine session size (default 1: 1440x960)"
    )
    parser.add_argument(
        "--panel-scale", type=float, default=0.5, help="light-panel session size (default 0.5)"
    )
    parser.add_argument("--keep", type=Path, default=None, help="keep the sessions in this folder")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")

    tmp = tempfile.TemporaryDirectory()
    root = args.keep or Path(tmp.name)
    levels = 9 if args.scale >= 1 else max(5, int(np.log2(1024 * args.scale)) - 1)
    config = VirtualCaptureConfig(
        camera_scale=args.scale, projector_scale=args.scale, levels=levels
    )

    t0 = time.perf_counter()
    session = capture_session(config, root / "figurine", overwrite=True)
    view = session.views[0]
    t_capture = time.perf_counter() - t0
    t0 = time.perf_counter()
    range_map = decode_view(session, view).range_map
    t_decode = time.perf_counter() - t0

    panel_config = replace(
        config, camera_scale=args.panel_scale, projector_scale=args.panel_scale, levels=5
    )
    t0 = time.perf_counter()
    panel_session = capture_light_calibration(root / "panel", config=panel_config, overwrite=True)
    estimated = calibrate_lights(panel_session)
    t_lights = time.perf_counter() - t0
    rig = session.calibration
    true_lights = LightCalibration.from_rig(rig, ambient=config.optics.ambient)

    # --- truth --------------------------------------------------------------------------
    scene = builtin_object()
    geom = trace_view(scene, rig, view.rig_from_object)
    truth = session.load_ground_truth(view)
    albedo_true = truth.albedo.astype(np.float64)
    seen = np.isfinite(albedo_true[..., 0])
    blurred = cv2.GaussianBlur(
        np.where(seen[..., None], albedo_true, 0).astype(np.float32),
        (0, 0),
        config.sensor.blur_sigma,
    ).astype(np.float64)
    lit_count = (geom.light_diffuse > 0).sum(0)
    rays = rig.camera.rays_local(
        np.stack(
            np.meshgrid(
                np.arange(rig.camera.width, dtype=float), np.arange(rig.camera.height, dtype=float)
            ),
            -1,
        )
    )
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos_view = -np.einsum("hwi,hwi->hw", np.nan_to_num(truth.normal.astype(np.float64)), rays)
    non_grazing = seen & (cos_view > np.cos(np.radians(75)))

    # --- light calibration ---------------------------------------------------------------
    pos_err = np.linalg.norm(estimated.positions - true_lights.positions, axis=1)
    int_err = np.abs(estimated.intensities / true_lights.intensities - 1).max(axis=1)
    print(
        f"\nLight calibration: {len(panel_session.views)} panel poses at scale {args.panel_scale}, "
        f"{estimated.fit['samples']} panel pixels, {t_lights:.1f} s"
    )
    print("| light | position error (mm) | 1-sigma (mm) | intensity error (max RGB) |")
    print("|---|---|---|---|")
    for k in range(len(pos_err)):
        print(
            f"| {k} | {pos_err[k]:.2f} | {estimated.position_sigma[k]:.2f} | {100 * int_err[k]:.2f} % |"
        )
    print(
        f"ambient: estimated {np.round(estimated.ambient, 4).tolist()}, true {list(config.optics.ambient)}"
    )

    # --- methods ------------------------------------------------------------------------
    factor = exposure_factor(session, view)
    white = session.read_image(view, view.image_for("white")).astype(np.float64) / (255.0 * factor)
    lit_mean = read_lit_images(session, view).values.mean(0).astype(np.float64)
    runs = {}
    for name, lights, cfg in (
        ("un-shaded, estimated lights", estimated, AlbedoConfig()),
        ("un-shaded, true lights", true_lights, AlbedoConfig()),
        (
            "un-shaded, estimated lights, range-map normals",
            estimated,
            AlbedoConfig(normals="range"),
        ),
        ("un-shaded, estimated lights, no specular fit", estimated, AlbedoConfig(specular="none")),
    ):
        t0 = time.perf_counter()
        result = albedo_view(session, view, range_map, lights, cfg)
        runs[name] = (result, time.perf_counter() - t0)
    reference = runs["un-shaded, estimated lights"][0]
    valid_all = reference.valid
    for result, _ in runs.values():
        valid_all = valid_all & result.valid

    masks = {
        "lit (>= 3 lights), non-grazing": non_grazing & (lit_count >= 3) & reference.surface.hit,
        "lit by all 6 lights, non-grazing": non_grazing
        & (lit_count == len(rig.lights))
        & reference.surface.hit,
    }
    print(
        f"\nFigurine, {rig.camera.width}x{rig.camera.height}, one view: capture {t_capture:.1f} s, "
        f"decode {t_decode:.1f} s; specular lobe fitted: strength "
        f"{reference.lobe.strength:.3f}, shininess {reference.lobe.shininess:.1f} (true 0.12, 30)"
    )
    lit_ng = non_grazing & (lit_count >= 3)
    print(
        f"The range map covers {100 * (lit_ng & reference.surface.hit).sum() / lit_ng.sum():.1f} % of "
        "the lit, non-grazing pixels (the rest: projector shadow or undecoded; no geometry, no albedo)."
    )
    for mask_name, eligible in masks.items():
        scored = eligible & valid_all
        for truth_name, target in (
            ("truth blurred by the camera optics", blurred),
            ("truth at pixel centres", albedo_true),
        ):
            print(f"\n{mask_name}; {truth_name}; {scored.sum():,} pixels")
            print("| method | rel. RMS R | G | B | within 5 % | coverage | scale | time |")
            print("|---|---|---|---|---|---|---|---|")
            for name, image in (
                ("naive: white frame", white),
                ("naive: mean of the lit images", lit_mean),
            ):
                s = best_scale(image, target, scored)
                rel, within = scores(image * s, target, scored)
                print(
                    f"| {name} (x{s:.3f}) | {100 * rel[0]:.1f} % | {100 * rel[1]:.1f} % | {100 * rel[2]:.1f} % | "
                    f"{100 * within:.1f} % | - | fitted | - |"
                )
            for name, (result, seconds) in runs.items():
                rel, within = scores(result.albedo, target, scored)
                coverage = (result.valid & eligible).sum() / max(eligible.sum(), 1)
                s = best_scale(result.albedo, target, scored)
                print(
                    f"| {name} | {100 * rel[0]:.1f} % | {100 * rel[1]:.1f} % | {100 * rel[2]:.1f} % | "
                    f"{100 * within:.1f} % | {100 * coverage:.1f} % | {s:.3f} | {seconds:.1f} s |"
                )
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
