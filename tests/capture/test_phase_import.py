"""Tests for the phase-shifting importer: synthetic captures in each preset's layout and in
order specs (the projected images written here from the tools' own formulas, warped by a
known homography into the camera: grey and RGB, 8 and 16 bit, PNG, TIFF, JPEG, BMP),
imported and decoded back to the warp's projector coordinates; every bad input; and the
kamino410 phase-shifting captures, imported and decoded with one command each."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from slscan.capture.phase_import import PRESETS, import_phase, is_phase_order, parse_phase_order
from slscan.capture.session import load_session
from slscan.cli import main
from slscan.decode.codes import FLOAT_ENCODING, read_codes
from slscan.decode.phase import decode_phase
from slscan.errors import SlscanError
from slscan.patterns.graycode import gray
from slscan.patterns.phase import joint_period

CAMERA = (240, 180)


# --- what the tools project (written from their formulas, not from the importer) -------------


def _homography(projector: tuple[int, int]) -> np.ndarray:
    """Camera-from-projector homography (pixel centres at whole numbers): the projector
    image lands slanted inside the camera image, about 1.1 camera px per projector px."""
    pw, ph = projector
    src = np.float32([[-0.5, -0.5], [pw - 0.5, -0.5], [pw - 0.5, ph - 0.5], [-0.5, ph - 0.5]])
    w, h = CAMERA
    dst = np.float32([[0.04 * w, 0.08 * h], [0.96 * w, 0.03 * h], [0.93 * w, 0.95 * h], [0.07 * w, 0.9 * h]])
    return cv2.getPerspectiveTransform(src, dst)


def _truth(projector: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projector column and row (float) at each camera pixel centre, and where well inside."""
    hinv = np.linalg.inv(_homography(projector))
    ys, xs = np.mgrid[0 : CAMERA[1], 0 : CAMERA[0]].astype(np.float64)
    p = hinv @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    u, v = (p[:2] / p[2]).reshape(2, *xs.shape)
    inside = (u >= 2) & (u <= projector[0] - 3) & (v >= 2) & (v <= projector[1] - 3)
    return u, v, inside


def _along(values: np.ndarray, axis: str, projector: tuple[int, int]) -> np.ndarray:
    """A (ph, pw) projector image varying along ``axis`` with ``values`` (one per px)."""
    pw, ph = projector
    return np.broadcast_to(values[None, :] if axis == "columns" else values[:, None], (ph, pw)).astype(np.float64)


def _sine(axis, projector, period, shift, *, form="cos", sign=1, origin=0.0, power=1.0, rounding=np.rint):
    """The 8-bit fringe a tool computes: 255 * (0.5 + 0.5 f(sign 2 pi (x - origin) / P + shift)) ** power."""
    size = projector[0] if axis == "columns" else projector[1]
    x = np.arange(size, dtype=np.float64)
    f = np.cos if form == "cos" else np.sin
    value = rounding(255 * (0.5 + 0.5 * f(sign * 2 * np.pi * (x - origin) / period + shift)) ** power)
    return _along(np.clip(value, 0, 255) / 255, axis, projector)


def _gray(axis, projector, cell, bit, bits, *, inverse=False, origin=0.0):
    """OpenCV's GrayCodePattern image of ``cell``-px cells: bit ``bit`` (0 = MSB) of gray(cell index)."""
    size = projector[0] if axis == "columns" else projector[1]
    index = np.floor((np.arange(size) - origin) / cell).astype(np.int64)
    on = ((gray(np.maximum(index, 0)) >> (bits - 1 - bit)) & 1).astype(np.float64)
    return _along(1 - on if inverse else on, axis, projector)


def _flat(projector, value):
    return np.full((projector[1], projector[0]), float(value))


def _photograph(light: np.ndarray, projector, rng, *, response=1.0, channels=1, depth=8, srgb=False):
    """What the camera records of projector ``light`` (values in [0, 1]): the projector's
    response, the warp, a little blur, black level, gain, noise; grey or RGB, 8 or 16 bit."""
    emitted = light**response
    warped = cv2.warpPerspective(emitted.astype(np.float32), _homography(projector), CAMERA, flags=cv2.INTER_LINEAR)
    warped = cv2.GaussianBlur(warped, (0, 0), 0.6)
    signal = 0.05 + 0.8 * warped + rng.normal(0, 0.003, warped.shape)
    if srgb:
        signal = np.where(signal <= 0.0031308, 12.92 * signal, 1.055 * np.clip(signal, 0, 1) ** (1 / 2.4) - 0.055)
    top = 255 if depth == 8 else 65535
    image = np.clip(np.round(signal * top), 0, top).astype(np.uint8 if depth == 8 else np.uint16)
    return np.repeat(image[..., None], 3, axis=2) if channels == 3 else image


