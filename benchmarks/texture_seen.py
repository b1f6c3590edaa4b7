"""Seen share of a texture: what a right model gets, and what a wrong one gets.

    .venv/bin/python benchmarks/texture_seen.py [--work DIR] [--scale 0.25] [--views 8]

Scans the built-in figurine on the virtual rig (the demo recipe's stages up to simplify,
resumed from ``--work`` when already there), then bakes its views into an atlas of
several models and prints the share of atlas texels some view saw (``observed_share`` of
``texture.json``, the figure ``slscan texture`` warns about below
:data:`slscan.texture.pipeline.MIN_SEEN_SHARE`):

- the right model with every view, and with fewer views (a partial scan is legitimate:
  the views of one side see less of the model);
- the right model moved or turned (a registration of another run, a model moved in an
  editor): 20 mm, 200 mm, 2 m away; turned 90 degrees; scaled by 1.5 (metres read as mm
  would be 1000);
- another object: Stanford's bunny (``$SLSCAN_DATA`` or ``../shared/data``) scaled to the
  figurine's height and put where the figurine is; a sphere of the figurine's size.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def run_stages(work: Path, scale: float, views: int, voxel: float, faces: int) -> Path:
    from slscan.recipe.runner import parse_recipe, run_recipe

    stages = ["capture", "decode", "lights", "albedo", "register", "fuse", "simplify"]
    data = tomllib.loads((ROOT / "recipes" / "demo.toml").read_text())
    data["recipe"]["stages"] = stages
    data["recipe"].pop("reduced", None)
    data.pop("texture", None)
    data["capture"].update(camera_scale=scale, projector_scale=max(scale, 0.25), views=views, levels=7)
    data["fuse"]["voxel_size"] = voxel
    data["simplify"]["faces"] = faces
    run_recipe(parse_recipe(data, where="benchmarks/texture_seen.py"), work)
    return work


def seen_share(vertices: np.ndarray, faces: np.ndarray, views, size: int) -> tuple[float, float, float, float]:
    """(share of atlas texels seen; lowest, median and highest share of a view's object
    pixels the model covers)."""
    from slscan.texture.atlas import AtlasOptions, build_atlas
    from slscan.texture.bake import bake

    atlas = build_atlas(vertices, faces, AtlasOptions(size=size))
    baked = bake(vertices, faces, atlas, views)
    shares = np.array(list(baked.view_model_share.values()))
    return (float(baked.observed.sum() / max(int(baked.covered.sum()), 1)), float(np.nanmin(shares)),
            float(np.nanmedian(shares)), float(np.nanmax(shares)))


def about_centre(vertices: np.ndarray, transform) -> np.ndarray:
    centre = vertices.mean(axis=0)
    return transform(vertices - centre) + centre


def sphere(radius: float, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=n)
    return np.asarray(mesh.vertices, float), np.asarray(mesh.triangles, np.int64)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", type=Path, default=Path("/tmp/slscan-bench-texture-seen"))
    p.add_argument("--scale", type=float, default=0.25, help="camera scale (1: the paper's 1440x960)")
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--size", type=int, default=512, help="atlas size")
    p.add_argument("--voxel", type=float, default=2.0, help="fusion voxel, mm")
    p.add_argument("--faces", type=int, default=20_000, help="simplified model's faces")
    args = p.parse_args(argv)
    from slscan.fuse import read_mesh
    from slscan.texture.views import load_views

    t0 = time.perf_counter()
    work = run_stages(args.work, args.scale, args.views, args.voxel, args.faces)
    mesh = read_mesh(work / "simplify" / "mesh.ply")
    views = load_views(work / "albedo", work / "register")
    v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.faces, np.int64)
    extent = v.max(axis=0) - v.min(axis=0)
    print(f"# virtual rig: figurine, {len(views)} turntable views, camera scale {args.scale}, fused at "
          f"{args.voxel} mm; model "
          f"{len(f):,} faces, {extent[0]:.0f} x {extent[1]:.0f} x {extent[2]:.0f} mm; atlas {args.size}; "
          f"scans ready in {time.perf_counter() - t0:.0f} s")

    turn = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # 90 degrees about x
    cases: list[tuple[str, str, np.ndarray, np.ndarray, list]] = []
    cases.append(("right", f"the model, all {len(views)} views", v, f, views))
    for k in (4, 2, 1):
        if k < len(views):
            cases.append(("right", f"the model, {k} adjacent view(s)", v, f, views[:k]))
    for mm in (20, 200, 2000):
        cases.append(("wrong", f"the model moved {mm} mm (x)", v + [mm, 0, 0], f, views))
    cases.append(("wrong", "the model moved 2 m (z)", v + [0, 0, 2000], f, views))
    cases.append(("wrong", "the model turned 90 deg", about_centre(v, lambda x: x @ turn.T), f, views))
    cases.append(("wrong", "the model scaled 1.5", about_centre(v, lambda x: 1.5 * x), f, views))
    data = Path(os.environ.get("SLSCAN_DATA", ROOT.parent / "shared" / "data"))
    bunny_file = data / "stanford_bunny" / "reconstruction" / "bun_zipper_res2.ply"
    if bunny_file.is_file():
        bunny = read_mesh(bunny_file)
        b = np.asarray(bunny.vertices, float)
        b = (b - b.mean(axis=0)) * (extent[1] / np.ptp(b[:, 1])) + v.mean(axis=0)
        cases.append(("wrong", "another object: the bunny, same place and height", b,
                      np.asarray(bunny.faces, np.int64), views))
    sv, sf = sphere(0.5 * float(np.median(extent)))
    cases.append(("wrong", "another object: a sphere, same place", sv + v.mean(axis=0), sf, views))

    print("\ncase    model                                              seen share  model on a view's object: "
          "lowest  median  highest")
    for kind, name, cv, cf, cviews in cases:
        share, low, median, high = seen_share(cv, cf, cviews, args.size)
        print(f"{kind:<7} {name:<50} {share:>10.1%}  {low:>33.1%}  {median:>6.1%}  {high:>7.1%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
