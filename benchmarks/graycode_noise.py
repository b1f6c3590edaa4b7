"""The Gray-code decoder's noise estimate against the true noise, and what it decides.

    .venv/bin/python benchmarks/graycode_noise.py [--scale 0.5] [--data DIR] [--against REV]

The decoder thresholds every bit's ``pattern - inverse`` at 3 standard deviations of its
noise, estimated from the captures (``GrayResult.noise``). Two tables:

1. virtual rig (figurine ``object`` and the ``concave`` corner with inter-reflection),
   plain Gray code and XOR-04, a linear camera and an sRGB one (effect ``tone``), each
   decoded twice: "linear" as the pipeline does (``decode_gray``: the recorded sRGB curve
   undone) and "as saved" (``decode_gray_images`` on the captures as they are, as for a
   session whose camera curve is not recorded). ``truth``: the same view rendered with
   noise seeds 0 and 1, the two renders' difference of every column bit's ``pattern -
   inverse`` over the lit pixels, divided by sqrt(2), as a standard deviation from its
   median absolute deviation (the estimator's statistic). ``est`` is the decoder's
   estimate, ``est/truth`` their ratio, ``valid`` the share of pixels decoded. On 8-bit
   captures decoded as saved both come in steps of 0.35 DN (the median of integer
   differences), and the estimate is at least the quantisation floor (0.41 DN), so the
   figurine is also rendered with a 16-bit sensor (``bits``);
2. the kamino410/procam-calibration real captures (1280x1024 grey, as saved: the
   session records no curve): estimate and valid share. No truth: one capture per view.

``--against REV`` decodes the same renders with REV's toolbox (git archive, a child
process) and prints its estimate and valid share beside this tree's. Every row of table 1
comes from our own simulator; table 2 is real data.
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from measure import export_toolbox, kamino410_gray_views, run_json

from slscan.capture.session import load_session
from slscan.data import shared_data_dir
from slscan.decode.graycode import decode_gray, decode_gray_images, gray_bits
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor

CASES = [(scene, family, effects, 8) for scene, extra in (("object", ()), ("concave", ("interreflection",)))
         for family in ("gray", "xor") for effects in (extra, (*extra, "tone"))]
CASES[2:2] = [("object", family, effects, 16) for family in ("gray", "xor") for effects in ((), ("tone",))]
"""(scene, pattern family, effects, sensor bit depth) of table 1."""


def render(work: Path, scene: str, family: str, effects: tuple, bits: int, scale: float, seed: int) -> Path:
    out = work / f"{scene}-{family}-{'+'.join(effects) or 'none'}-{bits}-{seed}"
    if not out.is_dir():  # the parent renders; an --against child reuses the folder
        config = VirtualCaptureConfig(scene=scene, views=1, patterns=family, gray_rows=False, lit_images=False,
                                      camera_scale=scale, projector_scale=scale, effects=effects, seed=seed,
                                      sensor=Sensor(bit_depth=bits))
        capture_session(config, out)
    return out


def grey(image: np.ndarray) -> np.ndarray:
    """Grey fractions of full scale of a capture (integer or float fractions)."""
    a = np.asarray(image)
    a = a / float(np.iinfo(a.dtype).max) if a.dtype.kind == "u" else a.astype(np.float64)
    return a.mean(axis=2) if a.ndim == 3 else a


def view_images(folder: Path, linear: bool):
    session = load_session(folder)
    view = session.views[0]
    descs = [p for p in session.patterns if p.family == "gray"]
    white_id, black_id = session.flat_frame_ids("noise benchmark")
    images = {p.id: session.read_image(view, view.image_for(p.id), linear=linear) for p in descs}
    return (session, view, images, descs, session.read_image(view, view.image_for(white_id), linear=linear),
            session.read_image(view, view.image_for(black_id), linear=linear))


def truth_dn(folders: list[Path], linear: bool) -> float:
    """Noise of ``pattern - inverse`` (DN of 255) from two renders that differ only in noise."""
    (_, _, im0, descs, w0, b0), (_, _, im1, _, _, _) = (view_images(f, linear) for f in folders)
    lit = (grey(w0) - grey(b0)) > 0.03
    resid = []
    for pid, inv in gray_bits(descs, "columns").pairs:
        d0 = grey(im0[pid]) - grey(im0[inv])
        d1 = grey(im1[pid]) - grey(im1[inv])
        resid.append((d0 - d1)[lit] / np.sqrt(2))
    r = np.concatenate(resid)
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) * 255


def decode_rows(work: Path, scale: float, data: Path | None) -> list[dict]:
    """Estimate (DN of 255) and valid share of every case and real capture, with this toolbox."""
    rows = []
    for scene, family, effects, bits in CASES:
        folder = render(work, scene, family, effects, bits, scale, 0)
        for domain in ("linear", "as saved"):
            if domain == "linear":
                session = load_session(folder)
                res = decode_gray(session, session.views[0])
            else:
                _, _, images, descs, white, black = view_images(folder, False)
                res = decode_gray_images(images, descs, white, black)
            rows.append({"key": [scene, family, "+".join(effects) or "none", bits, domain],
                         "est": res.noise * 255, "valid": float(res.mask.mean())})
    src = data / "procam_graycode_kamino410" / "sample_data" if data else None
    if src is not None and src.is_dir():
        for name, images, descs, white, black in kamino410_gray_views(src):
            res = decode_gray_images(images, descs, white, black)
            rows.append({"key": ["kamino410", name], "est": res.noise * 255, "valid": float(res.mask.mean())})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=0.5, help="virtual camera and projector scale")
    ap.add_argument("--data", type=Path, default=None, help="shared data folder (kamino410 captures)")
    ap.add_argument("--against", metavar="REV", help="git revision whose decoder to show side by side")
    ap.add_argument("--work", type=Path, default=None, help=argparse.SUPPRESS)  # the child's renders
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # the child's output
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    data = args.data or shared_data_dir()
    if args.json:
        print(json.dumps(decode_rows(args.work, args.scale, data)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) / "renders"
        for scene, family, effects, bits in CASES:
            for seed in (0, 1):
                render(work, scene, family, effects, bits, args.scale, seed)
        mine = decode_rows(work, args.scale, data)
        theirs = {}
        if args.against:
            toolbox = export_toolbox(args.against, Path(tmp) / "against")
            command = [sys.executable, __file__, "--json", "--work", str(work), "--scale", str(args.scale)]
            if data:
                command += ["--data", str(data)]
            theirs = {tuple(r["key"]): r for r in run_json(command, f"--against {args.against}", toolbox)}
        rev = subprocess.run(["git", "-C", str(Path(__file__).parent), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, check=False).stdout.strip() or "this tree"
        old = args.against or "-"
        print(f"1. virtual rig at {args.scale} size (our own simulator); DN of 255; new: this tree ({rev}), "
              f"old: {old}")
        head = (f"{'scene':<9}{'family':<7}{'effects':<22}{'bits':>4} {'decoded':<10}{'truth':>7}{'old est':>9}{'new est':>9}"
                f"{'old/tru':>9}{'new/tru':>9}{'old valid':>10}{'new valid':>10}")
        print(head)
        print("-" * len(head))
        for row in mine:
            key = tuple(row["key"])
            if key[0] == "kamino410":
                continue
            scene, family, effects, bits, domain = key
            folders = [render(work, scene, family, tuple(e for e in effects.split("+") if e != "none"), bits,
                              args.scale, seed) for seed in (0, 1)]
            truth = truth_dn(folders, domain == "linear")
            t = theirs.get(key, {"est": np.nan, "valid": np.nan})
            print(f"{scene:<9}{family:<7}{effects:<22}{bits:>4} {domain:<10}{truth:>7.3f}{t['est']:>9.3f}{row['est']:>9.3f}"
                  f"{t['est'] / truth:>9.2f}{row['est'] / truth:>9.2f}{t['valid']:>10.4f}{row['valid']:>10.4f}",
                  flush=True)
        real = [r for r in mine if r["key"][0] == "kamino410"]
        print()
        if not real:
            print("2. kamino410 real captures not found (pass --data): table skipped")
            return
        print(f"2. kamino410 real captures (as saved), DN of 255; old: {old}")
        head = f"{'capture':<11}{'old est':>9}{'new est':>9}{'old valid':>10}{'new valid':>10}{'new/old valid':>14}"
        print(head)
        print("-" * len(head))
        for row in real:
            t = theirs.get(tuple(row["key"]), {"est": np.nan, "valid": np.nan})
            print(f"{row['key'][1]:<11}{t['est']:>9.3f}{row['est']:>9.3f}{t['valid']:>10.4f}{row['valid']:>10.4f}"
                  f"{row['valid'] / t['valid']:>14.4f}", flush=True)


if __name__ == "__main__":
    main()