def _write(folder: Path, images: list[np.ndarray], names: list[str], projector, *, seed=0, ext=".png", **options):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for light, name in zip(images, names):
        image = _photograph(light, projector, rng, **options)
        path = folder / f"{name}{ext}"
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
        assert cv2.imwrite(str(path), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95] if ext == ".jpg" else [])
        paths.append(path)
    return paths


def _write_config(path: Path, **values) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in values.items():
        fs.write(key, value)
    fs.release()


def _kamino_phase(projector, step) -> list[np.ndarray]:
    """phase_shifting.py gen W H STEP: 2 column sets (period STEP/3, STEP/2), 2 row sets,
    OpenCV Gray code of int(STEP/2)-px cells (columns then rows, pairs, MSB first), white, black."""
    out = []
    for axis in ("columns", "rows"):
        for period in (step / 3, step / 2):
            out += [_sine(axis, projector, period, 2 * np.pi * (k - 2) / 3) for k in (1, 2, 3)]
    cell = int(step / 2)
    for axis, size in (("columns", projector[0]), ("rows", projector[1])):
        bits = math.ceil(math.log2(int((size - 1) / cell) + 1))
        out += [_gray(axis, projector, cell, b, bits, inverse=inv) for b in range(bits) for inv in (False, True)]
    return out + [_flat(projector, 1), _flat(projector, 0)]


def _kamino_gamma(projector, step, g1, g2) -> list[np.ndarray]:
    """gamma_correction.py gen W H G1 G2 -step S (rows truncated to 8 bits, as the tool does)."""
    period = int(projector[0] / 8)
    out = []
    for axis, rounding in (("columns", np.rint), ("rows", np.floor)):
        for g in (g1, g2):
            out += [_sine(axis, projector, period, 2 * np.pi * (k - 2) / 3, power=1 / g, rounding=rounding)
                    for k in (1, 2, 3)]
    for axis, size in (("columns", projector[0]), ("rows", projector[1])):
        bits = math.ceil(math.log2(int((size - 1) / step) + 1))
        out += [_gray(axis, projector, step, b, bits, inverse=inv) for b in range(bits) for inv in (False, True)]
    return out + [_flat(projector, 1), _flat(projector, 0)]


def _errors(session, projector, **options):
    """(column RMS, row RMS or None, share of the inside pixels decoded, the result)."""
    result = decode_phase(session, session.views[0], **options)
    u, v, inside = _truth(projector)
    m = inside & np.isfinite(result.column)
    col = float(np.sqrt(np.mean((result.column[m] - u[m]) ** 2)))
    row = None if result.row is None else float(np.sqrt(np.mean((result.row[m] - v[m]) ** 2)))
    return col, row, m.sum() / inside.sum(), result


# --- presets ----------------------------------------------------------------------------------


KAMINO_PROJECTOR = (200, 120)


def _kamino_folder(root: Path, **options) -> Path:
    images = _kamino_phase(KAMINO_PROJECTOR, 40)
    _write(root, images, [f"pat{i:02d}" for i in range(len(images))], KAMINO_PROJECTOR, **options)
    _write_config(root / "config.xml", disp_width=KAMINO_PROJECTOR[0], disp_height=KAMINO_PROJECTOR[1], step=40)
    cv2.imwrite(str(root / "color.png"), np.zeros((CAMERA[1], CAMERA[0], 3), np.uint8))  # not a capture
    return root


