"""Cost of the quality-weighted TSDF fusion against Open3D's plain VoxelBlockGrid integration.

    .venv/bin/python benchmarks/fusion.py [--views 4] [--voxel 0.57] [--against REV]
                                          [--work DIR]

Captures the built-in figurine on the virtual rig with the paper recipe's settings (full
size: 1440x960 camera, 1024x768 projector, 9 levels, hybrid patterns; no lit images,
fusion does not use them), decodes ``--views`` turntable views into range maps, and fuses
them at the true poses, each way in its own process (so that its peak memory, VmHWM, is
its own), from the same range maps:

- **Open3D plain**: each range map rendered into a depth image of its camera (ray cast,
  the camera's pinhole) and integrated by ``VoxelBlockGrid.integrate`` (every observation
  weighs 1: no quality weights, nearest-pixel depth), meshed by
  ``extract_triangle_mesh``;
- **slscan REV** (``--against``, default 6cbba4b, the code before the update was vectorised per block): ``fuse_scans`` of
  git revision REV's toolbox (exported with ``git archive``);
- **slscan, this tree**: ``fuse_scans`` of the working tree as it chooses its voxel
  update: numpy until the volume has updated ``COMPILED_FROM_BLOCKS`` blocks, then the
  numba kernel (the ``fast`` extra) when numba is installed;
- **slscan, this tree, numba**: the numba kernel from the first scan on, loaded from
  numba's on-disk cache (a fresh cache folder for the run, filled by the compile
  measured below);
- **slscan, this tree, numpy**: the numpy update throughout (what runs without numba).
  The three give the same tsdf and weights bit for bit.

Open3D is imported before the clock starts in every way (the plain way always did; a
fusion stage pays ``import open3d`` once whichever way it fuses); numba's import and the
kernel's cache load are inside slscan's clock. Below the table: the numba kernel's first
call in a fresh process with an empty cache (import numba + compile) and with the cache
filled (import numba + load), CPU seconds.

Printed per way: CPU seconds (user + system of the process, every thread) and wall
seconds from the range maps in memory to the mesh (depth images / height maps,
integration, extraction; slscan also puts the mesh in canonical order), the integration
alone (block allocation and voxel updates, without making the depth images / height
maps), peak resident memory, faces, and the model's distance to the true surface: mean
and 95th percentile (mm) over 300,000 points spread by area on the model, and the share
of the true surface within 1 mm of the model (as ``benchmarks/meshing.py``).
With ``--work DIR`` the captured range maps are kept there and reused by the next run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from measure import cpu_seconds, export_toolbox, model_vs_truth, peak_rss_bytes, surface_samples

ROOT = Path(__file__).resolve().parent.parent


def prepare(work: Path, views: int) -> Path:
    """Range maps of ``views`` full-size figurine views (npz), captured once per folder."""
    from slscan.decode.pipeline import DecodeConfig, decode_view
    from slscan.decode.rangemap import build_range_map
    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    out = work / f"figurine_{views}.npz"
    if out.is_file():
        return out
    t = time.perf_counter()
    config = VirtualCaptureConfig(camera_scale=1.0, projector_scale=1.0, levels=9,
                                  lit_images=False, patterns="hybrid", views=views)
    session = capture_session(config, work / f"figurine_{views}")
    camera = session.calibration.camera
    arrays = {"K": camera.K, "size": np.array([camera.width, camera.height])}
    for k, view in enumerate(session.views):
        res = decode_view(session, view, DecodeConfig(method="hybrid"))
        rm = build_range_map(res.samples, res.points, white_image=res.white, camera=camera,
                             view=view.name)
        arrays.update({f"{k}_vertices": rm.vertices, f"{k}_faces": rm.faces,
                       f"{k}_quality": rm.quality, f"{k}_normals": rm.normals,
                       f"{k}_rig_from_object": view.rig_from_object})
    np.savez(out, **arrays)
    print(f"(captured and decoded {views} views in {time.perf_counter() - t:.0f} s, kept in {out})",
          flush=True)
    return out


def _views(path: Path) -> tuple[dict, list[dict]]:
    data = np.load(path)
    n = len([k for k in data.files if k.endswith("_vertices")])
    views = [{key: data[f"{k}_{key}"] for key in
              ("vertices", "faces", "quality", "normals", "rig_from_object")} for k in range(n)]
    return {"K": data["K"], "size": tuple(int(v) for v in data["size"])}, views


def run_plain(path: Path, voxel: float) -> dict:
    """Open3D's own integration: depth images of the range maps, weight 1 per observation."""
    import open3d as o3d
    import open3d.core as o3c

    from slscan.fuse import BLOCK_RESOLUTION, FuseConfig, _mesh_arrays

    camera, views = _views(path)
    width, height = camera["size"]
    K = camera["K"]
    trunc = FuseConfig().truncation
    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    cols, rows = np.meshgrid(np.arange(width, dtype=np.float32),
                             np.arange(height, dtype=np.float32))
    rays = np.zeros((height, width, 6), np.float32)
    rays[..., 3] = (cols - K[0, 2]) / K[0, 0]
    rays[..., 4] = (rows - K[1, 2]) / K[1, 1]
    rays[..., 5] = 1.0
    rays_t = o3c.Tensor(rays)
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1), (1)), voxel_size=voxel, block_resolution=BLOCK_RESOLUTION,
        block_count=50_000, device=o3c.Device("CPU:0"))
    intrinsic = o3c.Tensor(K, o3c.float64)
    integrate = 0.0
    for v in views:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3c.Tensor(v["vertices"].astype(np.float32)),
                            o3c.Tensor(v["faces"].astype(np.uint32)))
        t_hit = scene.cast_rays(rays_t)["t_hit"].numpy()  # ray z = 1: t is the depth
        depth = o3d.t.geometry.Image(o3c.Tensor(np.where(np.isfinite(t_hit), t_hit, 0).astype(np.float32)))
        extrinsic = o3c.Tensor(v["rig_from_object"], o3c.float64)
        c = cpu_seconds()
        blocks = grid.compute_unique_block_coordinates(
            depth, intrinsic, extrinsic, depth_scale=1.0, depth_max=1e5,
            trunc_voxel_multiplier=trunc)
        grid.integrate(blocks, depth, intrinsic, extrinsic, depth_scale=1.0, depth_max=1e5,
                       trunc_voxel_multiplier=trunc)
        integrate += cpu_seconds() - c
    mesh = _mesh_arrays(grid.extract_triangle_mesh(weight_threshold=FuseConfig().min_weight))
    return _finish(mesh, cpu0, wall0, integrate, int(grid.hashmap().size()))


