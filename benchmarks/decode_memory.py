"""Peak memory and time of decoding one 16 MP, 42-image Gray-code view: this tree against a git revision.

    .venv/bin/python benchmarks/decode_memory.py --against REV [--size 4896x3264] [--capture 0]

Makes the view by upscaling a kamino410 capture (1280x1024 grey, 10 + 10 Gray-code bits
with inverses, white and black: 42 images) with ``cv2.resize`` (bilinear) to ``--size``,
writes it as PNG into a temporary folder, imports it with ``import_kamino410`` and decodes it with ``decode_gray`` in a child process
per code version, one after the other: the child reports its peak resident memory
(``VmHWM``), wall and CPU seconds, and what it decoded (valid share, column-decoded share,
edge samples, samples found along columns, checksums of the maps and of the edges found
along rows), so equal output shows next to the cost; a third run decodes with this tree's
row-only edge search, whose edges must equal the revision's bit for bit.
``--against REV`` runs the toolbox of git revision ``REV`` (exported with ``git archive``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parent))
from measure import export_toolbox, run_json

from slscan.data import shared_data_dir

CHILD = r"""
import hashlib, json, sys, time
from pathlib import Path
import numpy as np
from slscan.capture.session import load_session
from slscan.decode.graycode import decode_gray

session = load_session(sys.argv[1])
t, c = time.perf_counter(), time.process_time()
res = decode_gray(session, session.views[0], **json.loads(sys.argv[2]))
wall, cpu = time.perf_counter() - t, time.process_time() - c
peak = 0
for line in Path("/proc/self/status").read_text().splitlines():
    if line.startswith("VmHWM:"):
        peak = int(line.split()[1]) * 1024
e = res.edges
along = getattr(e, "along_columns", None)
print(json.dumps({
    "peak_bytes": peak, "wall_s": wall, "cpu_s": cpu,
    "valid": float(res.mask.mean()), "column": float((res.column >= 0).mean()),
    "edges": len(e), "along_columns": 0 if along is None else int(along.sum()),
    "noise_dn": float(res.noise * 255),
    "maps": hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in (res.column, res.row, res.mask))).hexdigest()[:8],
    "rows_edges": hashlib.sha1(b"".join(np.ascontiguousarray(getattr(e, f)[~along if along is not None else slice(None)]).tobytes()
                                        for f in ("row", "x", "stripe", "contrast"))).hexdigest()[:8],
}))
"""


def make_view(src: Path, size: tuple[int, int], folder: Path) -> Path:
    """``src`` capture folder upscaled to ``size`` (PNG) in ``folder``; returns the folder."""
    folder.mkdir(parents=True)
    for f in sorted(src.glob("*.png")):
        image = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(folder / f.name), cv2.resize(image, size, interpolation=cv2.INTER_LINEAR),
                    [cv2.IMWRITE_PNG_COMPRESSION, 1])
    return folder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", required=True, metavar="REV", help="git revision to compare with")
    ap.add_argument("--size", default="4896x3264", help="camera size WxH of the made view")
    ap.add_argument("--capture", type=int, default=0, help="kamino410 capture to upscale")
    ap.add_argument("--data", type=Path, default=None, help="shared data folder")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    data = args.data or shared_data_dir()
    src = data / "procam_graycode_kamino410" / "sample_data" / f"capture_{args.capture}"
    if not src.is_dir():
        raise SystemExit(f"kamino410 capture not found: {src}")
    from slscan.capture.kamino410 import import_kamino410

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        view = make_view(src, size, tmp / "sample_data" / "capture_0")
        pattern = src.parent / "graycode_pattern"
        if pattern.is_dir():
            (tmp / "sample_data" / "graycode_pattern").symlink_to(pattern)
        session = import_kamino410(view, tmp / "session")
        n = len(session.views[0].images)
        old = export_toolbox(args.against, tmp / "old")
        rows = []
        runs = ((args.against, old, {}), ("this tree", None, {}),
                ("rows only", None, {"edge_axes": "rows"}))
        for label, toolbox, options in runs:
            rows.append((label, run_json([sys.executable, "-c", CHILD, str(tmp / "session"), json.dumps(options)],
                                         f"decode ({label})", toolbox)))
    print(f"one view: kamino410 capture_{args.capture} upscaled to {size[0]}x{size[1]} "
          f"({size[0] * size[1] / 1e6:.1f} MP grey), {n} PNG images; decode_gray in a child process")
    head = (f"{'code':<12}{'peak GB':>9}{'wall s':>8}{'CPU s':>7}{'valid':>8}{'column':>8}"
            f"{'edges':>10}{'along col':>10}{'noise DN':>9}{'maps':>10}{'row edges':>10}")
    print(head)
    print("-" * len(head))
    for label, r in rows:
        print(f"{label:<12}{r['peak_bytes'] / 1e9:>9.2f}{r['wall_s']:>8.1f}{r['cpu_s']:>7.1f}"
              f"{r['valid']:>8.4f}{r['column']:>8.4f}{r['edges']:>10d}{r['along_columns']:>10d}"
              f"{r['noise_dn']:>9.2f}{r['maps']:>10}{r['rows_edges']:>10}")
    print("maps: checksum of the column, row and mask maps; row edges: of the samples found along "
          "rows (row, x, stripe, contrast); 'rows only' is this tree with edge_axes='rows'")


if __name__ == "__main__":
    main()