def test_kamino410_phase_preset_imports_and_decodes_to_truth(tmp_path: Path):
    src = _kamino_folder(tmp_path / "object1")
    calls = []
    session = import_phase(src, tmp_path / "o1", preset="kamino410-phase", progress=lambda d, t: calls.append(d))
    assert session.projector_size == KAMINO_PROJECTOR and session.camera_size == CAMERA
    assert (session.channels, session.bit_depth, session.lossy, session.response) == (1, 8, False, "linear")
    assert session.device["tool"] == "kamino410/phase-shifting" and session.device["preset"] == "kamino410-phase"
    assert calls[-1] == 12 + 2 * (4 + 3) + 2  # 10 column cells of 20 px: 4 bits; 6 row cells: 3 bits
    view = load_session(tmp_path / "o1").views[0]
    assert view.image_for("phase-col-p0-s0").file == "00_phase-col-p0-s0.png"
    assert view.image_for("phase-row-gray-02-inv").file == "25_phase-row-gray-02-inv.png"
    assert view.image_for("white").file == "26_white.png"
    fringe = session.pattern("phase-col-p0-s1").params
    assert fringe["period"] == pytest.approx(40 / 3) and fringe["shift"] == pytest.approx(0.0)
    assert session.pattern("phase-col-p1-s0").params["shift"] == pytest.approx(-2 * np.pi / 3)
    for rec in view.images:  # byte for byte
        original = src / f"pat{int(rec.file[:2]):02d}.png"
        assert (tmp_path / "o1" / view.name / rec.file).read_bytes() == original.read_bytes()
    col, row, share, result = _errors(session, KAMINO_PROJECTOR)
    assert share > 0.95 and col < 0.08 and row < 0.08, (share, col, row)
    assert result.projector_gamma == 1.0  # a linear rig: nothing to correct


def test_kamino410_gamma_preset_describes_the_predistortion(tmp_path: Path):
    projector = (240, 160)
    images = _kamino_gamma(projector, 2, 0.75, 1.25)
    src = tmp_path / "gamma_correction"
    _write(src, images, [f"pat{i:02d}" for i in range(len(images))], projector, response=1.6)
    _write_config(src / "config.xml", disp_width=240, disp_height=160, gamma_p1=0.75, gamma_p2=1.25, step=2)
    session = import_phase(src, tmp_path / "g", preset="kamino410-gamma")
    assert len(images) == 12 + 2 * (7 + 7) + 2 and session.projector_size == projector
    first, second = session.pattern("phase-col-p0-s0").params, session.pattern("phase-col-p1-s0").params
    assert (first["period"], first["gamma"], second["gamma"]) == (30.0, 0.75, 1.25)
    assert session.pattern("phase-col-gray-06").params["cell"] == 2.0
    col, row, share, result = _errors(session, projector)
    assert result.projector_gamma == pytest.approx(1.6, abs=0.15)  # the rig's, through both pre-distortions
    assert share > 0.9 and col < 0.15 and row < 0.25, (share, col, row)
    raw, _, _, _ = _errors(session, projector, projector_gamma=None)
    assert raw > 2 * col


def test_opencv_sinusoidal_rgb_jpeg(tmp_path: Path):
    """SinusoidalPattern's 3 images (sin form, shifts 0, 2 pi/3, 4 pi/3, period width // 20),
    then GrayCodePattern column pairs of one-period cells, white and black; an sRGB JPEG camera,
    RGB, numbered without padding (natural order)."""
    projector = (200, 150)
    period = 200 // 20
    images = [_sine("columns", projector, period, i * 2 * np.pi / 3, form="sin") for i in range(3)]
    images += [_gray("columns", projector, period, b, 5, inverse=inv) for b in range(5) for inv in (False, True)]
    images += [_flat(projector, 1), _flat(projector, 0)]
    _write(tmp_path / "shots", images, [f"img{i}" for i in range(len(images))], projector, ext=".jpg",
           channels=3, srgb=True)
    session = import_phase(tmp_path / "shots", tmp_path / "s", preset="opencv-sinusoidal", projector_size=projector)
    assert (session.channels, session.lossy, session.response) == (3, True, "srgb")
    assert session.view(session.views[0].name).image_for("phase-col-p0-s2").file == "02_phase-col-p0-s2.jpg"
    col, row, share, _ = _errors(session, projector)
    assert row is None and share > 0.9 and col < 0.15, (share, col)


def test_preset_projector_and_shift_conventions():
    assert set(PRESETS) == {"kamino410-phase", "kamino410-gamma", "opencv-sinusoidal"}
    slots = parse_phase_order("white,black,cols:sine:count=20:steps=3:sin,cols:gray").slots((800, 600))
    shifts = [s.desc.params["shift"] for s in slots if s.kind == "sine"]
    assert slots[2].desc.params["period"] == 40.0
    assert np.allclose(shifts, [-np.pi / 2, 2 * np.pi / 3 - np.pi / 2, 4 * np.pi / 3 - np.pi / 2])


