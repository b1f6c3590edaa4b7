"""Gray-code thresholds on the kamino410 captures: adaptive vs OpenCV's fixed rule, PNG and JPEG.

    .venv/bin/python benchmarks/graycode_thresholds.py [--data DIR] [--quality 90]

For each kamino410/procam-calibration capture (1280x1024 grey, 10 + 10 bits with inverses),
as stored (PNG) and round-tripped through JPEG at ``--quality`` (which raises the noise
from about 2 to 4-5 DN), decodes with ``decode_gray_images(threshold=...)`` in both modes
and prints per mode:

- ``valid``: share of pixels whose column and row decode (the mask);
- ``cv valid``: the same share under OpenCV ``GrayCodePattern``'s rule, implemented here
  independently in numpy from its source (``computeShadowMasks``: ``|white - black| > 40``;
  ``getProjPixel``: a bit is an error when ``|pattern - inverse| < 5``, set when
  ``pattern > inverse``; codes beyond the projector are errors);
- ``agree``: share of pixels on which the mode and that rule agree exactly (both reject, or
  both accept with the same column and row);
- what the decode's ``diagnostics`` say limited the mask, as shares of all pixels: ``low
  contrast`` (white - black), ``weak noise`` / ``weak ratio`` (a bit under the noise term /
  under the share of white - black), and the noise in DN.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from measure import kamino410_gray_views

from slscan.data import shared_data_dir
from slscan.decode.graycode import decode_gray_images, gray_pairs
from slscan.patterns.graycode import inverse_gray


def opencv_rule(images, descs, white, black, black_threshold=40, white_threshold=5):
    """(valid, column, row) of OpenCV GrayCodePattern's decode on grey uint8 captures."""
    valid = np.abs(white.astype(np.int32) - black.astype(np.int32)) > black_threshold
    values = []
    for axis, size in (("columns", descs[0].width), ("rows", descs[0].height)):
        code = np.zeros(white.shape, np.int64)
        for pid, inv in gray_pairs(descs, axis):
            p, q = images[pid].astype(np.int32), images[inv].astype(np.int32)
            valid &= ~(np.abs(p - q) < white_threshold)
            code = (code << 1) | (p > q)
        value = inverse_gray(code)
        valid &= value < size
        values.append(value)
    return valid, values[0], values[1]


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    _, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--quality", type=int, default=90, help="JPEG quality of the round trip")
    args = ap.parse_args()
    src = (args.data or shared_data_dir()) / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        raise SystemExit(f"kamino410 captures not found at {src}")
    head = (f"{'capture':<11}{'images':<8}{'mode':<10}{'valid':>7}{'cv valid':>9}{'agree':>9}"
            f"{'low contrast':>13}{'weak noise':>11}{'weak ratio':>11}{'noise DN':>9}")
    print(f"kamino410 captures from {src}; JPEG round trip at quality {args.quality}")
    print(head)
    print("-" * len(head))
    for view_name, raw, descs, white, black in kamino410_gray_views(src):
        raw = {**raw, "white": white, "black": black}
        for kind in ("PNG", f"JPEG{args.quality}"):
            imgs = raw if kind == "PNG" else {k: jpeg(v, args.quality) for k, v in raw.items()}
            cv_valid, cv_col, cv_row = opencv_rule(imgs, descs, imgs["white"], imgs["black"])
            for mode in ("adaptive", "opencv"):
                res = decode_gray_images(imgs, descs, imgs["white"], imgs["black"], threshold=mode)
                same = (res.mask == cv_valid) & (
                    ~cv_valid | ((res.column == cv_col) & (res.row == cv_row)))
                d = res.diagnostics
                n = d["pixels"]
                print(f"{view_name:<11}{kind:<8}{mode:<10}{res.mask.mean():>7.3f}{cv_valid.mean():>9.3f}"
                      f"{same.mean():>9.4f}{d['low_contrast'] / n:>13.3f}{d['weak_bit_noise'] / n:>11.3f}"
                      f"{d['weak_bit_ratio'] / n:>11.3f}{d['noise_dn']:>9.2f}")


if __name__ == "__main__":
    main()
