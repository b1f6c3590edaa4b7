"""Paint edges: what the hybrid decoder's paint-edge handling costs in surface and buys in
accuracy, on the demo and on the painted scenes of ``benchmarks/light_transport.py``.

    .venv/bin/python benchmarks/paint_edges.py [--work DIR] [--demo reduced|SCALE|none]
        [--scenes object,marble,bronze] [--scale 0.5] [--effects none]
        [--variant LABEL=KEY:VALUE[,KEY:VALUE] ...]

Every variant is a set of ``DecodeConfig`` settings, decoded from the same captures; by
default the three ``paint_edges`` modes: "drop" (``true``, the default before issue #35),
"keep" (``false``) and "shift" (the default since).

**demo** (``--demo reduced``: the recipe's quarter-size version, as the test suite runs
it; a number: ``slscan demo --scale`` that size; ``none``: skipped). The demo recipe is
run once per variant in ``WORK/demo-<size>`` (the capture and the lights are rendered
once; decode and everything after run again with ``decode.<key>`` set). Per variant:

  samples    line samples kept over the 8 views (range_maps.json), and those dropped at
             paint edges
  holes      boundary loops of the fused mesh (``fuse/mesh.ply``; an open surface also
             has its outer boundary), and of the simplified mesh
  pieces     connected pieces of the fused mesh (faces sharing an edge)
  surface    share of the true figurine's surface (200,000 points spread evenly over it)
             within 2 mm of the fused mesh: what the holes cost in area (the underside and
             deep folds no view sees count against every variant alike)
  atlas      the texture's atlas size, px: 512 (reduced) or 2048 for the first variant, the
             others sized by their simplified mesh's area to the same texel density (a
             model with more surface in a fixed atlas gets larger, blurrier texels)
  PSNR       the texture baked on the simplified mesh against the true albedo in the same
             atlas, 8-bit sRGB, over the texels a view saw and over all texels (as
             ``benchmarks/texture.py`` measures it, blended bake); each over the surface
             its own model has, so below the table also the PSNR over the seen texels on
             the surface that every variant's fused mesh has (within 2 mm)

**scenes**: one view of each scene of ``--scenes`` at ``--scale`` with ``--effects``
(light_transport.py's captures: hybrid patterns, default sensor noise), decoded by
``decode_view``. Paint edges are where the true albedo of a channel changes by more than
1.5x between neighbouring camera pixels (both lit, the brighter above 0.1); "near" is
within 3 px of one. Per variant: range-map vertices, their distance to the true surface
(mean, p95 in mm; all vertices, and those whose camera pixel is near a paint edge; the
share more than 1 mm off), and the coverage (share of the lit pixels, and of the lit
pixels near paint edges, under a range-map triangle).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import tomllib
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))

EDGE_RATIO = 1.5  # a channel's albedo changing by more than this between neighbours is a paint edge
EDGE_FLOOR = 0.1  # ... where the brighter of the two reflects at least this
NEAR_PX = 3  # camera px from a paint edge that count as near it
SURFACE_POINTS = 200_000  # points on the true figurine for the surface share
SURFACE_TOL = 2.0  # mm: a true-surface point this close to the fused mesh is covered
DEFAULT_VARIANTS = ("drop=paint_edges:drop", "keep=paint_edges:keep", "shift=paint_edges:shift")


def parse_variant(text: str) -> tuple[str, dict]:
    """``"label=key:value,key:value"`` -> (label, {key: value}); values read as TOML."""
    label, _, spec = text.partition("=")
    settings = {}
    for item in filter(None, spec.split(",")):
        key, _, raw = item.partition(":")
        try:
            settings[key.strip()] = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            settings[key.strip()] = raw.strip()
    return label.strip(), settings


def mesh_topology(path: Path) -> tuple[int, int, int]:
    """(faces, boundary loops, connected pieces) of a triangle mesh file."""
    import trimesh
    from trimesh.graph import connected_components

    mesh = trimesh.load(path, process=True, force="mesh")
    edges = mesh.edges_sorted
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    loops = len(connected_components(boundary, min_len=1)) if len(boundary) else 0
    pieces = len(connected_components(mesh.face_adjacency, nodes=np.arange(len(mesh.faces)), min_len=1))
    return len(mesh.faces), loops, pieces


def run_demo(work: Path, size: str, settings: dict) -> None:
    from slscan.cli import demo_overrides
    from slscan.recipe.runner import load_recipe, run_recipe, shipped_recipe

    overrides = [] if size == "reduced" else list(demo_overrides(scale=float(size)))
    overrides += [f"decode.{k}={json.dumps(v) if not isinstance(v, bool) else str(v).lower()}"
                  for k, v in settings.items()]
    recipe = load_recipe(shipped_recipe("demo"), reduced=size == "reduced", overrides=overrides)
    run_recipe(recipe, work)


def demo_row(work: Path, size: str, texel_mm: float | None = None) -> dict:
    maps = json.loads((work / "decode" / "range_maps.json").read_text())
    samples = int(sum(v["metrics"].get("samples", 0) for v in maps["views"]))
    dropped = int(sum(v["metrics"].get("paint_edge_samples_dropped", 0) for v in maps["views"]))
    faces, holes, pieces = mesh_topology(work / "fuse" / "mesh.ply")
    _, s_holes, s_pieces = mesh_topology(work / "simplify" / "mesh.ply")
    texture = texture_errors(work, 512 if size == "reduced" else 2048, texel_mm)
    return {"samples": samples, "dropped": dropped, "faces": faces, "holes": holes, "pieces": pieces,
            "s_holes": s_holes, "s_pieces": s_pieces, "psnr_seen": texture["psnr_seen"],
            "psnr_all": texture["psnr_all"], "surface": surface_share(work / "fuse" / "mesh.ply", work),
            "texels": texture["points"], "error2": texture["error2"], "fused": fused_in_scene(work),
            "texel_mm": texture["texel_mm"], "atlas": texture["atlas"]}


def scene_from_model(work: Path) -> np.ndarray:
    """(4, 4) the figurine's own frame from the model's (upright object) frame."""
    from slscan.register.frame import read_frame

    frame = read_frame(work / "register" / "registration.json")
    return np.linalg.inv(frame.object_from_reference) if frame is not None else np.eye(4)


def fused_in_scene(work: Path) -> tuple[np.ndarray, np.ndarray]:
    """The fused mesh's vertices (n, 3) in the figurine's frame and its faces (m, 3)."""
    from slscan.fuse import read_mesh

    mesh = read_mesh(work / "fuse" / "mesh.ply")
    pose = scene_from_model(work)
    return mesh.vertices @ pose[:3, :3].T + pose[:3, 3], np.asarray(mesh.faces)


def texture_errors(work: Path, size: int, texel_mm: float | None = None) -> dict:
    """The texture baked on the simplified mesh (default bake) against the true albedo in the
    same atlas (``benchmarks/texture.py``'s measure): PSNR over the texels a view saw and
    over all; and, per texel a view saw, its surface point (k, 3) in the figurine's frame
    and its squared 8-bit error summed over the channels (k,), for :func:`common_psnr`."""
    from texture import truth_texture

    from slscan.colour import srgb8
    from slscan.fuse import read_mesh
    from slscan.texture.atlas import AtlasOptions, build_atlas
    from slscan.texture.bake import BakeOptions, bake
    from slscan.texture.metrics import psnr, texel_points
    from slscan.texture.views import load_views
    from slscan.virtual.scenes import builtin_object

    mesh = read_mesh(work / "simplify" / "mesh.ply")
    views = load_views(work / "albedo", work / "register")
    v = mesh.vertices[mesh.faces]
    area = 0.5 * float(np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())
    if texel_mm is not None:  # the same texel density as another model: an atlas sized by the area
        size = int(round(np.sqrt(area) / texel_mm))
    atlas = build_atlas(mesh.vertices, mesh.faces, AtlasOptions(size=size))
    pose = scene_from_model(work)
    vertices = mesh.vertices @ pose[:3, :3].T + pose[:3, 3]
    truth = srgb8(truth_texture(vertices, mesh.faces, atlas, builtin_object()))
    baked = bake(mesh.vertices, mesh.faces, atlas, views, BakeOptions())
    image = srgb8(baked.linear)
    texel, points = texel_points(vertices, mesh.faces, atlas)
    seen = baked.observed.reshape(-1)[texel]
    d = image.reshape(-1, 3)[texel[seen]].astype(np.float64) - truth.reshape(-1, 3)[texel[seen]]
    return {"psnr_seen": psnr(image, truth, baked.observed), "psnr_all": psnr(image, truth, baked.covered),
            "points": points[seen], "error2": (d * d).sum(axis=1), "texel_mm": np.sqrt(area) / size, "atlas": size}


def common_psnr(rows: dict[str, dict]) -> dict[str, float]:
    """Per variant, the PSNR (dB, 8-bit) over the seen texels whose surface point lies within
    ``SURFACE_TOL`` mm of every variant's fused mesh: the same surface for all, so a model
    with holes is not credited with leaving out the texels beside paint edges."""
    import open3d as o3d

    scenes = []
    for r in rows.values():
        rs = o3d.t.geometry.RaycastingScene()
        vertices, faces = r["fused"]
        rs.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
        scenes.append(rs)
    out = {}
    for label, r in rows.items():
        query = o3d.core.Tensor(r["texels"].astype(np.float32))
        common = np.logical_and.reduce([rs.compute_distance(query).numpy() <= SURFACE_TOL for rs in scenes])
        mse = float(r["error2"][common].mean()) / 3.0 if common.any() else float("nan")
        out[label] = 10.0 * np.log10(255.0**2 / mse)
    return out


def surface_share(path: Path, work: Path) -> float:
    """Share of the figurine's true surface (``SURFACE_POINTS`` points spread evenly over it)
    within ``SURFACE_TOL`` mm of the model: what holes cost, in area."""
    import open3d as o3d
    import trimesh

    from slscan.fuse import read_mesh
    from slscan.virtual.scenes import builtin_object

    mesh = read_mesh(path)
    pose = scene_from_model(work)
    vertices = mesh.vertices @ pose[:3, :3].T + pose[:3, 3]
    scene = builtin_object()
    points, _ = trimesh.sample.sample_surface_even(trimesh.Trimesh(scene.vertices, scene.triangles, process=False),
                                                  SURFACE_POINTS, seed=0)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    d = rs.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
    return float(np.mean(d <= SURFACE_TOL))


def edge_distance(albedo: np.ndarray, lit: np.ndarray) -> np.ndarray:
    """(h, w) float32 camera px (L1) to the nearest paint edge of the true albedo."""
    a = np.nan_to_num(albedo.astype(np.float32))
    left, right = a[:, :-1], a[:, 1:]
    hi, lo = np.maximum(left, right), np.minimum(left, right)
    step = ((hi > EDGE_FLOOR) & (hi > EDGE_RATIO * lo)).any(axis=2) & lit[:, :-1] & lit[:, 1:]
    up, down = a[:-1], a[1:]
    hi, lo = np.maximum(up, down), np.minimum(up, down)
    vstep = ((hi > EDGE_FLOOR) & (hi > EDGE_RATIO * lo)).any(axis=2) & lit[:-1] & lit[1:]
    edge = np.zeros(lit.shape, np.uint8)
    edge[:, :-1] |= step
    edge[:, 1:] |= step
    edge[:-1] |= vstep
    edge[1:] |= vstep
    return cv2.distanceTransform((1 - edge).astype(np.uint8), cv2.DIST_L1, 3)


def scene_row(session, scene, settings: dict) -> dict:
    from reconstruction import true_surface_distance

    from slscan.capture.session import LIT
    from slscan.decode.pipeline import DecodeConfig, decode_view
    from slscan.decode.rangemap import covered_pixels

    view = session.views[0]
    result = decode_view(session, view, DecodeConfig(method="hybrid", **settings))
    rm = result.range_map
    truth = session.load_ground_truth(view)
    lit = truth.visibility == LIT
    dist = edge_distance(truth.albedo, lit)
    near_px = lit & (dist <= NEAR_PX)
    camera = session.calibration.camera
    covered = covered_pixels(rm, camera, lit.shape)
    d = true_surface_distance(rm.vertices, scene, view.rig_from_object)
    pix = np.round(camera.project_local(rm.vertices)).astype(int)
    h, w = lit.shape
    inside = (pix[:, 0] >= 0) & (pix[:, 0] < w) & (pix[:, 1] >= 0) & (pix[:, 1] < h)
    near = np.zeros(len(d), bool)
    near[inside] = dist[pix[inside, 1], pix[inside, 0]] <= NEAR_PX

    def stats(x):
        return (float(x.mean()), float(np.percentile(x, 95))) if len(x) else (np.nan, np.nan)

    return {"vertices": len(d), "all": stats(d), "near": stats(d[near]), "n_near": int(near.sum()),
            "gross": float(np.mean(d > 1.0) * 100) if len(d) else np.nan,
            "gross_near": float(np.mean(d[near] > 1.0) * 100) if near.any() else np.nan,
            "coverage": float(covered[lit].mean()), "coverage_near": float(covered[near_px].mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, help="folder for the demo runs (default: a temporary one)")
    parser.add_argument("--demo", default="reduced", help="reduced, a --scale for `slscan demo`, or none")
    parser.add_argument("--scenes", default="object,marble,bronze", help="light_transport.py scenes, or none")
    parser.add_argument("--scale", type=float, default=0.5, help="camera and projector size of the scenes")
    parser.add_argument("--effects", default="none", help="light-transport effects of the scenes (none, all, a+b)")
    parser.add_argument("--variant", action="append", default=None,
                        help="LABEL=KEY:VALUE[,KEY:VALUE]: DecodeConfig settings (repeatable)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    variants = [parse_variant(v) for v in (args.variant or DEFAULT_VARIANTS)]
    lw = max(8, max(len(label) for label, _ in variants) + 1)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        if args.demo != "none":
            print(f"demo ({args.demo}): 8 views; holes = boundary loops, pieces = connected pieces")
            print(f"{'variant':<{lw}}{'samples':>9}{'dropped':>9}{'fused faces':>12}{'holes':>7}{'pieces':>7}"
                  f"{'simpl. holes':>13}{'pieces':>7}{'surface':>8}{'atlas':>6}{'PSNR seen':>10}{'PSNR all':>9}")
            rows = {}
            for label, settings in variants:
                folder = work / f"demo-{args.demo}"
                run_demo(folder, args.demo, settings)
                first = next(iter(rows.values()), None)
                r = rows[label] = demo_row(folder, args.demo, first["texel_mm"] if first else None)
                print(f"{label:<{lw}}{r['samples']:>9d}{r['dropped']:>9d}{r['faces']:>12d}{r['holes']:>7d}"
                      f"{r['pieces']:>7d}{r['s_holes']:>13d}{r['s_pieces']:>7d}{r['surface']:>8.4f}"
                      f"{r['atlas']:>6d}{r['psnr_seen']:>10.2f}{r['psnr_all']:>9.2f}", flush=True)
            common = common_psnr(rows)
            print(f"PSNR over the seen texels of the surface every variant's fused mesh has (within "
                  f"{SURFACE_TOL:g} mm): " + ", ".join(f"{label} {v:.2f} dB" for label, v in common.items()))
        if args.scenes != "none":
            from slscan.capture.session import load_session
            from slscan.virtual.device import VirtualCaptureConfig, capture_session
            from slscan.virtual.effects import parse_effects

            effects = () if args.effects == "none" else parse_effects(args.effects.replace("+", ","), "--effects")
            levels = min(9, int(np.log2(1024 * args.scale)) - 1)
            print(f"\nscenes at {args.scale}x, {levels} levels, effects: {args.effects}; "
                  f"near = within {NEAR_PX} px of a paint edge; distances in mm")
            print(f"{'scene':<8}{'variant':<{lw}}{'vertices':>9}{'mean':>8}{'p95':>7}{'gross %':>8}{'near n':>7}"
                  f"{'near mean':>10}{'near p95':>9}{'near gross %':>13}{'coverage':>9}{'near cov':>9}")
            for name in filter(None, args.scenes.split(",")):
                config = VirtualCaptureConfig(scene=name, views=1, patterns="hybrid", levels=levels, gray_rows=False,
                                              lit_images=False, camera_scale=args.scale,
                                              projector_scale=args.scale, effects=effects)
                out = Path(tmp) / f"scene-{name}"
                capture_session(config, out)
                session, scene = load_session(out), config.build_scene()
                for label, settings in variants:
                    r = scene_row(session, scene, settings)
                    print(f"{name:<8}{label:<{lw}}{r['vertices']:>9d}{r['all'][0]:>8.4f}{r['all'][1]:>7.3f}"
                          f"{r['gross']:>8.3f}{r['n_near']:>7d}{r['near'][0]:>10.4f}{r['near'][1]:>9.3f}"
                          f"{r['gross_near']:>13.3f}{r['coverage']:>9.3f}{r['coverage_near']:>9.3f}", flush=True)


if __name__ == "__main__":
    main()