# --- order specs ------------------------------------------------------------------------------


def test_order_spec_decreasing_lsb_split_complementary_16bit_tiff(tmp_path: Path):
    """Decreasing phase, a first shift of 90 degrees, Gray code split and least significant
    first with its complementary bit, rows with explicit shifts and plain Gray code, a
    skipped frame; 16-bit grey TIFF."""
    projector = (128, 96)
    seq = [_flat(projector, 0), _flat(projector, 1), _flat(projector, 0.5)]
    seq += [_sine("columns", projector, 16, np.radians(90 + 90 * k), sign=-1) for k in range(4)]
    seq += [_gray("columns", projector, 16, b, 3) for b in (2, 1, 0)]
    seq += [_gray("columns", projector, 16, b, 3, inverse=True) for b in (2, 1, 0)]
    seq += [_gray("columns", projector, 8, 3, 4, inverse=inv) for inv in (False, True)]
    seq += [_sine("rows", projector, 12, np.radians(d)) for d in (10, 100, 190, 280)]
    seq += [_gray("rows", projector, 12, b, 3) for b in range(3)] + [_gray("rows", projector, 6, 3, 4)]
    order = ("black,white,skip,cols:sine:period=16:steps=4:shift=90:decreasing,cols:gray:cell=16:split:lsb,"
             "cols:comp:pairs,rows:sine:period=12:shifts=10/100/190/280,rows:gray:plain,rows:comp:plain")
    assert is_phase_order(order) and not is_phase_order("white,black,cols:10:pairs")
    _write(tmp_path / "set", seq, [f"frame_{i:03d}" for i in range(len(seq))], projector, ext=".tif", depth=16)
    session = import_phase(tmp_path / "set", tmp_path / "s", order=order, projector_size=projector)
    assert (session.bit_depth, session.lossy) == (16, False) and session.device["order"] == order
    assert len(session.views[0].images) == len(seq) - 1
    comp = session.pattern("phase-col-gray-03-inv").params
    assert comp["complementary"] and comp["cell"] == 8.0 and comp["bits"] == 4
    col, row, share, result = _errors(session, projector)
    assert result.axes["columns"].method == "complementary"
    assert share > 0.9 and col < 0.08 and row < 0.08, (share, col, row)


def test_joint_period_is_the_beat_of_the_beats():
    """16, 17, 18 px repeat together every 2448 px (beats 272 and 306, their beat 2448);
    the periods were once folded in one by one (19 px), which refused every heterodyne set."""
    assert joint_period((16, 17, 18)) == pytest.approx(2448)
    assert joint_period((18, 16, 17)) == pytest.approx(2448)
    assert joint_period((100, 200 / 3)) == pytest.approx(200)
    assert joint_period((20, 20)) == math.inf


def test_order_spec_heterodyne_rgb_16bit_png_and_bmp(tmp_path: Path):
    """Three periods and no Gray code (heterodyne); RGB 16-bit PNG; and the same 8-bit as
    BMP, converted to PNG pixel for pixel."""
    projector = (160, 100)
    seq = [_flat(projector, 1), _flat(projector, 0)]
    for period in (16, 17, 18):
        seq += [_sine("columns", projector, period, 2 * np.pi * k / 3) for k in range(3)]
    order = "white,black," + ",".join(f"cols:sine:period={p}:steps=3" for p in (16, 17, 18))
    _write(tmp_path / "png", seq, [f"{i}" for i in range(len(seq))], projector, channels=3, depth=16)
    session = import_phase(tmp_path / "png", tmp_path / "s", order=order, projector_size=projector)
    assert (session.channels, session.bit_depth) == (3, 16)
    col, _, share, result = _errors(session, projector)
    assert result.axes["columns"].method == "heterodyne" and share > 0.9 and col < 0.08, (share, col)
    paths = _write(tmp_path / "bmp", seq, [f"{i}" for i in range(len(seq))], projector, ext=".bmp")
    session = import_phase(tmp_path / "bmp", tmp_path / "b", order=order, projector_size=projector)
    view = session.views[0]
    rec = view.image_for("phase-col-p2-s1")
    assert rec.file == "09_phase-col-p2-s1.png"  # white, black, then periods 16, 17, 18 in file order
    assert np.array_equal(session.read_image(view, rec), cv2.imread(str(paths[9]), cv2.IMREAD_UNCHANGED))
    col, _, share, _ = _errors(session, projector)
    assert share > 0.9 and col < 0.08


