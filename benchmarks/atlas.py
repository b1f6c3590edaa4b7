"""Texture atlas of a 1M-face scanned model: charts, utilisation and time, xatlas vs patches.

    .venv/bin/python benchmarks/atlas.py [MESH] [--timeout 300] [--small 100000]

MESH (default ``/tmp/tex/bunny/simplify/mesh.ply``) is the fused Stanford bunny simplified
to 1M faces; make it with

    slscan run recipes/bunny.toml --out /tmp/tex/bunny --set fuse.voxel_size=0.15 \\
        --set simplify.faces=1000000

Rows (each in its own process, timed around the atlas call only), on a ``--small``-face
version of MESH (fast-simplification) and on MESH itself:

- **xatlas defaults**: on the small mesh only (on 1M faces they take over 15 minutes);
- **xatlas tuned**: ``max_iterations=0`` (no chart-growing refinement), 4x4 block
  alignment, no brute-force packing;
- **xatlas fast**: the same with ``max_cost=0.5`` (charts stop growing early: many small
  charts, the fastest xatlas settings we found);
- **patches**: :func:`slscan.texture.atlas.build_atlas` with its defaults (our
  segmentation, xatlas packing).

Rows on MESH are stopped after ``--timeout`` seconds and shown as "> N".

xatlas rows ask for a 4096² page and let xatlas choose the texels per mm
(``texels_per_unit = 0``), so their page may come out larger: "page" gives its size.
"utilisation" is the charts' UV area over the page area, for all rows. "shared" counts
texels whose centre lies in triangles of two different charts (must be 0), at the
atlas's own size. Targets: 1M faces well under a minute, hundreds to low thousands of
charts, utilisation >= 0.6, one page.
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

DEFAULT_MESH = Path("/tmp/tex/bunny/simplify/mesh.ply")
SIZE = 4096
PADDING = 4
MAKE_MESH = (
    "slscan run recipes/bunny.toml --out /tmp/tex/bunny --set fuse.voxel_size=0.15 "
    "--set simplify.faces=1000000"
)


# --- rows (each in its own process) ---------------------------------------------------------------


XATLAS_SETTINGS = {
    "xatlas-defaults": {},
    "xatlas-tuned": {"max_iterations": 0},
    "xatlas-fast": {"max_iterations": 0, "max_cost": 0.5},
}


def row_xatlas(vertices: np.ndarray, faces: np.ndarray, settings: str) -> dict:
    import xatlas

    chart = xatlas.ChartOptions()
    for name, value in XATLAS_SETTINGS[settings].items():
        setattr(chart, name, value)
    tuned = settings != "xatlas-defaults"
    pack = xatlas.PackOptions()
    pack.resolution = SIZE
    pack.padding = PADDING // 2  # xatlas pads each chart, so charts end up PADDING apart
    pack.blockAlign = tuned
    pack.bruteForce = False
    atlas = xatlas.Atlas()
    atlas.add_mesh(vertices.astype(np.float32), faces.astype(np.uint32))
    t = time.perf_counter()
    atlas.generate(chart, pack)
    seconds = time.perf_counter() - t
    _, indices, uvs = atlas.get_mesh(0)
    width, height = atlas.width, atlas.height
    texels = uvs.astype(np.float64)[indices.astype(np.int64)] * [width, height]
    chart_of = np.full(len(faces), -1, np.int64)
    for c in range(atlas.get_mesh_chart_count(0)):
        chart_of[np.asarray(atlas.get_mesh_chart(0, c).faces, np.int64)] = c
    return {
        "faces": len(faces),
        "charts": atlas.chart_count,
        "utilisation": _uv_area(texels) / (width * height * atlas.atlas_count),
        "seconds": seconds,
        "page": f"{width} x {height}"
        + (f" x {atlas.atlas_count}" if atlas.atlas_count > 1 else ""),
        "shared": _shared_texels(texels, chart_of),
        "note": "",
    }


def row_patches(vertices: np.ndarray, faces: np.ndarray) -> dict:
    from slscan.texture.atlas import AtlasOptions, build_atlas

    t = time.perf_counter()
    atlas = build_atlas(vertices, faces, AtlasOptions(size=SIZE, padding=PADDING))
    seconds = time.perf_counter() - t
    texels = atlas.uvs.astype(np.float64)[atlas.faces] * atlas.size
    phases = ", ".join(f"{k} {v:.1f}" for k, v in atlas.seconds.items() if k != "total")
    return {
        "faces": len(faces),
        "charts": atlas.n_charts,
        "utilisation": atlas.utilisation,
        "seconds": seconds,
        "page": f"{atlas.size} x {atlas.size}",
        "shared": _shared_texels(texels, atlas.chart),
        "note": (
            f"{atlas.texels_per_mm:.1f} texels/mm; {atlas.n_folded} faces folded "
            f"({100 * atlas.n_folded / len(faces):.1f} %); {phases} s"
        ),
    }


def _uv_area(texels: np.ndarray) -> float:
    e1, e2 = texels[:, 1] - texels[:, 0], texels[:, 2] - texels[:, 0]
    return float(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum() / 2)


def _shared_texels(texels: np.ndarray, chart: np.ndarray) -> int:
    """Texel centres inside triangles of two different charts."""
    from slscan.texture.atlas import rasterise

    face, col, row = rasterise(texels)
    key = row * (int(col.max()) + 1) + col
    order = np.lexsort((chart[face], key))
    key, owner = key[order], chart[face][order]
    return int(np.sum((key[1:] == key[:-1]) & (owner[1:] != owner[:-1])))


def run_row(args: argparse.Namespace) -> dict:
    from slscan.fuse import read_mesh

    mesh = read_mesh(args.mesh)
    if args.row == "patches":
        return row_patches(mesh.vertices, mesh.faces)
    return row_xatlas(mesh.vertices, mesh.faces, args.row)


# --- driver ---------------------------------------------------------------------------------------


def _in_process(row: str, mesh: Path, timeout: float | None) -> dict | None:
    """The row's result, or None when it ran past ``timeout`` seconds."""
    command = [sys.executable, __file__, str(mesh), "--row", row]
    try:
        proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return None
    if proc.returncode != 0:
        raise SystemExit(f"row {row} on {mesh} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("mesh", nargs="?", type=Path, default=DEFAULT_MESH, help="1M-face mesh")
    parser.add_argument(
        "--timeout", type=float, default=300.0, help="seconds before rows on MESH are stopped"
    )
    parser.add_argument(
        "--small", type=int, default=100_000, help="faces of the version xatlas defaults run on"
    )
    parser.add_argument("--row", choices=(*XATLAS_SETTINGS, "patches"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.row:
        print(json.dumps(run_row(args)))
        return
    if not args.mesh.is_file():
        raise SystemExit(f"{args.mesh}: not found; make it with\n    {MAKE_MESH}")

    from slscan.fuse import read_mesh, write_mesh
    from slscan.simplify import simplify_mesh

    load_before = os.getloadavg()[0]
    mesh = read_mesh(args.mesh)
    rows = []
    with tempfile.TemporaryDirectory(prefix="slscan-atlas-") as tmp:
        small = Path(tmp) / "small.ply"
        write_mesh(simplify_mesh(mesh, args.small), small)
        plan = [
            ("xatlas defaults", "xatlas-defaults", small),
            ("xatlas tuned", "xatlas-tuned", small),
            ("xatlas fast", "xatlas-fast", small),
            ("patches", "patches", small),
            ("xatlas tuned", "xatlas-tuned", args.mesh),
            ("xatlas fast", "xatlas-fast", args.mesh),
            ("patches", "patches", args.mesh),
        ]
        for name, row, path in plan:
            print(f"  running {name} on {path.name} ...", file=sys.stderr, flush=True)
            timeout = args.timeout if path == args.mesh else None
            result = _in_process(row, path, timeout)
            if result is None:
                faces = mesh.n_faces if path == args.mesh else read_mesh(path).n_faces
                result = {"faces": faces, "timeout": timeout}
            rows.append((name, result))

    print(
        f"atlas benchmark: {args.mesh} ({mesh.n_faces} faces), {SIZE}² page, {PADDING}-texel "
        f"padding, {os.cpu_count()} CPUs, load average {load_before:.1f} before, "
        f"{os.getloadavg()[0]:.1f} after"
    )
    header = ("method", "faces", "charts", "utilisation", "seconds", "page", "shared", "notes")
    table = []
    for name, r in rows:
        if "timeout" in r:
            table.append(
                (name, f"{r['faces']:,}", "-", "-", f"> {r['timeout']:.0f}", "-", "-", "stopped")
            )
            continue
        table.append(
            (
                name,
                f"{r['faces']:,}",
                f"{r['charts']:,}",
                f"{r['utilisation']:.3f}",
                f"{r['seconds']:.1f}",
                r["page"],
                str(r["shared"]),
                r["note"],
            )
        )
    widths = [max(len(str(line[k])) for line in [header, *table]) for k in range(len(header) - 1)]
    for line in [header, *table]:
        cells = [
            f"{c:<{w}}" if k == 0 else f"{c:>{w}}" for k, (c, w) in enumerate(zip(line, widths))
        ]
        print(" | ".join(cells) + " | " + line[-1])


if __name__ == "__main__":
    main()
