"""Gray-code thresholds against OpenCV's fixed rule, and the camera response each session measures.

    .venv/bin/python benchmarks/graycode_thresholds.py [--data DIR] [--quality 90] [--scale 0.5]
                                                       [--tables captures,kinds]

Table ``captures``: for each kamino410/procam-calibration capture (1280x1024 grey, 10 + 10 bits with inverses),
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

Table ``kinds``: one session of each kind, decoded through ``decode_gray`` as ``slscan
decode`` does (the session's files, its measured ``camera.response``). Virtual figurine
at ``--scale`` of the paper's camera (quarter-size projector, exposure 1.5, row codes):
grey 8-bit PNG, grey 16-bit PNG, RGB 8-bit PNG (linear camera), RGB JPEG from a linear
camera (a fixed-exposure shot of grey stripes), RGB JPEG from an sRGB camera, and the sRGB
camera's RGB PNG session as rendered; then the real kamino410 captures (grey PNG, 10 + 10
bits) and the kamino410 phase-shifting captures' Gray-code images (``pat12``-``pat29``,
OpenCV ``GrayCodePattern`` of 20 x 11 cells, ``pat30`` white, ``pat31`` black). Per kind:

- ``response``: what the captures of that view measure (what the import records for a
  session's first view; ``*``: not measured, linear by default), the residual of linear
  and of sRGB (``capture/response.py``), the nearest power law, and the fit's time
  (reading the 6 captures included);
- ``adaptive``: share of pixels the default decoder keeps; ``(other)``: the same with the
  captures read through the other curve (``slscan decode --response``): what assuming
  the wrong one costs;
- ``opencv`` / ``cv rule``: share under ``threshold="opencv"`` / under OpenCV's rule
  implemented here independently on the files as an OpenCV user loads them
  (``cv2.imread``, RGB through ``cvtColor(BGR2GRAY)``; 16 bit: thresholds x 257);
- ``agree``: share of pixels where the two agree exactly (both reject, or both accept with
  the same column and row);
- ``agree imread``: the same against that rule on files loaded with
  ``cv2.IMREAD_GRAYSCALE`` (libpng's / libjpeg's own grey: OpenCV's sample loads the
  patterns so), which differs by a DN on some RGB pixels.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from measure import kamino410_gray_views

from slscan.capture.graycode_import import import_graycode
from slscan.capture.response import measure_session_response, with_response
from slscan.capture.session import Session, load_session
from slscan.data import shared_data_dir
from slscan.decode.graycode import decode_gray, decode_gray_images, gray_pairs
from slscan.patterns.graycode import inverse_gray

ORDER = "white,black,cols:pairs,rows:pairs"  # the virtual rig's pattern order


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


def opencv_rule_on_files(session: Session, view_name: str, flags: int = cv2.IMREAD_UNCHANGED,
                         black_threshold: int = 40, white_threshold: int = 5):
    """(valid, column, row) of OpenCV GrayCodePattern's rule on a session view's files as an
    OpenCV user loads them: ``cv2.imread(file, flags)``, colour through ``cvtColor(BGR2GRAY)``;
    16-bit captures with the thresholds times 257."""
    view = session.view(view_name)

    def grey(pid: str) -> np.ndarray:
        image = cv2.imread(str(session.root / view.name / view.image_for(pid).file), flags)
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return image.astype(np.int64)

    scale = 257 if session.bit_depth == 16 and flags == cv2.IMREAD_UNCHANGED else 1
    descs = [p for p in session.patterns if p.family == "gray"]
    valid = np.abs(grey("white") - grey("black")) > black_threshold * scale
    values = []
    for axis, size in (("columns", session.projector_size[0]), ("rows", session.projector_size[1])):
        code = np.zeros(valid.shape, np.int64)
        for pid, inv in gray_pairs(descs, axis):
            p, q = grey(pid), grey(inv)
            valid &= ~(np.abs(p - q) < white_threshold * scale)
            code = (code << 1) | (p > q)
        value = inverse_gray(code)
        valid &= value < size
        values.append(value)
    return valid, values[0], values[1]


def _export(session: Session, folder: Path, *, grey: bool, ext: str, quality: int) -> Path:
    """A rendered session's captures saved as another camera would: grey (cvtColor) or
    RGB, PNG at the session's depth or JPEG, numbered in ORDER."""
    view = session.views[0]
    folder.mkdir(parents=True)
    ids = ["white", "black"] + [p.id for p in session.patterns if p.family == "gray"]
    for k, pid in enumerate(ids):
        image = session.read_image(view, view.image_for(pid))
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY if grey else cv2.COLOR_RGB2BGR)
        params = [cv2.IMWRITE_JPEG_QUALITY, quality] if ext == ".jpg" else []
        cv2.imwrite(str(folder / f"{k:02d}{ext}"), image, params)
    return folder