def test_decode_command_writes_float_tiff_codes(tmp_path: Path, capsys):
    """``slscan import`` then ``slscan decode`` (no calibration: codes only) of a synthetic
    kamino410 set; the float maps read back equal the decoder's to float32 precision."""
    src = _kamino_folder(tmp_path / "object1")
    assert main(["import", str(src), "--out", str(tmp_path / "o1"), "--preset", "kamino410-phase", "--quiet"]) == 0
    assert main(["decode", str(tmp_path / "o1"), "--out", str(tmp_path / "codes"), "--quiet"]) == 0
    assert "columns.tiff" in capsys.readouterr().err
    manifest = json.loads((tmp_path / "codes" / "projector_codes.json").read_text())
    assert manifest["encoding"] == FLOAT_ENCODING and manifest["invalid"] == "NaN"
    codes = read_codes(tmp_path / "codes")
    assert codes.column.dtype == np.float32 and sorted(p.name for p in (tmp_path / "codes" / "object1").iterdir()) \
        == ["codes.json", "columns.tiff", "mask.png", "rows.tiff"]
    result = decode_phase(load_session(tmp_path / "o1"), "object1")
    assert np.array_equal(np.isnan(codes.column), np.isnan(result.column))
    assert np.allclose(codes.column, result.column, atol=1e-4, equal_nan=True)
    assert np.array_equal(codes.mask, result.mask)


# --- bad input --------------------------------------------------------------------------------


def _fail(tmp_path: Path, message: str, src: Path | None = None, **options) -> None:
    out = tmp_path / "bad-session"
    with pytest.raises(SlscanError, match=message):
        import_phase(src or tmp_path / "object1", out, **options)
    assert not out.exists() and not list(tmp_path.glob(".bad-session*"))  # nothing half-written


def test_a_missing_image_is_named_with_what_it_shows(tmp_path: Path):
    src = _kamino_folder(tmp_path / "object1")
    (src / "pat04.png").unlink()
    _fail(tmp_path, r"pat04\.png: image not found; expected the column fringe of period 20 px, step 2 of 3 "
                    r"\(position 4 of the order", preset="kamino410-phase")


def test_a_missing_complementary_partner_is_named(tmp_path: Path):
    projector = (64, 32)
    seq = [_flat(projector, 1), _flat(projector, 0)] + [_sine("columns", projector, 16, k) for k in range(3)]
    seq += [_gray("columns", projector, 16, b, 2, inverse=inv) for b in range(2) for inv in (False, True)]
    seq += [_gray("columns", projector, 8, 2, 3, inverse=inv) for inv in (False, True)]
    paths = _write(tmp_path / "object1", seq, [f"im{i:02d}" for i in range(len(seq))], projector)
    paths[-1].unlink()
    order = "white,black,cols:sine:period=16:shifts=0/57.3/114.6,cols:gray,cols:comp"
    _fail(tmp_path, r"im10\.png: image not found; expected the inverse of the complementary column Gray bit 2",
          order=order, projector_size=projector)


