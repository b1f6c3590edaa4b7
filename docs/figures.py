"""Regenerate the pictures in docs/images from a demo session: .venv/bin/python docs/figures.py SESSION"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from slscan.capture.session import load_session
from slscan.viewer.log import projector_column_image

CROP = (slice(190, 770), slice(410, 1010))  # the figurine in the default 1440x960 view


def save(name: str, rgb: np.ndarray) -> None:
    out = Path(__file__).parent / "images" / name
    small = cv2.resize(rgb[CROP], None, fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(out), np.ascontiguousarray(small[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def main(session_dir: str) -> None:
    s = load_session(session_dir)
    view = s.views[0]
    for pid, name in (("white", "capture_white.png"), ("hybrid-04", "capture_hybrid_level4.png")):
        save(name, s.read_image(view, view.image_for(pid)))
    save("capture_lit_0.png", s.read_image(view, view.lit_images()[0]))
    truth = s.load_ground_truth(view)
    save("truth_projector_column.png", projector_column_image(truth.projector_uv[..., 0], s.projector_size[0]))
    vis = np.array([[0, 0, 0], [60, 60, 150], [255, 210, 60]], np.uint8)[truth.visibility]
    save("truth_visibility.png", vis)
    crop = s.read_image(view, view.image_for("hybrid-09"))[430:490, 700:760]
    zoom = cv2.resize(crop, None, fx=6, fy=6, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(Path(__file__).parent / "images" / "capture_hybrid_level9_zoom.png"), zoom[..., ::-1])


if __name__ == "__main__":
    main(sys.argv[1])
