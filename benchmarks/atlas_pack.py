"""Atlas packing settings: time against charts and utilisation, side by side in one run.

    .venv/bin/python benchmarks/atlas_pack.py MESH [MESH ...] [--size 2048] [--repeat 1]

For each mesh, :func:`slscan.texture.atlas.build_atlas` ("patches": our segmentation,
xatlas packing) under a few settings, each row in its own process, rows interleaved:

- **default**: :class:`slscan.texture.atlas.AtlasOptions` as it is (xatlas 4x4 block
  alignment, no brute force, up to 6 packings to find the finest scale that fits);
- **no block align**: xatlas places charts texel by texel;
- **brute force**: xatlas tries every position (its densest, slowest packing);
- **2 packings** / **3 packings**: ``max_pack_attempts``, fewer tries at the finest scale;
- **fill 0.6**: the first packing aims lower (``fill``), so it rarely spills;
- **min patch 60** / **min patch 200**: ``min_patch_faces``, fewer, larger charts.

Columns: charts, utilisation (charts' UV area over the page), texels per mm the charts
were packed at (the texture's resolution on the model: larger is finer), packings run,
CPU seconds of the whole atlas and of the packing phase (process time; the machine is
shared), and wall seconds.
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import time
from pathlib import Path

SETTINGS = {
    "default": ({}, {}),
    "no block align": ({}, {"blockAlign": False}),
    "brute force": ({}, {"bruteForce": True}),
    "2 packings": ({"max_pack_attempts": 2}, {}),
    "3 packings": ({"max_pack_attempts": 3}, {}),
    "fill 0.6": ({"fill": 0.6}, {}),
    "min patch 60": ({"min_patch_faces": 60}, {}),
    "min patch 200": ({"min_patch_faces": 200}, {}),
}


def row(mesh_path: str, setting: str, size: int) -> dict:
    wall_clock = time.perf_counter
    time.perf_counter = time.process_time  # the atlas's phase timers now read CPU seconds

    import slscan.texture.atlas as atlas_mod
    from slscan.errors import SlscanError
    from slscan.fuse import read_mesh

    options, pack = SETTINGS[setting]
    base = atlas_mod._pack_options

    def pack_options(opts, texels_per_mm):
        p = base(opts, texels_per_mm)
        for name, value in pack.items():
            setattr(p, name, value)
        return p

    atlas_mod._pack_options = pack_options
    packings = []

    class Count(logging.Handler):
        def emit(self, record):
            if record.getMessage().startswith("atlas: packed at"):
                packings.append(1)

    atlas_mod.log.addHandler(Count())
    atlas_mod.log.setLevel(logging.DEBUG)
    mesh = read_mesh(mesh_path)
    t0, c0 = wall_clock(), time.process_time()
    try:
        atlas = atlas_mod.build_atlas(mesh.vertices, mesh.faces, atlas_mod.AtlasOptions(size=size, **options))
    except SlscanError as exc:  # a setting that cannot pack says so in its row
        return {"faces": len(mesh.faces), "error": str(exc).splitlines()[0][:60]}
    return {
        "faces": len(mesh.faces), "charts": atlas.n_charts, "utilisation": atlas.utilisation,
        "texels_per_mm": atlas.texels_per_mm, "packings": len(packings),
        "cpu": time.process_time() - c0, "pack_cpu": atlas.seconds.get("pack", float("nan")),
        "wall": wall_clock() - t0,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mesh", nargs="*", type=Path)
    p.add_argument("--size", type=int, default=2048)
    p.add_argument("--repeat", type=int, default=1, help="runs per row; the least CPU is kept")
    p.add_argument("--row", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.row:
        print(json.dumps(row(args.row[0], args.row[1], args.size)))
        return 0
    if not args.mesh:
        p.error("give at least one mesh (e.g. a demo run's simplify/mesh.ply)")
    results = {}
    for mesh in args.mesh:
        if not mesh.is_file():
            raise SystemExit(f"{mesh}: not found; expected a PLY mesh")
        for _ in range(args.repeat):
            for setting in SETTINGS:
                proc = subprocess.run([sys.executable, __file__, "--size", str(args.size), "--row", str(mesh), setting],
                                      check=False, capture_output=True, text=True)
                if proc.returncode != 0:
                    sys.stderr.write(proc.stderr[-3000:])
                    raise SystemExit(f"row {setting} on {mesh} failed")
                r = json.loads(proc.stdout.strip().splitlines()[-1])
                best = results.get((mesh, setting))
                if best is None or "error" in best or ("cpu" in r and r["cpu"] < best["cpu"]):
                    results[(mesh, setting)] = r
    print(f"# atlas packing settings, {args.size}² page, CPU seconds (process time), least of {args.repeat}")
    print(f"{'mesh':<28} {'setting':<15} {'faces':>9} {'charts':>7} {'utilisation':>11} {'texels/mm':>9} "
          f"{'packings':>8} {'atlas CPU s':>11} {'pack CPU s':>10} {'wall s':>7}")
    for (mesh, setting), r in results.items():
        name = f"{mesh.parent.parent.name}/{mesh.name}"[-28:]
        if "error" in r:
            print(f"{name:<28} {setting:<15} {r['faces']:>9,}  {r['error']}")
            continue
        print(f"{name:<28} {setting:<15} {r['faces']:>9,} {r['charts']:>7,} {r['utilisation']:>11.3f} "
              f"{r['texels_per_mm']:>9.2f} {r['packings']:>8} {r['cpu']:>11.2f} {r['pack_cpu']:>10.2f} "
              f"{r['wall']:>7.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