@pytest.mark.parametrize(("order", "message"), [
    ("white,black,cols:sine:period=300:steps=3,cols:gray", r"period=300 px does not fit the projector's 200 px"),
    ("white,black,cols:sine:count=100:steps=3,cols:gray", r"count=100 fringes .* leaves 2 px per fringe"),
    ("white,black,cols:sine:period=20:steps=3,cols:gray:bits=2", r"2 column Gray bits of 20 px cells cover 80 px"),
    ("white,black,cols:sine:period=20:shifts=0/120,cols:gray", r"2 phase step\(s\); .* needs at least 3"),
    ("white,black,cols:sine:period=20:shifts=0/120/360,cols:gray", r"repeats a phase shift"),
    ("white,black,cols:sine:period=20:steps=3", r"no way to unwrap the phase"),
    ("white,black,cols:sine:period=20:steps=3,cols:sine:period=40:steps=3", r"repeat together every 40 px"),
    ("white,black,cols:sine:period=20:steps=3,cols:gray:cell=15", r"cannot unwrap fringes of 20 px"),
    ("white,black,cols:sine:period=20:steps=3,cols:comp", r"cols:comp without cols:gray"),
    ("white,black,cols:sine:period=20:steps=3,cols:gray:plain,cols:comp:pairs", r"needs its inverse exactly"),
    ("white,black,cols:sine:period=20:steps=3,cols:comp:split,cols:gray", r"one image or a pair"),
    ("white,black,cols:sine:steps=3,cols:gray", r"needs period=LEN .* or count=N"),
    ("white,black,cols:sine:period=20,cols:gray", r"needs steps=N"),
    ("white,black,cols:sine:period=x:steps=3", r"period='x' is not a number"),
    ("white,black,cols:sine:period=20:steps=3:steps=4", r"bad or repeated option 'steps=4'"),
    ("white,black,cols:sine:period=20:steps=3:gamma=9,cols:gray", r"gamma=9; expected 0.2 .. 5"),
    ("white,black,cols:sine:period=20:steps=3,cols:gray,cols:gray", r"'cols:gray' appears twice"),
    ("white,black,cols:10:pairs", r"unknown item 'cols:10:pairs'"),
    ("white,black,rows:sine:period=20:steps=3,rows:gray", r"no 'cols:sine'"),
    ("black,cols:sine:period=20:steps=3,cols:gray", r"no 'white'"),
])
def test_bad_orders_are_one_line_naming_the_option(tmp_path: Path, order: str, message: str):
    projector = (200, 120)
    (tmp_path / "object1").mkdir()
    cv2.imwrite(str(tmp_path / "object1" / "a0.png"), np.zeros((8, 8), np.uint8))
    with pytest.raises(SlscanError, match=message) as exc:
        parse_phase_order(order).slots(projector)
    assert "\n" not in str(exc.value)
    _fail(tmp_path, message, order=order, projector_size=projector)


def test_wrong_counts_and_extra_images(tmp_path: Path):
    src = _kamino_folder(tmp_path / "object1")
    cv2.imwrite(str(src / "pat28.png"), np.zeros((CAMERA[1], CAMERA[0]), np.uint8))
    _fail(tmp_path, r"pat28\.png: unexpected image \(found 29\); expected 28 images pat00\.png … pat27\.png",
          preset="kamino410-phase")
    names = ["white", "black", "one", "two", "three", "gray0", "gray0i", "gray1", "gray1i", "gray2", "gray2i", "gray3"]  # no numbering
    other = tmp_path / "named"
    _write(other, [_flat(KAMINO_PROJECTOR, 1)] * len(names), names, KAMINO_PROJECTOR)
    _fail(tmp_path, r"named: found 12 images, the order .* needs 13 images \(white, black, 3 column fringes of 20 "
                    r"px, 8 column Gray\); the file names carry no common numbering", src=other,
          order="white,black,cols:sine:period=20:steps=3,cols:gray", projector_size=KAMINO_PROJECTOR)


def test_images_of_different_sizes_name_both(tmp_path: Path):
    src = _kamino_folder(tmp_path / "object1")
    cv2.imwrite(str(src / "pat07.png"), np.zeros((CAMERA[1], CAMERA[0] - 2), np.uint8))
    _fail(tmp_path, r"pat07\.png: image is 238x180, 1 channel\(s\), 8-bit; expected 240x180, .* like .*pat00\.png",
          preset="kamino410-phase")


def test_config_file_problems_are_named(tmp_path: Path):
    src = _kamino_folder(tmp_path / "object1")
    _fail(tmp_path, r"config\.xml: no number gamma_p1, gamma_p2; expected disp_width", preset="kamino410-gamma")
    (src / "config.xml").unlink()
    _fail(tmp_path, r"object1/config\.xml: not found; expected the tool's settings \(disp_width, disp_height, step\)",
          preset="kamino410-phase")
    (src / "config.xml").write_text("not xml")
    _fail(tmp_path, r"config\.xml: not a readable OpenCV FileStorage file", preset="kamino410-phase")


