"""Importing Gray-code captures: the generic importer against the kamino410 one, and JPEG
captures kept as they are against converting them to PNG first.

    .venv/bin/python benchmarks/graycode_import.py [--data DIR] [--against REV] [--repeat 3]

Prints two tables, both on the five kamino410/procam-calibration captures (5 views x 42
grey 1280x1024 PNGs) from ``slscan.data.shared_data_dir()`` or ``--data``.

1. Import time of the 210 images: ``import_kamino410`` of git revision ``--against``
   (default ``main``, run from a temporary export of its ``toolbox/``), and in this tree
   ``import_kamino410`` (now a wrapper that also checks ``graycode_pattern/``) and
   ``import_graycode(preset="kamino410")``. Each run is a child process; wall and CPU
   seconds (the child's user + system) are medians of ``--repeat`` runs. "same" says
   whether the session's pattern descriptions, image names and bytes equal the
   ``--against`` import's (equal bytes and descriptions decode to equal maps; the tests
   decode both to check).
2. A JPEG folder: the same captures written as JPEG (OpenCV, quality 95, a typical camera
   setting), imported as they are, against the old way: every JPEG decoded and written as
   PNG (what slscan required before), then imported. Size on disk of the session, the
   conversion, import and Gray-code decode times (``decode_gray`` over the 5 views, this
   process's CPU incl. the reading thread), and the decoded share of pixels (column and
   row); "maps equal" compares both ways' decoded columns, rows and masks.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from measure import cpu_seconds, export_toolbox

from slscan.capture.graycode_import import import_graycode
from slscan.capture.session import load_session
from slscan.data import ENV_VAR, shared_data_dir
from slscan.decode.graycode import decode_gray

CHILD = """
import json, resource, sys, time
src, out, how = sys.argv[1:4]
t0 = time.perf_counter()
if how == "graycode":
    from slscan.capture.graycode_import import import_graycode
    import_graycode(src, out, preset="kamino410")
else:
    from slscan.capture.kamino410 import import_kamino410
    import_kamino410(src, out)
u = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": u.ru_utime + u.ru_stime}))
"""


def _folder_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _signature(session_dir: Path) -> tuple:
    meta = json.loads((session_dir / "session.json").read_text())
    files = tuple(
        (v["name"], r["file"], (session_dir / v["name"] / r["file"]).read_bytes())
        for v in meta["views"] for r in v["images"]
    )
    return json.dumps(meta["patterns"], sort_keys=True), files


def _run_child(toolbox: Path, src: Path, out: Path, how: str) -> dict:
    import os

    env = dict(os.environ, PYTHONPATH=str(toolbox))
    proc = subprocess.run([sys.executable, "-c", CHILD, str(src), str(out), how],
                          capture_output=True, text=True, env=env, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"import ({how}, {toolbox}) failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def import_table(src: Path, against: str, repeat: int, tmp: Path) -> None:
    here = Path(__file__).resolve().parent.parent / "toolbox"
    old = export_toolbox(against, tmp / "old")
    rows = [(f"import_kamino410 @ {against}", old, "kamino410"),
            ("import_kamino410 (this tree)", here, "kamino410"),
            ("import_graycode kamino410 (this tree)", here, "graycode")]
    print(f"\nimport of {src} (5 views x 42 PNGs), median of {repeat} runs, each a child process")
    print(f"{'path':<40}{'wall s':>8}{'CPU s':>8}{'session MB':>12}{'same':>6}")
    reference = None
    for k, (label, toolbox, how) in enumerate(rows):
        walls, cpus = [], []
        for r in range(repeat):
            out = tmp / f"imp{k}_{r}"
            m = _run_child(toolbox, src, out, how)
            walls.append(m["wall"])
            cpus.append(m["cpu"])
        sig = _signature(tmp / f"imp{k}_0")
        reference = reference or sig
        print(f"{label:<40}{statistics.median(walls):>8.2f}{statistics.median(cpus):>8.2f}"
              f"{_folder_bytes(tmp / f'imp{k}_0') / 1e6:>12.1f}{'yes' if sig == reference else 'NO':>6}")


def _decode_all(session_dir: Path) -> tuple[float, float, float, list]:
    session = load_session(session_dir)
    c0, t0 = cpu_seconds(), time.perf_counter()
    results = [decode_gray(session, v) for v in session.views]
    wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
    share = float(np.mean([r.mask.mean() for r in results]))
    return wall, cpu, share, [(r.column, r.row, r.mask) for r in results]


def jpeg_table(src: Path, tmp: Path) -> None:
    jpeg_src = tmp / "jpeg_src"
    for view in sorted(src.glob("capture_*")):
        (jpeg_src / view.name).mkdir(parents=True)
        for png in sorted(view.glob("graycode_*.png")):
            cv2.imwrite(str(jpeg_src / view.name / (png.stem + ".jpg")),
                        cv2.imread(str(png), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_JPEG_QUALITY, 95])

    # the new way: the JPEGs as they are
    c0, t0 = cpu_seconds(), time.perf_counter()
    import_graycode(jpeg_src, tmp / "s_jpeg", preset="kamino410")
    jpeg_import = (time.perf_counter() - t0, cpu_seconds() - c0)
    jpeg_decode = _decode_all(tmp / "s_jpeg")

    # the old way: decode every JPEG, write it as PNG, import the PNGs
    png_src = tmp / "png_src"
    c0, t0 = cpu_seconds(), time.perf_counter()
    for jpg in sorted(jpeg_src.rglob("*.jpg")):
        target = png_src / jpg.parent.name / (jpg.stem + ".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(target), cv2.imread(str(jpg), cv2.IMREAD_UNCHANGED))
    convert = (time.perf_counter() - t0, cpu_seconds() - c0)
    c0, t0 = cpu_seconds(), time.perf_counter()
    import_graycode(png_src, tmp / "s_png", preset="kamino410")
    png_import = (time.perf_counter() - t0, cpu_seconds() - c0)
    png_decode = _decode_all(tmp / "s_png")
    original = _decode_all(tmp / "s_orig") if (tmp / "s_orig").exists() else None

    equal = all(all(np.array_equal(a, b) for a, b in zip(x, y)) for x, y in zip(jpeg_decode[3], png_decode[3]))
    print("\nthe same captures as JPEG (quality 95): kept as they are vs converted to PNG first")
    print(f"{'path':<28}{'session MB':>11}{'convert s (CPU)':>17}{'import s (CPU)':>16}"
          f"{'decode s (CPU)':>16}{'decoded':>9}{'maps equal':>12}")
    for label, folder, conv, imp, dec in (
        ("JPEG as is (new)", tmp / "s_jpeg", None, jpeg_import, jpeg_decode),
        ("JPEG -> PNG (before)", tmp / "s_png", convert, png_import, png_decode),
    ):
        conv_text = "-" if conv is None else f"{conv[0]:.2f} ({conv[1]:.2f})"
        print(f"{label:<28}{_folder_bytes(folder) / 1e6:>11.1f}{conv_text:>17}"
              f"{f'{imp[0]:.2f} ({imp[1]:.2f})':>16}{f'{dec[0]:.2f} ({dec[1]:.2f})':>16}"
              f"{dec[2]:>9.2%}{'yes' if equal else 'NO':>12}")
    if original is not None:
        print(f"{'original PNGs (reference)':<28}{_folder_bytes(tmp / 's_orig') / 1e6:>11.1f}{'-':>17}{'-':>16}"
              f"{f'{original[0]:.2f} ({original[1]:.2f})':>16}{original[2]:>9.2%}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, help=f"shared data folder (default: ${ENV_VAR} or ../shared/data)")
    parser.add_argument("--against", default="main", help="git revision whose import_kamino410 is timed (default main)")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    data = args.data or shared_data_dir()
    src = None if data is None else data / "procam_graycode_kamino410" / "sample_data"
    if src is None or not src.is_dir():
        raise SystemExit(f"kamino410 captures not found (looked in {src}); give --data")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        import_table(src, args.against, args.repeat, tmp)
        import_graycode(src, tmp / "s_orig", preset="kamino410")
        jpeg_table(src, tmp)


if __name__ == "__main__":
    main()
