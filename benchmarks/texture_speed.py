"""Texture stage speed, this tree against a git revision, side by side in the same run.

    .venv/bin/python benchmarks/texture_speed.py [--work DIR] [--against REV] [--views 4,8]
        [--size 2048] [--repeat 1]

``--work`` is a run of the demo recipe (or any figurine run on the virtual rig) with
``simplify/mesh.ply``, ``albedo/`` and ``register/``; without it one is made as
``benchmarks/texture.py`` makes it (``--scale``, 8 views, 100k faces) in
``/tmp/slscan-bench-texture/model``. ``--against REV`` checks REV out in a temporary
``git worktree`` and runs its code the same way (default ``HEAD``: the last commit;
pass the commit before a change to see the change).

Each row is the whole texture stage (:func:`slscan.texture.pipeline.texture_model`: atlas,
bake, export, no Blender preview) in its own process, on the first N views of the
registration, runs of the two codes interleaved. Phase times are **CPU seconds** of the
process (the stage's own phase timers, read with ``time.process_time``: the machine is
shared, CPU time drifts less than wall time); "wall" is the stage's wall time. From the
two view counts, each phase is split into seconds per view and fixed seconds (a straight
line through the two). Accuracy, in the same rows: the baked atlas against the true
albedo rendered into the same atlas (PSNR in 8-bit sRGB over the texels a view saw and
over all texels, as in ``benchmarks/texture.py``), the share of texels seen and filled,
and the largest difference between the two codes' baked atlases (linear RGB).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PHASES = ("atlas", "depth_maps", "vertices", "rasterise", "blend", "targets", "views", "fill_pad", "export")
"""The bake's phases before and after views were baked in groups (depth maps, vertex and texel
blending are one phase, "views", since; "targets" lays the texels out for it): a code shows
nan for the phases it does not have."""


# --- one row, in its own process -----------------------------------------------------------------


def child(spec: dict) -> dict:
    import numpy as np

    wall_clock = time.perf_counter
    time.perf_counter = time.process_time  # the stage's phase timers now read CPU seconds

    import slscan.texture.atlas as atlas_mod
    import slscan.texture.bake as bake_mod
    from slscan.register.frame import read_frame
    from slscan.texture.metrics import psnr
    from slscan.texture.pipeline import TextureConfig, texture_model
    from slscan.texture.views import read_poses

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from texture import truth_texture  # this tree's benchmark: the same truth for both codes

    captured = {}
    build_atlas, bake = atlas_mod.build_atlas, bake_mod.bake

    def keep_atlas(*a, **k):
        captured["atlas"] = build_atlas(*a, **k)
        return captured["atlas"]

    def keep_bake(*a, **k):
        captured["baked"] = bake(*a, **k)
        return captured["baked"]

    atlas_mod.build_atlas, bake_mod.bake = keep_atlas, keep_bake
    work = Path(spec["work"])
    poses = read_poses(work / "register")
    names = sorted(poses)[: spec["views"]]
    out = Path(spec["out"])
    usage = resource.getrusage(resource.RUSAGE_SELF)
    t0 = wall_clock()
    result = texture_model(work / "simplify" / "mesh.ply", work / "albedo", out,
                           poses={n: poses[n] for n in names},
                           config=TextureConfig(size=spec["size"], preview=False), overwrite=True)
    wall = wall_clock() - t0
    after = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (after.ru_utime - usage.ru_utime) + (after.ru_stime - usage.ru_stime)

    from slscan.colour import srgb8
    from slscan.fuse import read_mesh
    from slscan.virtual.scenes import builtin_object

    mesh = read_mesh(work / "simplify" / "mesh.ply")
    atlas, baked = captured["atlas"], captured["baked"]
    frame = read_frame(work / "register" / "registration.json")
    scene_from_model = np.linalg.inv(frame.object_from_reference) if frame is not None else np.eye(4)
    scene_vertices = mesh.vertices @ scene_from_model[:3, :3].T + scene_from_model[:3, 3]
    truth = srgb8(truth_texture(scene_vertices, mesh.faces, atlas, builtin_object()))
    image = srgb8(baked.linear)
    np.save(out.parent / f"{out.name}.npy", baked.linear)
    covered = max(int(baked.covered.sum()), 1)
    return {
        "views": len(names), "charts": atlas.n_charts, "texels": covered,
        "phases": {k: float(result.seconds.get(k, float("nan"))) for k in PHASES},
        "cpu": cpu, "wall": wall, "peak_gib": after.ru_maxrss / 2**20,
        "psnr_seen": psnr(image, truth, baked.observed), "psnr_all": psnr(image, truth, baked.covered),
        "seen": float(baked.observed.sum() / covered),
        "filled": float((baked.covered & ~baked.observed).sum() / covered),
    }


# --- the table -------------------------------------------------------------------------------------


def run_child(code: Path, spec: dict) -> dict:
    env = dict(os.environ, PYTHONPATH=str(code / "toolbox"))
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)],
                          check=False, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr)
        raise SystemExit(f"benchmark row failed ({code}, {spec['views']} views)")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def make_work(scale: float) -> Path:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from texture import run_stages

    stages = ["capture", "decode", "lights", "albedo", "register", "fuse", "simplify"]
    voxel = 0.5 / min(1.0, scale)
    return run_stages(Path("/tmp/slscan-bench-texture/model"), scale, 8, stages,
                      {"fuse": {"voxel_size": voxel}, "simplify": {"faces": 100_000}})


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", type=Path, help="a figurine run with simplify/, albedo/, register/")
    p.add_argument("--scale", type=float, default=0.5, help="camera scale when making --work")
    p.add_argument("--against", default="HEAD", help="git revision to compare with (default HEAD)")
    p.add_argument("--views", default="4,8", help="two view counts (default 4,8)")
    p.add_argument("--size", type=int, default=2048, help="atlas size")
    p.add_argument("--repeat", type=int, default=1, help="runs per row; the least CPU is kept")
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return 0
    counts = [int(v) for v in args.views.split(",")]
    if len(counts) != 2 or counts[0] >= counts[1]:
        raise SystemExit("--views: two increasing view counts, e.g. 4,8")
    work = (args.work or make_work(args.scale)).resolve()
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", args.against], check=True,
                         capture_output=True, text=True).stdout.strip()
    head = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"], check=True,
                          capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="slscan-texture-speed-") as tmp:
        tmp = Path(tmp)
        old_tree = tmp / "old"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(old_tree), rev], check=True)
        try:
            codes = {f"old {rev}": old_tree, f"new {head}": ROOT}
            rows = {}
            for n in counts:
                for _ in range(args.repeat):
                    for label, code in codes.items():
                        spec = {"work": str(work), "views": n, "size": args.size,
                                "out": str(tmp / f"{label.split()[0]}_{n}")}
                        row = run_child(code, spec)
                        best = rows.get((label, n))
                        if best is None or row["cpu"] < best["cpu"]:
                            rows[(label, n)] = row
            import numpy as np

            diff = {n: float(np.nanmax(np.abs(np.load(tmp / f"old_{n}.npy") - np.load(tmp / f"new_{n}.npy"))))
                    for n in counts}
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old_tree)], check=False)

    first = rows[(next(iter(codes)), counts[0])]
    print(f"# texture stage: {work}, {first['charts']} charts, {first['texels']:,} texels, atlas {args.size}; "
          f"CPU seconds per phase (process time), runs interleaved, least CPU of {args.repeat}")
    head_cols = "  ".join(f"{k:>9}" for k in PHASES)
    print(f"\n{'code':<18} {'views':>5}  {head_cols}  {'CPU s':>7}  {'wall s':>7}  {'peak GiB':>8}  "
          f"{'PSNR seen':>9}  {'PSNR all':>8}  {'seen':>6}  {'filled':>6}")
    for n in counts:
        for label in codes:
            r = rows[(label, n)]
            phases = "  ".join(f"{r['phases'][k]:>9.2f}" for k in PHASES)
            print(f"{label:<18} {n:>5}  {phases}  {r['cpu']:>7.1f}  {r['wall']:>7.1f}  {r['peak_gib']:>8.2f}  "
                  f"{r['psnr_seen']:>9.2f}  {r['psnr_all']:>8.2f}  {r['seen']:>6.3f}  {r['filled']:>6.3f}")
    a, b = counts
    print(f"\n## per view and fixed (straight line through {a} and {b} views), CPU s")
    print(f"{'code':<18} {'':>5}  {head_cols}  {'CPU s':>7}")
    for label in codes:
        lo, hi = rows[(label, a)], rows[(label, b)]
        for what in ("per view", "fixed"):
            vals = []
            for k in (*PHASES, "cpu"):
                x0 = lo["cpu"] if k == "cpu" else lo["phases"][k]
                x1 = hi["cpu"] if k == "cpu" else hi["phases"][k]
                slope = (x1 - x0) / (b - a)
                vals.append(slope if what == "per view" else x0 - a * slope)
            print(f"{label:<18} {what:>8}" + "".join(f"  {v:>9.2f}" for v in vals[:-1]) + f"  {vals[-1]:>7.1f}")
    print("\nlargest |new - old| of the baked atlas (linear RGB): "
          + ", ".join(f"{n} views {diff[n]:.2e}" for n in counts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
