"""Projector codes on real captures: what ``slscan decode --codes`` costs per view, and its files.

    .venv/bin/python benchmarks/codes.py [--data DIR] [--repeat 3]

The five kamino410/procam-calibration captures (1280x1024 grey PNG, 1024x768 projector,
10 column + 10 row Gray-code bits with inverses, no calibration) are imported once with
``import_kamino410``. Per view, side by side in the same run:

- before: ``decode_gray(session, view)``, the Python call that was the only way to get
  the maps (nothing written);
- now: the same decode plus writing the maps (``decode_codes`` + ``write_view_codes``, what
  each worker of ``slscan decode --codes`` does): CPU and wall seconds (median of
  ``--repeat``), the share of the time spent writing, the size of ``columns.png``,
  ``rows.png``, ``mask.png`` and ``codes.json`` against the same maps saved with ``np.save``
  (int32 column and row, bool mask), and the accuracy: the valid share, and the pixels
  where the maps read back with ``read_codes`` differ from ``decode_gray``'s (0 expected).

Then the whole command, ``slscan decode SESSION --out DIR`` on one worker (the session has
no calibration, so it writes codes only): CPU (this process's children) and wall seconds.

The data folder is ``slscan.data.shared_data_dir()`` (``$SLSCAN_DATA`` or ``../shared/data``)
unless ``--data`` is given.
"""

from __future__ import annotations

import argparse
import io
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from slscan.capture.kamino410 import import_kamino410
from slscan.data import shared_data_dir
from slscan.decode.codes import codes_from_gray, read_codes, write_view_codes
from slscan.decode.graycode import decode_gray


def _timed(fn, *args):
    """(``fn(*args)``, CPU s of this process incl. the reading thread, wall s)."""
    c, w = time.process_time(), time.perf_counter()
    out = fn(*args)
    return out, time.process_time() - c, time.perf_counter() - w


def _decode_and_write(session, view, folder: Path) -> float:
    """What a worker of ``slscan decode --codes`` does for one view; returns the writing's wall s."""
    found = codes_from_gray(decode_gray(session, view), session, view.name)
    t = time.perf_counter()
    write_view_codes(found, folder)
    return time.perf_counter() - t


def _npy_bytes(*arrays: np.ndarray) -> int:
    total = 0
    for a in arrays:
        buf = io.BytesIO()
        np.save(buf, a)
        total += buf.tell()
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    data = args.data or shared_data_dir()
    src = None if data is None else data / "procam_graycode_kamino410" / "sample_data"
    if src is None or not src.is_dir():
        sys.exit(f"kamino410 captures not found at {src}: pass --data or set SLSCAN_DATA")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        session = import_kamino410(src, tmp / "session")
        print(f"kamino410 captures from {src}: camera {session.camera_size[0]}x{session.camera_size[1]}, "
              f"projector {session.projector_size[0]}x{session.projector_size[1]}, median of {args.repeat} runs")
        head = (f"{'view':<10}{'before CPU s':>13}{'wall s':>8}{'now CPU s':>11}{'wall s':>8}{'writing':>8}"
                f"{'columns':>9}{'rows':>8}{'mask':>8}{'json':>6}{'all KB':>8}{'npy KB':>8}"
                f"{'valid':>7}{'noise DN':>9}{'differ':>7}")
        print(head)
        print("-" * len(head))
        totals = np.zeros(4)
        for view in session.views:
            before, now, write = [], [], []
            for k in range(args.repeat):
                ref, cpu, wall = _timed(decode_gray, session, view)
                before.append((cpu, wall))
                folder = tmp / "codes" / f"{view.name}-{k}"
                t_write, cpu, wall = _timed(_decode_and_write, session, view, folder)
                now.append((cpu, wall))
                write.append(t_write / wall)
            back = read_codes(folder)
            differ = int((back.column != ref.column).sum() + (back.row != ref.row).sum()
                         + (back.mask != ref.mask).sum())
            sizes = [(folder / name).stat().st_size for name in ("columns.png", "rows.png", "mask.png", "codes.json")]
            npy = _npy_bytes(ref.column, ref.row, ref.mask)
            b = [statistics.median(x) for x in zip(*before)]
            n = [statistics.median(x) for x in zip(*now)]
            totals += [*b, *n]
            print(f"{view.name:<10}{b[0]:>13.2f}{b[1]:>8.2f}{n[0]:>11.2f}{n[1]:>8.2f}"
                  f"{statistics.median(write):>8.0%}{sizes[0] / 1e3:>9.0f}{sizes[1] / 1e3:>8.0f}"
                  f"{sizes[2] / 1e3:>8.0f}{sizes[3] / 1e3:>6.1f}{sum(sizes) / 1e3:>8.0f}{npy / 1e3:>8.0f}"
                  f"{back.valid_share.decoded:>7.3f}{back.valid_share.noise_dn:>9.2f}{differ:>7d}")
        print("-" * len(head))
        print(f"{'all':<10}{totals[0]:>13.2f}{totals[1]:>8.2f}{totals[2]:>11.2f}{totals[3]:>8.2f}")

        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        cmd = [sys.executable, "-m", "slscan.cli", "decode", str(session.root), "--out", str(tmp / "cli"),
               "--quiet", "--workers", "1"]
        subprocess.run(cmd, check=True, capture_output=True)
        wall = time.perf_counter() - t
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
        size = sum(p.stat().st_size for p in (tmp / "cli").rglob("*") if p.is_file())
        print(f"\nslscan decode SESSION --out DIR --workers 1 (codes only, {len(session.views)} views, "
              f"start-up included): CPU {cpu:.2f} s, wall {wall:.2f} s, {size / 1e6:.2f} MB written")


if __name__ == "__main__":
    main()
