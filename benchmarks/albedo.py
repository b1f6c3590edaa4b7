"""Albedo accuracy on the virtual rig, against its ground truth.

    .venv/bin/python benchmarks/albedo.py [--scale 1.0] [--panel-scale 0.5] [--against REV]
        [--rounds 1] [--set KEY=VALUE ...]

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
the pixel centre, and the same blurred by the camera's optical blur (its ``blur_sigma``,
0.6 px by default; no un-shading can be sharper than the images it comes from).

Each un-shading runs in a fresh interpreter on the same files (the range map as PLY, the
lights as JSON, as the pipeline's albedo stage reads them), its imports paid before it is
timed; the time table gives CPU seconds (process time) of the whole view and of its
parts: the specular **lobe fit**, the per-pixel **solve** (normal and albedo), the
normals' **regularisation** with the albedo re-solved, and the rest (reading the images,
ray casting, shadow rays).

``--against REV`` checks REV out into a temporary git worktree and runs it and the working
tree on the same files, ``--rounds`` times in turn (CPU: median over rounds); every table
then has a row per version. ``--set KEY=VALUE`` overrides an ``AlbedoConfig`` field in the
working tree's runs only (to weigh a setting against REV).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from slscan.albedo.lights import LightCalibration, calibrate_lights, write_lights
from slscan.albedo.radiometry import exposure_factor, read_lit_images
from slscan.decode.pipeline import decode_view
from slscan.decode.rangemap import write_ply
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.panels import capture_light_calibration
from slscan.virtual.render import trace_view
from slscan.virtual.scenes import builtin_object

HERE = Path(__file__).resolve().parent
TOOLBOX = HERE.parent / "toolbox"
METHODS = (  # name, lights, AlbedoConfig fields
    ("un-shaded, estimated lights", "estimated", {}),
    ("un-shaded, true lights", "true", {}),
    ("un-shaded, estimated lights, range-map normals", "estimated", {"normals": "range"}),
    ("un-shaded, estimated lights, no specular fit", "estimated", {"specular": "none"}),
)
PARTS = {  # part of the time table -> functions of slscan.albedo.unshade timed as it
    "lobe fit": ("fit_view_lobe",),
    "solve": ("solve_pixels",),
    "regularise": ("regularise_normals", "albedo_for_normals"),
}


def run_methods(root: Path, overrides: dict, out: Path) -> None:
    """Un-shade the view under ``root`` by every method with the slscan on sys.path; write
    the albedo images to ``out`` (.npz) and the CPU seconds to ``out`` (.json)."""
    import open3d  # noqa: F401  (imports paid before the clock starts, as in a warm worker)

    from slscan.albedo import unshade
    from slscan.albedo.lights import read_lights
    from slscan.albedo.photometric import AlbedoConfig
    from slscan.capture.session import load_session
    from slscan.decode.rangemap import read_ply

    session = load_session(root / "figurine")
    view = session.views[0]
    range_map = read_ply(root / "range_map.ply")
    lights = {k: read_lights(root / f"lights_{k}.json") for k in ("estimated", "true")}
    spent: dict[str, float] = {}

    def timed(part, fn):
        def wrapper(*args, **kwargs):
            t = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[part] = spent.get(part, 0.0) + time.process_time() - t

        return wrapper

    for part, names in PARTS.items():
        for name in names:
            setattr(unshade, name, timed(part, getattr(unshade, name)))
    arrays, seconds = {}, {}
    for i, (name, light_key, fields) in enumerate(METHODS):
        spent.clear()
        config = AlbedoConfig(**{**fields, **overrides})
        t, wall = time.process_time(), time.perf_counter()
        result = unshade.albedo_view(session, view, range_map, lights[light_key], config)
        seconds[name] = {
            "cpu": time.process_time() - t,
            "wall": time.perf_counter() - wall,
            **{part: spent.get(part, 0.0) for part in PARTS},
            "lobe": [result.lobe.strength, result.lobe.shininess],
        }
        arrays[f"albedo_{i}"] = result.albedo
        arrays[f"valid_{i}"] = result.valid
        arrays[f"hit_{i}"] = result.surface.hit
    np.savez(out.with_suffix(".npz"), **arrays)
    out.with_suffix(".json").write_text(json.dumps(seconds))


def run_version(toolbox: Path, root: Path, label: str, overrides: dict, rounds_done: int) -> dict:
    """:func:`run_methods` in a fresh interpreter importing slscan from ``toolbox``."""
    out = root / f"result_{rounds_done}_{abs(hash(label))}"
    env = dict(os.environ, PYTHONPATH=str(toolbox))
    subprocess.run(
        [sys.executable, __file__, "--worker", str(root), str(out), json.dumps(overrides)],
        env=env,
        check=True,
    )
    data = np.load(out.with_suffix(".npz"))
    seconds = json.loads(out.with_suffix(".json").read_text())
    return {
        name: {
            "albedo": data[f"albedo_{i}"],
            "valid": data[f"valid_{i}"],
            "hit": data[f"hit_{i}"],
            "seconds": seconds[name],
        }
        for i, (name, _, _) in enumerate(METHODS)
    }


def parse_overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--set {item!r}: expected KEY=VALUE")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


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
    parser.add_argument("--against", metavar="REV", help="git revision to run side by side")
    parser.add_argument("--rounds", type=int, default=1, help="runs of each version, in turn")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="AlbedoConfig field for the working tree's runs (repeatable)",
    )
    parser.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        root, out, overrides = args.worker
        run_methods(Path(root), json.loads(overrides), Path(out))
        return 0
    overrides = parse_overrides(args.overrides)
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
    write_ply(range_map, root / "range_map.ply")
    write_lights(root / "lights_estimated.json", estimated)
    write_lights(root / "lights_true.json", true_lights)
    versions = [("working tree", TOOLBOX, overrides)]
    worktree = None
    if args.against:
        worktree = Path(tmp.name) / "against"
        subprocess.run(
            [
                "git",
                "-C",
                str(HERE.parent),
                "worktree",
                "add",
                "--detach",
                "-q",
                str(worktree),
                args.against,
            ],
            check=True,
        )
        versions.insert(0, (args.against, worktree / "toolbox", {}))
    runs: dict[str, list[dict]] = {label: [] for label, _, _ in versions}
    try:
        for k in range(args.rounds):
            for label, toolbox, fields in versions:
                runs[label].append(run_version(toolbox, root, label, fields, k))
    finally:
        if worktree is not None:
            subprocess.run(
                ["git", "-C", str(HERE.parent), "worktree", "remove", "--force", str(worktree)],
                check=False,
            )
    labels = [label for label, _, _ in versions]
    last = {label: runs[label][-1] for label in labels}
    reference = last[labels[-1]][METHODS[0][0]]
    hit = reference["hit"]
    valid_all = reference["valid"]
    for label in labels:
        for result in last[label].values():
            valid_all = valid_all & result["valid"]

    def row_name(name: str, label: str) -> str:
        return f"{name} [{label}]" if len(labels) > 1 else name

    masks = {
        "lit (>= 3 lights), non-grazing": non_grazing & (lit_count >= 3) & hit,
        "lit by all 6 lights, non-grazing": non_grazing & (lit_count == len(rig.lights)) & hit,
    }
    lobes = "; ".join(
        f"{label}: strength {last[label][METHODS[0][0]]['seconds']['lobe'][0]:.3f}, shininess "
        f"{last[label][METHODS[0][0]]['seconds']['lobe'][1]:.1f}"
        for label in labels
    )
    print(
        f"\nFigurine, {rig.camera.width}x{rig.camera.height}, one view: capture {t_capture:.1f} s, "
        f"decode {t_decode:.1f} s; specular lobe fitted ({lobes}; true 0.12, 30)"
    )
    if overrides:
        print(f"working tree with {overrides}")
    lit_ng = non_grazing & (lit_count >= 3)
    print(
        f"The range map covers {100 * (lit_ng & hit).sum() / lit_ng.sum():.1f} % of "
        "the lit, non-grazing pixels (the rest: projector shadow or undecoded; no geometry, no albedo)."
    )

    def cpu(label: str, name: str, key: str) -> float:
        return statistics.median(r[name]["seconds"][key] for r in runs[label])

    for mask_name, eligible in masks.items():
        scored = eligible & valid_all
        for truth_name, target in (
            ("truth blurred by the camera optics", blurred),
            ("truth at pixel centres", albedo_true),
        ):
            print(f"\n{mask_name}; {truth_name}; {scored.sum():,} pixels")
            print("| method | rel. RMS R | G | B | within 5 % | coverage | scale | CPU |")
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
            for name, _, _ in METHODS:
                for label in labels:
                    result = last[label][name]
                    rel, within = scores(result["albedo"], target, scored)
                    coverage = (result["valid"] & eligible).sum() / max(eligible.sum(), 1)
                    s = best_scale(result["albedo"], target, scored)
                    print(
                        f"| {row_name(name, label)} | {100 * rel[0]:.1f} % | {100 * rel[1]:.1f} % | "
                        f"{100 * rel[2]:.1f} % | {100 * within:.1f} % | {100 * coverage:.1f} % | "
                        f"{s:.3f} | {cpu(label, name, 'cpu'):.1f} s |"
                    )

    print(
        f"\nCPU seconds per view (process time, median of {args.rounds} run(s) per version, "
        "imports paid before timing); wall seconds on this shared machine for reference"
    )
    print(
        "| method | version | CPU total | lobe fit | solve | regularise | rest | "
        "solver (lobe fit + solve) | wall |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, _, _ in METHODS:
        for label in labels:
            parts = {key: cpu(label, name, key) for key in ("cpu", *PARTS, "wall")}
            rest = parts["cpu"] - sum(parts[p] for p in PARTS)
            solver = parts["lobe fit"] + parts["solve"]
            ratio = ""
            if len(labels) > 1 and label == labels[-1]:
                old = cpu(labels[0], name, "lobe fit") + cpu(labels[0], name, "solve")
                ratio = f" ({old / max(solver, 1e-9):.1f}x less)"
            print(
                f"| {name} | {label} | {parts['cpu']:.2f} s | {parts['lobe fit']:.2f} s | "
                f"{parts['solve']:.2f} s | {parts['regularise']:.2f} s | {rest:.2f} s | "
                f"{solver:.2f} s{ratio} | {parts['wall']:.1f} s |"
            )
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
