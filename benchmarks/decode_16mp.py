"""Decoding one 16 MP JPEG Gray-code view: time and peak memory of slscan against OpenCV's rule.

    .venv/bin/python benchmarks/decode_16mp.py [--against REV] [--session DIR] [--size 4896x3264]
                                               [--quality 90] [--repeat 1] [--keep DIR]

The view (unless ``--session`` names a capture session to decode instead): the five
kamino410/procam-calibration captures' first (1280x1024 grey, real photographs of a wall
and a board, lit across the whole frame: 10 + 10 Gray-code bits with inverses, white and
black, 42 images; a linear camera) upscaled (bilinear) to ``--size`` and saved as colour
JPEG at ``--quality`` as an sRGB camera would save them (a warm white balance, R, G, B
gains 1.00, 0.93, 0.82 in linear light so that the channels differ, then the sRGB curve),
then imported with ``import_graycode`` (preset kamino410), which measures the sRGB
response from the captures: what ``slscan import`` makes of a 3DUNDERWORLD-style camera
folder, lossy, read as luma in linear light.

Each decoder runs in a child process, one after the other; the child reports its peak
resident memory (``VmHWM``, the interpreter and imports included), wall and CPU seconds
(median of ``--repeat`` runs; the JPEG files are in the page cache after the first):

- **OpenCV rule**: OpenCV ``structured_light::GrayCodePattern``'s decode as a user runs it,
  written in numpy (opencv-contrib is not installed): every image loaded with
  ``cv2.imread(file, cv2.IMREAD_GRAYSCALE)`` into a list (as OpenCV's sample collects
  ``captured``), ``|white - black| > 40``, every bit ``|pattern - inverse| >= 5``, bit set
  where ``pattern > inverse``, Gray to binary, codes beyond the projector invalid
  (``computeShadowMasks``, ``getProjPixel``). No sub-pixel edges, no noise estimate, no
  global-light test.
- **slscan REV** (``--against``, default the merge base with ``main``): ``decode_gray``
  of that revision's toolbox (exported with ``git archive``).
- **slscan**: ``decode_gray`` of this tree: adaptive thresholds from the measured noise,
  the direct/global split and consistency test, sub-pixel stripe edges along both axes.
- **slscan, rule**: the same with OpenCV's rule for the mask (``--gray-threshold opencv``:
  the captures as stored, no noise estimate, no global-light test), still finding the
  sub-pixel edges: what the rule costs inside slscan.

"maps" and "edges" are checksums of the decoded column, row and mask maps and of the edge
samples: equal checksums mean equal results.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from measure import export_toolbox, run_json

from slscan.data import shared_data_dir

SLSCAN = r"""
import hashlib, json, sys, time
from pathlib import Path
import numpy as np
from slscan.capture.session import load_session
from slscan.decode.graycode import decode_gray

session = load_session(sys.argv[1], validate=False)
options = {"threshold": sys.argv[2]} if len(sys.argv) > 2 else {}
t, c = time.perf_counter(), time.process_time()
res = decode_gray(session, session.views[0], **options)
wall, cpu = time.perf_counter() - t, time.process_time() - c
peak = next(int(l.split()[1]) * 1024 for l in Path("/proc/self/status").read_text().splitlines() if l.startswith("VmHWM:"))
digest = lambda arrays: hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest()[:8]
e = res.edges
print(json.dumps({
    "peak_bytes": peak, "wall_s": wall, "cpu_s": cpu, "valid": float(res.mask.mean()),
    "maps": digest((res.column, res.row, res.mask)), "edges": digest((e.row, e.x, e.stripe, e.contrast)),
}))
"""

OPENCV = r"""
import json, sys, time
from pathlib import Path
import cv2
import numpy as np

meta = json.loads((Path(sys.argv[1]) / "session.json").read_text())
view = Path(sys.argv[1]) / meta["views"][0]["name"]
files = {r["pattern"]: view / r["file"] for r in meta["views"][0]["images"]}
gray = [p for p in meta["patterns"] if p["family"] == "gray"]
t, c = time.perf_counter(), time.process_time()
captured = {pid: cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for pid, f in files.items()}
valid = np.abs(captured["white"].astype(np.int16) - captured["black"]) > 40   # computeShadowMasks
decoded = {}
for axis, size in (("columns", meta["projector"]["width"]), ("rows", meta["projector"]["height"])):
    bits = sorted((p for p in gray if p["axis"] == axis and not p["inverse"]), key=lambda p: p["bit"])
    code = np.zeros(valid.shape, np.int32)
    for p in bits:                                                                # getProjPixel
        a, b = captured[p["id"]], captured[p["id"] + "-inv"]
        valid &= cv2.absdiff(a, b) >= 5
        code <<= 1
        code |= a > b
    shift = code >> 1
    while shift.any():                                                            # Gray to binary
        code ^= shift
        shift >>= 1
    valid &= code < size
    decoded[axis] = code