def run_slscan(path: Path, voxel: float, update: str = "auto") -> dict:
    """slscan's quality-weighted fusion (whichever toolbox is on the path); ``update``
    "numpy" or "numba": that voxel update throughout, "auto": as fuse_scans chooses."""
    import open3d  # noqa: F401  (outside the clock, as in run_plain)

    from slscan import fuse
    from slscan.register.rangescan import scan_from_mesh

    if update == "numpy":
        fuse._KERNEL[:] = [None]  # as if numba were not installed
    elif update == "numba":
        fuse.COMPILED_FROM_BLOCKS = 0
    _, views = _views(path)
    scans, poses = [], {}
    for k, v in enumerate(views):
        centre = v["vertices"].mean(axis=0)
        name = f"view_{k:03d}"
        scans.append(scan_from_mesh(v["vertices"], v["faces"], quality=v["quality"],
                                    normals=v["normals"], name=name,
                                    view_direction=-centre / np.linalg.norm(centre)))
        poses[name] = np.linalg.inv(v["rig_from_object"])
    integrate = [0.0]
    original = fuse.TsdfVolume.integrate

    def timed(self, *args, **kwargs):
        c = cpu_seconds()
        original(self, *args, **kwargs)
        integrate[0] += cpu_seconds() - c

    fuse.TsdfVolume.integrate = timed
    cpu0, wall0 = cpu_seconds(), time.perf_counter()
    result = fuse.fuse_scans(scans, poses, config=fuse.FuseConfig(voxel_size=voxel))
    return _finish(result.mesh, cpu0, wall0, integrate[0], result.n_blocks)


def run_kernel() -> dict:
    """CPU seconds of the numba kernel's first call (import numba, then compile or load
    from the cache in ``NUMBA_CACHE_DIR``) on a one-block volume."""
    import numpy as np

    from slscan import fuse

    c = cpu_seconds()
    update = fuse._compiled_update()
    if update is None:
        return {"cpu": None}
    tsdf = np.ones((1, fuse.BLOCK_RESOLUTION**3), np.float32)
    weight = np.zeros_like(tsdf)
    lattice = np.ascontiguousarray(fuse._VOXEL_LATTICE.T.astype(np.float32))
    height = np.zeros(100, np.float32)
    update(tsdf, weight, np.zeros(1, np.int64), np.zeros((1, 3), np.float32), lattice, height,
           height.copy(), 10, np.float32(8), np.float32(8), np.float32(-1), np.float32(1))
    return {"cpu": cpu_seconds() - c}


