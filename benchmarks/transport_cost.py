"""Render cost of the virtual rig's global light transport, and the inter-reflection noise.

    .venv/bin/python benchmarks/transport_cost.py [--scales 0.5,1.0] [--scenes object,concave,marble,bronze]

Table 1, per scene and sensor scale, one view (all hybrid patterns and ring-light
images) with each effect off and on, side by side in the same run: CPU seconds (process
time) to trace the view and to shade all its images, wall seconds for both, and the
mean digital level of the white image (what the effect adds). "off" is the direct-light
rig, which renders byte-identical images to earlier slscan versions.

Table 2: noise of the indirect term against ``Optics.interreflection_samples`` on the
``concave`` scene: under white, the std over receivers of its relative error against a
4096-sample reference (``relative`` to the reference's mean); under the finest Gray-code
bit (stripes 2 projector px), the rms over receivers of the error against the reference
(relative to white's indirect light) when each path reads the pattern at its one point
("point", slscan before the cone lookups) and over its patch ("cone",
:func:`slscan.virtual.transport.path_footprint`, what the rig does); and the trace cost.
The reference reads points: at 4096 rays a patch is a fraction of a projector pixel.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from slscan.patterns import graycode
from slscan.virtual import transport
from slscan.virtual.device import VirtualCaptureConfig, capture_view, turntable_pose
from slscan.virtual.render import projector_light_at, trace_view

EFFECTS = {"off": (), "subsurface": ("subsurface",), "interreflection": ("interreflection",),
           "both": ("subsurface", "interreflection")}


def _view_cost(scene_name: str, scale: float, effects: tuple[str, ...]) -> dict:
    levels = min(9, int(np.log2(1024 * scale)) - 1)
    config = VirtualCaptureConfig(scene=scene_name, camera_scale=scale, projector_scale=scale, levels=levels,
                                  effects=effects)
    rig, scene = config.rig(), config.build_scene()
    pose = turntable_pose(rig, 0.0, scene.placement)
    cpu, wall = time.process_time(), time.perf_counter()
    geom = trace_view(scene, rig, pose, config.optics)
    trace_cpu, trace_wall = time.process_time() - cpu, time.perf_counter() - wall
    cpu, wall = time.process_time(), time.perf_counter()
    images, _ = capture_view(scene, rig, pose, config.pattern_set(rig), config, geometry=geom)
    shade_cpu, shade_wall = time.process_time() - cpu, time.perf_counter() - wall
    return {"trace_cpu": trace_cpu, "shade_cpu": shade_cpu, "wall": trace_wall + shade_wall,
            "images": len(images), "white": float(images[0][1][geom.hit].mean())}


def _noise(scale: float, samples: list[int], reference: int = 4096) -> list[tuple[int, float, float, float, float]]:
    config = VirtualCaptureConfig(scene="concave", camera_scale=scale, projector_scale=scale)
    rig, scene = config.rig(), config.build_scene()
    pose = turntable_pose(rig, 0.0, scene.placement)

    finest = [p for p in graycode.generate(rig.projector.lens.width, rig.projector.lens.height)
              if not p.params["inverse"]][-1]

    def indirect(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        optics = dataclasses.replace(config.optics, interreflection=True, interreflection_samples=n)
        cpu = time.process_time()
        geom = trace_view(scene, rig, pose, optics)
        cost = time.process_time() - cpu
        paths = geom.transport.indirect
        white = transport.gather_indirect(paths, lambda uv, w: np.ones((len(uv), 3)))[:, 0]
        point = transport.gather_indirect(paths, lambda uv, w: projector_light_at(uv, finest, optics, 1.0))[:, 0]
        cone = transport.gather_indirect(paths, lambda uv, w: projector_light_at(uv, finest, optics, w))[:, 0]
        return white, point, cone, cost

    ref, ref_fine, _, _ = indirect(reference)
    strong = ref > 0.2 * ref.max()
    rows = []
    for n in samples:
        white, point, cone, cost = indirect(n)
        fine_err = [float(np.sqrt(np.mean(((v - ref_fine) / ref)[strong] ** 2))) for v in (point, cone)]
        rows.append((n, float(np.std((white - ref)[strong]) / ref[strong].mean()), *fine_err, cost))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scales", default="0.5,1.0", help="sensor scales (1: 1440x960 camera)")
    parser.add_argument("--scenes", default="object,concave,marble,bronze")
    parser.add_argument("--noise-scale", type=float, default=0.5)
    parser.add_argument("--no-noise", action="store_true", help="skip table 2")
    args = parser.parse_args()

    _view_cost("tile", 0.25, ("subsurface", "interreflection"))  # warm up imports and Open3D
    print("| scene | scale | images | effect | trace CPU s | shade CPU s | wall s | white mean DN |")
    print("|---|---|---|---|---|---|---|---|")
    for scale in (float(s) for s in args.scales.split(",")):
        for name in args.scenes.split(","):
            for label, effects in EFFECTS.items():
                r = _view_cost(name, scale, effects)
                print(f"| {name} | {scale:g} | {r['images']} | {label} | {r['trace_cpu']:.2f} | {r['shade_cpu']:.2f} "
                      f"| {r['wall']:.2f} | {r['white']:.1f} |", flush=True)
    if args.no_noise:
        return
    print()
    print(f"concave scene, scale {args.noise_scale:g}; errors against a 4096-ray reference")
    print("| samples | white: relative std | finest bit, point reads: rms | finest bit, cone reads: rms | trace CPU s |")
    print("|---|---|---|---|---|")
    for n, std, point, cone, cost in _noise(args.noise_scale, [16, 64, 128, 256, 1024]):
        print(f"| {n} | {100 * std:.1f} % | {100 * point:.1f} % | {100 * cone:.1f} % | {cost:.2f} |", flush=True)


if __name__ == "__main__":
    main()
