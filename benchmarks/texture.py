"""Texture benchmark: baked texture against the true albedo, seam error, and time at 1M faces.

    .venv/bin/python benchmarks/texture.py [--work DIR] [--scale 1.0] [--views 8]

1. Scans the built-in figurine on the virtual rig (``--views`` turntable views at
   ``--scale`` of the paper's camera), decodes, un-shades, registers and fuses the range
   maps (the demo recipe's stages, resumed from ``--work`` when already there).
2. **Accuracy** on the simplified model: the baked atlas against the ground-truth albedo
   rendered into the *same* atlas (each texel the true albedo at its surface point,
   averaged over 2x2 sub-texel samples), as PSNR in 8-bit sRGB over the texels a view saw
   and over all texels; the seam error (8-bit levels across chart boundaries). Side by
   side in the same run: one view per texel (no blending: the best-angled view only) and
   per-vertex colour interpolated over the faces (no texture).
3. **Time and memory at 1M faces**: the same scans fused finer and simplified to
   1,000,000 faces, then atlas + bake (target: at most 2 min), peak memory of the process.
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def peak_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def run_stages(work: Path, scale: float, views: int, stages: list[str], extra: dict) -> Path:
    from slscan.recipe.runner import parse_recipe, run_recipe

    data = tomllib.loads((ROOT / "recipes" / "demo.toml").read_text())
    data["recipe"]["stages"] = stages
    data["recipe"].pop("reduced", None)
    for name in [k for k in data if k != "recipe" and k not in stages]:
        del data[name]
    levels = 9 if scale >= 1 else 8
    data["capture"].update(camera_scale=scale, projector_scale=max(scale, 0.5), views=views, levels=levels)
    for table, values in extra.items():
        data.setdefault(table, {}).update(values)
    recipe = parse_recipe(data, where="benchmarks/texture.py")
    run_recipe(recipe, work)
    return work


def truth_texture(vertices, faces, atlas, scene):
    """True albedo in the atlas, 2x2 sub-texel samples averaged; and its coverage."""
    from slscan.texture.metrics import render_into_atlas
    from slscan.virtual.scenes import surface_albedo

    size = atlas.size
    big = SimpleNamespace(uvs=atlas.uvs, faces=atlas.faces, size=2 * size)
    fine, covered = render_into_atlas(vertices, faces, big, lambda p: surface_albedo(scene, p))
    fine = fine.reshape(size, 2, size, 2, 3)
    cov = covered.reshape(size, 2, size, 2)
    n = cov.sum(axis=(1, 3))
    image = (fine * cov[..., None]).sum(axis=(1, 3)) / np.maximum(n, 1)[..., None]
    return image


def accuracy_rows(work: Path, size: int) -> list[tuple]:
    from slscan.colour import srgb8
    from slscan.fuse import read_mesh
    from slscan.register.frame import read_frame
    from slscan.texture.atlas import AtlasOptions, build_atlas
    from slscan.texture.bake import BakeOptions, bake
    from slscan.texture.metrics import psnr, seam_error
    from slscan.texture.views import load_views
    from slscan.virtual.scenes import builtin_object

    mesh = read_mesh(work / "simplify" / "mesh.ply")
    views = load_views(work / "albedo", work / "register")
    atlas = build_atlas(mesh.vertices, mesh.faces, AtlasOptions(size=size))
    # the model is in the upright object frame; the scene's albedo is known in its own frame
    frame = read_frame(work / "register" / "registration.json")
    scene_from_model = np.linalg.inv(frame.object_from_reference) if frame is not None else np.eye(4)
    scene_vertices = mesh.vertices @ scene_from_model[:3, :3].T + scene_from_model[:3, 3]
    truth = srgb8(truth_texture(scene_vertices, mesh.faces, atlas, builtin_object()))
    rows = []
    variants = [
        ("blended (default)", BakeOptions()),
        ("best view only", BakeOptions(angle_power=200.0, edge_px=1.0, border_px=1.0)),
    ]
    vertex_only = None
    for name, options in variants:
        t0 = time.perf_counter()
        baked = bake(mesh.vertices, mesh.faces, atlas, views, options)
        seconds = time.perf_counter() - t0
        image = srgb8(baked.linear)
        seams = seam_error(image, mesh.faces, atlas)
        rows.append((name, len(mesh.faces), size, psnr(image, truth, baked.observed), psnr(image, truth, baked.covered),
                     seams.mean, seams.p95, seconds))
        if vertex_only is None:
            vertex_only = baked
    # per-vertex colours interpolated over each face, in the same atlas
    from slscan.texture.bake import rasterise_uv

    texel, face, bary = rasterise_uv(np.asarray(atlas.uvs, np.float64) * size - 0.5, atlas.faces, size)
    colors = np.einsum("kj,kjc->kc", bary, vertex_only.vertex_colors[mesh.faces[face]])
    image = np.zeros((size * size, 3), np.float32)
    image[texel] = colors
    image = srgb8(image.reshape(size, size, 3))
    rows.append(("vertex colours only", len(mesh.faces), size, psnr(image, truth, vertex_only.observed),
                 psnr(image, truth, vertex_only.covered), float("nan"), float("nan"), float("nan")))
    return rows, atlas, len(views)


def scale_rows(work: Path, size: int) -> list[tuple]:
    from slscan.fuse import read_mesh
    from slscan.texture.atlas import AtlasOptions, build_atlas
    from slscan.texture.bake import bake
    from slscan.texture.views import load_views

    mesh = read_mesh(work / "simplify" / "mesh.ply")
    views = load_views(work / "albedo", work / "register")
    t0 = time.perf_counter()
    atlas = build_atlas(mesh.vertices, mesh.faces, AtlasOptions(size=size))
    t_atlas = time.perf_counter() - t0
    t0 = time.perf_counter()
    baked = bake(mesh.vertices, mesh.faces, atlas, views)
    t_bake = time.perf_counter() - t0
    return [(len(mesh.faces), size, atlas.n_charts, atlas.utilisation, len(views), t_atlas, t_bake,
             t_atlas + t_bake, peak_gib(), baked.seconds)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", type=Path, default=Path("/tmp/slscan-bench-texture"))
    p.add_argument("--scale", type=float, default=1.0, help="camera scale (1: the paper's 1440x960)")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--size", type=int, default=2048, help="atlas size for the accuracy rows")
    p.add_argument("--faces", type=int, default=100_000, help="model faces for the accuracy rows")
    p.add_argument("--skip-scale", action="store_true", help="no 1M-face timing")
    args = p.parse_args(argv)
    stages = ["capture", "decode", "lights", "albedo", "register", "fuse", "simplify"]
    voxel = 0.5 / min(1.0, args.scale)
    t0 = time.perf_counter()
    work = run_stages(args.work / "model", args.scale, args.views, stages,
                      {"fuse": {"voxel_size": voxel}, "simplify": {"faces": args.faces}})
    print(f"# virtual rig: figurine, {args.views} turntable views, camera scale {args.scale}, "
          f"fused at {voxel} mm; scans ready in {time.perf_counter() - t0:.0f} s (resumed when cached)")

    rows, atlas, n_views = accuracy_rows(work, args.size)
    print(f"\n## accuracy: baked atlas vs true albedo in the same atlas ({n_views} views, {atlas.n_charts} charts)")
    print("method               faces    atlas   PSNR seen dB  PSNR all dB  seam mean  seam p95  bake s")
    for name, faces, size, p_seen, p_all, s_mean, s_p95, sec in rows:
        print(f"{name:<20} {faces:>7,} {size:>6}   {p_seen:>11.2f}  {p_all:>11.2f}  {s_mean:>9.2f}  {s_p95:>8.2f}  "
              f"{sec:>6.1f}")
    print("(PSNR in 8-bit sRGB; seam error: mean |difference| in 8-bit levels across chart boundaries)")

    if not args.skip_scale:
        # the same scans (capture .. register resumed), fused finer and simplified to 1M faces
        big = run_stages(args.work / "model", args.scale, args.views, stages,
                         {"fuse": {"voxel_size": voxel / 2.5}, "simplify": {"faces": 1_000_000}})
        rows = scale_rows(big, 4096)
        print("\n## time at 1M faces (target: atlas + bake <= 120 s)")
        print("faces      atlas  charts  utilisation  views  atlas s  bake s  total s  peak GiB  bake phases s")
        for faces, size, charts, util, nv, ta, tb, tt, peak, phases in rows:
            detail = ", ".join(f"{k} {v:.1f}" for k, v in phases.items())
            print(f"{faces:>9,} {size:>6} {charts:>7,} {util:>12.3f} {nv:>6} {ta:>8.1f} {tb:>7.1f} {tt:>8.1f} "
                  f"{peak:>9.2f}  {detail}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