wall, cpu = time.perf_counter() - t, time.process_time() - c
peak = next(int(l.split()[1]) * 1024 for l in Path("/proc/self/status").read_text().splitlines() if l.startswith("VmHWM:"))
print(json.dumps({"peak_bytes": peak, "wall_s": wall, "cpu_s": cpu, "valid": float(valid.mean()),
                  "maps": "-", "edges": "-"}))
"""

GAINS = (1.0, 0.93, 0.82)
"""R, G, B gains of the made JPEGs (a camera's warm white balance): the channels differ."""


def make_session(size: tuple[int, int], quality: int, data: Path, folder: Path) -> Path:
    """kamino410 ``capture_0`` upscaled to ``size``, saved as colour JPEG and imported."""
    from slscan.capture.graycode_import import import_graycode

    src = data / "procam_graycode_kamino410" / "sample_data" / "capture_0"
    if not src.is_dir():
        raise SystemExit(f"kamino410 captures not found at {src} (--session, or $SLSCAN_DATA)")
    shots = folder / "jpeg" / "capture_0"
    shots.mkdir(parents=True)
    from slscan.virtual.sensor import srgb_oetf

    for f in sorted(src.glob("graycode_*.png")):
        grey = cv2.resize(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), size, interpolation=cv2.INTER_LINEAR)
        linear = grey.astype(np.float32) / 255
        bgr = np.stack([np.rint(srgb_oetf(np.clip(linear * g, 0, 1)) * 255).astype(np.uint8) for g in GAINS[::-1]],
                       axis=-1)
        cv2.imwrite(str(shots / f"{f.stem}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
    session = import_graycode(folder / "jpeg", folder / "session", preset="kamino410")
    return Path(session.root)


def run(code: str, session: Path, label: str, toolbox: Path | None, repeat: int, *extra: str) -> dict:
    runs = [run_json([sys.executable, "-c", code, str(session), *extra], label, toolbox) for _ in range(repeat)]
    out = dict(runs[0])
    for key in ("peak_bytes", "wall_s", "cpu_s"):
        out[key] = statistics.median(r[key] for r in runs)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", metavar="REV", help="git revision to compare with (default: merge base with main)")
    ap.add_argument("--session", type=Path, help="decode this capture session's first view instead of making one")
    ap.add_argument("--size", default="4896x3264", help="camera size WxH of the made view (default 4896x3264)")
    ap.add_argument("--quality", type=int, default=90, help="JPEG quality of the made view (default 90)")
    ap.add_argument("--repeat", type=int, default=1, help="runs per decoder (median; default 1)")
    ap.add_argument("--keep", type=Path, help="make the view in this folder and keep it")
    ap.add_argument("--data", type=Path, default=None, help="shared data folder")
    args = ap.parse_args()
    rev = args.against or subprocess.run(["git", "merge-base", "HEAD", "main"], capture_output=True, text=True,
                                         check=True).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.session:
            session = args.session
        else:
            size = tuple(int(v) for v in args.size.lower().split("x"))
            session = make_session(size, args.quality, args.data or shared_data_dir(), args.keep or tmp / "made")
        meta = json.loads((session / "session.json").read_text())
        old = export_toolbox(rev, tmp / "old")
        rows = [("OpenCV rule", run(OPENCV, session, "opencv", None, args.repeat)),
                (f"slscan {rev[:7]}", run(SLSCAN, session, "slscan old", old, args.repeat)),
                ("slscan", run(SLSCAN, session, "slscan", None, args.repeat)),
                ("slscan, rule", run(SLSCAN, session, "slscan opencv", None, args.repeat, "opencv"))]
    cam = meta["camera"]
    print(f"one view of {session}: {cam['width']}x{cam['height']} ({cam['width'] * cam['height'] / 1e6:.1f} MP), "
          f"{len(meta['views'][0]['images'])} {'JPEG' if cam['lossy'] else 'lossless'} images, "
          f"{cam['channels']} channel(s), response {cam['response']}; each decoder in a child process, "
          f"median of {args.repeat}")
    base = rows[0][1]
    head = (f"{'decoder':<16}{'peak GB':>9}{'x OpenCV':>9}{'wall s':>8}{'x OpenCV':>9}{'CPU s':>7}"
            f"{'decoded':>9}{'maps':>10}{'edges':>10}")
    print(head)
    print("-" * len(head))
    for label, r in rows:
        print(f"{label:<16}{r['peak_bytes'] / 1e9:>9.2f}{r['peak_bytes'] / base['peak_bytes']:>9.2f}"
              f"{r['wall_s']:>8.1f}{r['wall_s'] / base['wall_s']:>9.2f}{r['cpu_s']:>7.1f}{r['valid']:>9.3f}"
              f"{r['maps']:>10}{r['edges']:>10}")


if __name__ == "__main__":
    main()