def _finish(mesh, cpu0: float, wall0: float, integrate: float, blocks: int) -> dict:
    from slscan.virtual.scenes import builtin_object

    cpu, wall = cpu_seconds() - cpu0, time.perf_counter() - wall0
    peak = peak_rss_bytes()
    scene = builtin_object()
    d, complete = model_vs_truth(mesh, scene, surface_samples(scene.vertices, scene.triangles, 300_000))
    return {"cpu": cpu, "wall": wall, "integrate": integrate, "peak": peak, "blocks": blocks,
            "faces": len(mesh.faces), "mean": float(d.mean()),
            "p95": float(np.percentile(d, 95)), "complete": complete}



def _run(way: str, path: Path, voxel: float, toolbox: Path, numba_cache: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(toolbox), NUMBA_CACHE_DIR=str(numba_cache))
    proc = subprocess.run([sys.executable, __file__, "--way", way, "--maps", str(path),
                           "--voxel", str(voxel)], capture_output=True, text=True, env=env,
                          check=False)
    if proc.returncode != 0:
        raise SystemExit(f"{way} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=4, help="turntable views (full size)")
    parser.add_argument("--voxel", type=float, default=0.57, help="voxel size, mm (paper: 0.57)")
    parser.add_argument("--against", metavar="REV", default="6cbba4b",
                        help="git revision whose fuse_scans is run beside this tree's")
    parser.add_argument("--work", type=Path, help="folder for the range maps (kept, reused)")
    parser.add_argument("--way", choices=("plain", "slscan", "slscan-numba", "slscan-numpy", "kernel"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--maps", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.way:
        if args.way == "kernel":
            result = run_kernel()
        elif args.way == "plain":
            result = run_plain(args.maps, args.voxel)
        else:
            result = run_slscan(args.maps, args.voxel, update=args.way.partition("-")[2] or "auto")
        print(json.dumps(result))
        return
    with tempfile.TemporaryDirectory(prefix="slscan-fusion-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        maps = prepare(work, args.views)
        load = os.getloadavg()[0]
        cache = Path(tmp) / "numba"  # empty: the first call compiles, the next loads
        here = ROOT / "toolbox"
        kernel = {"compile": _run("kernel", maps, args.voxel, here, cache)["cpu"],
                  "load": _run("kernel", maps, args.voxel, here, cache)["cpu"]}
        rows = {
            "Open3D plain (weight 1)": _run("plain", maps, args.voxel, here, cache),
            f"slscan {args.against}": _run(
                "slscan", maps, args.voxel, export_toolbox(args.against, Path(tmp) / "against"),
                cache),
            "slscan, this tree": _run("slscan", maps, args.voxel, here, cache),
            "slscan, this tree, numba": _run("slscan-numba", maps, args.voxel, here, cache),
            "slscan, this tree, numpy": _run("slscan-numpy", maps, args.voxel, here, cache),
        }
    plain = rows["Open3D plain (weight 1)"]
    print(f"fusion of {args.views} full-size figurine views (paper recipe) at {args.voxel:g} mm voxels, "
          f"true poses; {os.cpu_count()} CPUs, load average {load:.1f} before, "
          f"{os.getloadavg()[0]:.1f} after")
    print(f"{'way':<26}{'CPU s':>8}{'x plain':>8}{'wall s':>8}{'integr. CPU s':>14}{'x plain':>8}"
          f"{'peak MiB':>10}{'blocks':>8}{'faces':>10}{'mean mm':>9}{'p95 mm':>8}{'within 1 mm':>12}")
    for label, r in rows.items():
        print(f"{label:<26}{r['cpu']:>8.2f}{r['cpu'] / plain['cpu']:>8.2f}{r['wall']:>8.2f}"
              f"{r['integrate']:>14.2f}{r['integrate'] / plain['integrate']:>8.2f}"
              f"{r['peak'] / 2**20:>10.0f}{r['blocks']:>8d}{r['faces']:>10d}{r['mean']:>9.4f}"
              f"{r['p95']:>8.4f}{r['complete']:>12.4f}")
    if kernel["compile"] is None:
        print("numba kernel: numba not installed (this tree's rows ran the numpy update)")
    else:
        print(f"numba kernel, first call in a fresh process (CPU s): import numba + compile "
              f"{kernel['compile']:.2f}, import numba + load from the cache {kernel['load']:.2f}")


if __name__ == "__main__":
    main()