def virtual_kinds(tmp: Path, scale: float, quality: int):
    """(kind, session) of each virtual session kind, imported from exported files (the
    import measures the response)."""
    from slscan.virtual.device import VirtualCaptureConfig, capture_session
    from slscan.virtual.sensor import Sensor

    def render(name: str, bit_depth: int = 8, response: str = "linear") -> Session:
        config = VirtualCaptureConfig(
            scene="object", patterns="gray", gray_rows=True, camera_scale=scale, projector_scale=0.25,
            lit_images=False, sensor=Sensor(bit_depth=bit_depth, response=response, exposure=1.5))
        return capture_session(config, tmp / name)

    def imported(name: str, source: Session, grey: bool, ext: str) -> Session:
        src = _export(source, tmp / name / "view_000", grey=grey, ext=ext, quality=quality)
        import_graycode(src, tmp / f"{name}-session", order=ORDER, projector_size=source.projector_size)
        return load_session(tmp / f"{name}-session")

    linear8, linear16, srgb = render("l8"), render("l16", 16), render("s8", response="srgb")
    yield "virtual grey 8-bit PNG", imported("g8", linear8, True, ".png")
    yield "virtual grey 16-bit PNG", imported("g16", linear16, True, ".png")
    yield "virtual RGB 8-bit PNG", imported("c8", linear8, False, ".png")
    yield f"virtual RGB JPEG{quality} lin", imported("jl", linear8, False, ".jpg")
    yield f"virtual RGB JPEG{quality} sRGB", imported("js", srgb, False, ".jpg")
    yield "virtual sRGB session (PNG)", imported("sp", srgb, False, ".png")


def real_kinds(data: Path, tmp: Path):
    """(kind, session) of the real captures: kamino410 procam (per capture) and phase
    captures' Gray code (per object)."""
    from slscan.capture.kamino410 import import_kamino410

    src = data / "procam_graycode_kamino410" / "sample_data"
    if src.is_dir():
        import_kamino410(src, tmp / "kamino")
        session = load_session(tmp / "kamino")
        for view in session.views:
            yield f"kamino410 {view.name}", session, view.name
    phase = data / "phaseshift_kamino410" / "sample_data"
    for obj in ("object1", "object2"):
        if (phase / obj).is_dir():
            import_graycode(phase / obj, tmp / obj, order=",".join(["skip"] * 12) + ",cols:pairs,rows:pairs,white,black",
                            projector_size=(20, 11), pattern="pat*")
            yield f"phase {obj} (20x11)", load_session(tmp / obj), obj


def kinds_table(data: Path | None, scale: float, quality: int) -> None:
    head = (f"{'kind':<29}{'response':<10}{'res lin':>8}{'res sRGB':>9}{'gamma (res)':>14}{'fit s':>6}"
            f"{'adaptive':>9}{'(other)':>8}{'opencv':>8}{'cv rule':>8}{'agree':>8}{'agree imread':>13}")
    print(f"\nsession kinds: virtual figurine at camera scale {scale}, JPEG quality {quality}; real captures")
    print(head)
    print("-" * len(head))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows = [(kind, session, session.views[0].name) for kind, session in virtual_kinds(tmp / "v", scale, quality)]
        if data is not None:
            rows += list(real_kinds(data, tmp / "r"))
        for kind, session, view in rows:
            t = time.perf_counter()
            fit = measure_session_response(session, views=[view])  # what the import does, on this view
            fit_s = time.perf_counter() - t
            assert fit.response == session.response or view != session.views[0].name
            adaptive = decode_gray(session, view)
            other = "srgb" if session.response == "linear" else "linear"
            adaptive_other = decode_gray(with_response(session, other), view)
            res = decode_gray(session, view, threshold="opencv")
            agree = []
            for flags in (cv2.IMREAD_UNCHANGED, cv2.IMREAD_GRAYSCALE):
                if flags == cv2.IMREAD_GRAYSCALE and session.bit_depth == 16:
                    agree.append(float("nan"))  # IMREAD_GRAYSCALE gives 8 bits
                    continue
                cv_valid, cv_col, cv_row = opencv_rule_on_files(session, view, flags)
                same = (res.mask == cv_valid) & (~cv_valid | ((res.column == cv_col) & (res.row == cv_row)))
                agree.append(float(same.mean()))
                if flags == cv2.IMREAD_UNCHANGED:
                    cv_share = float(cv_valid.mean())
            chosen = fit.response + ("" if fit.measured else "*")
            print(f"{kind:<29}{chosen:<10}{fit.residuals['linear']:>8.3f}{fit.residuals['srgb']:>9.3f}"
                  f"{f'{fit.gamma:.2f} ({fit.gamma_residual:.3f})':>14}{fit_s:>6.2f}"
                  f"{adaptive.mask.mean():>9.3f}{adaptive_other.mask.mean():>8.3f}{res.mask.mean():>8.3f}{cv_share:>8.3f}{agree[0]:>8.4f}"
                  f"{agree[1]:>13.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None)
    ap.add_argument("--quality", type=int, default=90, help="JPEG quality of the round trip")
    ap.add_argument("--scale", type=float, default=0.5, help="virtual camera size (1: the paper's 1440x960)")
    ap.add_argument("--tables", default="captures,kinds", help="which tables: captures, kinds")
    args = ap.parse_args()
    data = args.data or shared_data_dir()
    tables = args.tables.split(",")
    if "captures" in tables:
        captures_table(data, args.quality)
    if "kinds" in tables:
        kinds_table(data, args.scale, args.quality)


def captures_table(data: Path | None, quality: int) -> None:
    src = (data or Path("-")) / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        print(f"kamino410 captures not found at {src}: table 'captures' skipped")
        return
    head = (f"{'capture':<11}{'images':<8}{'mode':<10}{'valid':>7}{'cv valid':>9}{'agree':>9}"
            f"{'low contrast':>13}{'weak noise':>11}{'weak ratio':>11}{'noise DN':>9}")
    print(f"kamino410 captures from {src}; JPEG round trip at quality {quality}")
    print(head)
    print("-" * len(head))
    for view_name, raw, descs, white, black in kamino410_gray_views(src):
        raw = {**raw, "white": white, "black": black}
        for kind in ("PNG", f"JPEG{quality}"):
            imgs = raw if kind == "PNG" else {k: jpeg(v, quality) for k, v in raw.items()}
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