def test_other_bad_options(tmp_path: Path):
    _kamino_folder(tmp_path / "object1")
    _fail(tmp_path, r"unknown phase-shifting preset 'kamino'; expected one of kamino410-phase", preset="kamino")
    _fail(tmp_path, r"either a phase-shifting preset or an order spec", preset="kamino410-phase", order="white")
    _fail(tmp_path, r"rotation 45 is not one of", preset="kamino410-phase", rotation=45)
    with pytest.raises(SlscanError, match="must be written outside the source"):
        import_phase(tmp_path / "object1", tmp_path / "object1", preset="kamino410-phase", overwrite=True)
    assert (tmp_path / "object1" / "pat00.png").is_file()


def test_cli_refusals_are_one_line_and_non_zero(tmp_path: Path, capsys):
    src = _kamino_folder(tmp_path / "object1")
    (src / "pat04.png").unlink()
    assert main(["import", str(src), "--out", str(tmp_path / "s"), "--preset", "kamino410-phase", "--quiet"]) != 0
    err = capsys.readouterr().err.strip()
    assert "pat04.png: image not found" in err and len(err.splitlines()) == 1
    assert main(["import", str(src), "--out", str(tmp_path / "s"), "--preset", "kamino410-phase",
                 "--missing-bits", "drop", "--quiet"]) != 0
    assert "--missing-bits: only with --format graycode" in capsys.readouterr().err
    assert main(["import", str(src), "--out", str(tmp_path / "s"), "--format", "graycode",
                 "--preset", "kamino410-phase", "--quiet"]) != 0
    assert "is a phase preset; --format graycode takes" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


# --- the real captures --------------------------------------------------------------------------


def test_kamino410_phase_captures_import_and_decode(shared_data: Path, tmp_path: Path, capsys):
    src = shared_data / "phaseshift_kamino410" / "sample_data" / "object1"
    if not src.is_dir():
        pytest.skip(f"kamino410 phase-shifting captures not found at {src}")
    out = tmp_path / "o1"
    assert main(["import", str(src), "--out", str(out), "--preset", "kamino410-phase", "--quiet"]) == 0
    session = load_session(out)
    assert session.projector_size == (1920, 1080) and session.camera_size == (1936, 1216)
    assert len(session.views[0].images) == 32  # color.png is not a capture
    assert main(["decode", str(out), "--out", str(tmp_path / "codes"), "--quiet"]) == 0
    capsys.readouterr()
    codes = read_codes(tmp_path / "codes")
    assert 0.45 < codes.valid_share.decoded < 0.75  # measured 0.558: sponges and backdrop, not the shadows
    col = codes.column[codes.mask]
    assert np.nanmin(col) >= -0.5 and np.nanmax(col) <= 1919.5
    # the projector column grows to the right along camera rows (no mirror): 0.86 px per px
    steps = np.diff(codes.column, axis=1)
    assert 0.6 < float(np.nanmedian(steps)) < 1.2


def test_sub_folders_of_another_layout_are_skipped_and_named(tmp_path: Path, caplog):
    """A folder of kamino410 folders (two objects and a gamma set, as the tool's sample_data):
    the phase preset takes the objects as views and names the gamma set it skips."""
    _kamino_folder(tmp_path / "data" / "object1")
    _kamino_folder(tmp_path / "data" / "object2", seed=1)
    gamma = tmp_path / "data" / "gamma_correction"
    images = _kamino_gamma(KAMINO_PROJECTOR, 2, 0.75, 1.25)
    _write(gamma, images, [f"pat{i:02d}" for i in range(len(images))], KAMINO_PROJECTOR)
    _write_config(gamma / "config.xml", disp_width=200, disp_height=120, gamma_p1=0.75, gamma_p2=1.25, step=2)
    with caplog.at_level("WARNING"):
        session = import_phase(tmp_path / "data", tmp_path / "s", preset="kamino410-phase")
    assert [v.name for v in session.views] == ["object1", "object2"]
    assert "1 sub-folder(s) skipped" in caplog.text and "gamma_correction/ (period=0.666667 px does not fit" \
        in caplog.text
    session = import_phase(tmp_path / "data", tmp_path / "g", preset="kamino410-gamma")
    assert [v.name for v in session.views] == ["gamma_correction"]
    (tmp_path / "data" / "object2" / "config.xml").write_text((tmp_path / "data" / "object2" / "config.xml")
                                                              .read_text().replace(">40<", ">42<"))  # same count
    with pytest.raises(SlscanError, match=r"object2: its images show order .* expected one pattern set"):
        import_phase(tmp_path / "data", tmp_path / "x", preset="kamino410-phase")
