"""Tests for the Gray-code folder importer: synthetic captures in each preset's layout
(a known homography from projector to camera, rotated or not, PNG and JPEG), decoded back
to the warp's truth; bad input; the kamino410 real data through both import paths."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from slscan.capture.graycode_import import PRESETS, Slot, import_graycode, parse_order
from slscan.capture.kamino410 import import_kamino410
from slscan.capture.session import load_session
from slscan.decode.graycode import decode_gray
from slscan.errors import SlscanError
from slscan.patterns import PatternImage, flat, graycode, render

PROJECTOR = (64, 32)  # 6 column bits, 5 row bits: 24 images with white and black
CAMERA = (200, 150)
WHITE, BLACK = flat.generate(*PROJECTOR)
GRAY = graycode.generate(*PROJECTOR, rows=True)  # column then row pairs, MSB first

# each preset's projection order, written out here independently of the importer
SEQUENCES = {
    "opencv": GRAY + [WHITE, BLACK],
    "kamino410": GRAY + [WHITE, BLACK],
    "3dunderworld": [WHITE, BLACK] + GRAY,
}


def _homography(rotated: bool) -> np.ndarray:
    """Camera-from-projector homography (OpenCV pixel-centre coordinates): the projector
    image lands as a slanted quadrilateral inside the camera image, turned 90 degrees
    (columns horizontal) when ``rotated``."""
    pw, ph = PROJECTOR
    src = np.float32([[-0.5, -0.5], [pw - 0.5, -0.5], [pw - 0.5, ph - 0.5], [-0.5, ph - 0.5]])
    if rotated:  # projector x runs down the camera image, projector y right to left
        dst = np.float32([[165, 12], [170, 140], [40, 132], [36, 18]])
    else:
        dst = np.float32([[18, 30], [185, 20], [180, 128], [22, 118]])
    return cv2.getPerspectiveTransform(src, dst)


def _truth(rotated: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True projector column and row (int) of each camera pixel centre, and where inside."""
    h = np.linalg.inv(_homography(rotated))
    ys, xs = np.mgrid[0 : CAMERA[1], 0 : CAMERA[0]].astype(np.float64)
    p = h @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)])
    u, v = (p[:2] / p[2]).reshape(2, *xs.shape)
    col, row = np.floor(u + 0.5).astype(int), np.floor(v + 0.5).astype(int)
    inside = (col >= 0) & (col < PROJECTOR[0]) & (row >= 0) & (row < PROJECTOR[1])
    return col, row, inside


def _photograph(desc: PatternImage, rotated: bool, rng: np.random.Generator) -> np.ndarray:
    """What the camera sees of ``desc``: warped, blurred, black level, gain, noise (grey uint8)."""
    lit = render(desc)[..., 0].astype(np.float32) / 255
    warped = cv2.warpPerspective(lit, _homography(rotated), CAMERA, flags=cv2.INTER_LINEAR)
    warped = cv2.GaussianBlur(warped, (0, 0), 0.7)
    image = 25 + 190 * warped + rng.normal(0, 1.0, warped.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def _write_view(folder: Path, sequence: list[PatternImage], names: list[str], rotated: bool, ext: str,
                seed: int = 0) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for desc, name in zip(sequence, names):
        path = folder / f"{name}{ext}"
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if ext == ".jpg" else []
        assert cv2.imwrite(str(path), _photograph(desc, rotated, rng), params)
        paths.append(path)
    return paths


def _preset_folder(root: Path, preset: str, ext: str, rotated: bool) -> Path:
    """Captures in ``preset``'s layout and naming under ``root``; returns the import source."""
    seq = SEQUENCES[preset]
    n = len(seq)
    if preset == "kamino410":
        for k in (0, 1):
            _write_view(root / f"capture_{k}", seq, [f"graycode_{i:02d}" for i in range(n)], rotated, ext, k)
        return root
    if preset == "3dunderworld":
        _write_view(root / "dataset1", seq, [f"{i:04d}" for i in range(n)], rotated, ext)
        return root / "dataset1"
    # opencv: unpadded numbers, so only a natural sort gets the order right
    _write_view(root / "shots", seq, [f"pattern_{i}" for i in range(n)], rotated, ext)
    return root / "shots"


def _check_decoded(session, rotated: bool, *, exact: float, valid: float) -> None:
    col, row, inside = _truth(rotated)
    for view in session.views:
        res = decode_gray(session, view)
        # light reaches half a projector pixel (interpolation) and a camera pixel (blur) beyond
        edge = (col >= -1) & (col <= PROJECTOR[0]) & (row >= -1) & (row <= PROJECTOR[1])
        near = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert not (res.mask & ~near).any()
        m = res.mask & inside
        assert m.sum() >= valid * inside.sum(), (view.name, m.sum(), inside.sum())
        assert np.mean(res.column[m] == col[m]) >= exact
        assert np.mean(res.row[m] == row[m]) >= exact
        assert np.mean(np.abs(res.column[m] - col[m]) <= 1) >= 0.995
        assert np.mean(np.abs(res.row[m] - row[m]) <= 1) >= 0.995
        # stripe edges at (nearly) every column boundary, searched across the stripes: along
        # camera columns when the projector is turned (its column stripes run across the image)
        edges = res.edges
        assert len(np.unique(edges.stripe)) >= PROJECTOR[0] - 3
        across = 0.0 if edges.along_columns is None else float(np.mean(edges.along_columns))
        assert across > 0.95 if rotated else across < 0.05


# --- each preset, rotated and not, PNG and JPEG -----------------------------------------------


@pytest.mark.parametrize("ext", [".png", ".jpg"])
@pytest.mark.parametrize(
    ("preset", "rotation"), [("opencv", None), ("opencv", 90), ("kamino410", None), ("3dunderworld", None)]
)
def test_preset_layout_imports_and_decodes_to_truth(tmp_path: Path, preset: str, rotation, ext: str):
    rotated = (rotation or PRESETS[preset].rotation) in (90, 270)
    src = _preset_folder(tmp_path / "src", preset, ext, rotated)
    out = tmp_path / "session"
    calls = []
    import_graycode(src, out, preset=preset, projector_size=PROJECTOR, rotation=rotation,
                    progress=lambda d, t: calls.append((d, t)))
    session = load_session(out)
    assert session.lossy == (ext == ".jpg")
    assert session.projector_rotation == (90 if rotated else 0)
    assert session.camera_axis("columns") == ("y" if rotated else "x")
    assert session.camera_size == CAMERA and (session.channels, session.bit_depth) == (1, 8)
    assert [p.id for p in session.patterns] == [p.id for p in [WHITE, BLACK] + GRAY]
    assert calls[-1] == (24 * len(session.views),) * 2
    view = session.views[0]
    assert all(rec.file.endswith(ext) for rec in view.images)
    first = sorted(p for p in (src if preset != "kamino410" else src / "capture_0").iterdir())
    assert {session.image_path(view, r).read_bytes() for r in view.images} == {p.read_bytes() for p in first}
    if ext == ".png":
        _check_decoded(session, rotated, exact=0.97, valid=0.7)
    else:
        _check_decoded(session, rotated, exact=0.95, valid=0.6)


def test_custom_order_lsb_split(tmp_path: Path):
    """An order of no preset: black first, column patterns then their inverses, least
    significant bit first; rows as pairs; a skipped frame."""
    col = [g for g in GRAY if g.axis == "columns"]
    patterns = [g for g in col if not g.params["inverse"]][::-1]
    inverses = [g for g in col if g.params["inverse"]][::-1]
    rows = [g for g in GRAY if g.axis == "rows"]
    seq = [BLACK, WHITE, *patterns, *inverses, WHITE, *rows]  # the second white is skipped
    _write_view(tmp_path / "set", seq, [f"img{i}" for i in range(len(seq))], False, ".png")
    out = tmp_path / "session"
    import_graycode(tmp_path / "set", out, order="black,white,cols:6:split:lsb,skip,rows:pairs",
                    projector_size=PROJECTOR)
    session = load_session(out)
    assert len(session.views[0].images) == 24
    assert session.views[0].image_for("gray-col-05").file == "02_gray-col-05.png"
    assert session.device["order"] == "black,white,cols:6:split:lsb,skip,rows:pairs"
    _check_decoded(session, False, exact=0.97, valid=0.7)


def test_plain_patterns_are_described_without_inverses():
    slots = parse_order("white,black,cols:3:plain:lsb").slots((8, 8))
    assert slots[2:] == [Slot("gray", "columns", b, 3, False) for b in (2, 1, 0)]


# --- sets with missing bits ---------------------------------------------------------------------


def _underworld(tmp_path: Path, ext: str = ".png") -> Path:
    return _preset_folder(tmp_path / "src", "3dunderworld", ext, True)


def test_missing_images_are_named(tmp_path: Path):
    src = _underworld(tmp_path)
    (src / "0013.png").unlink()
    with pytest.raises(SlscanError, match=r"0013\.png: image not found \(1 missing.*found 23.*needs 24.*--missing-bits"):
        import_graycode(src, tmp_path / "session", preset="3dunderworld", projector_size=PROJECTOR)
    assert not (tmp_path / "session").exists()


def test_missing_bits_dropped_are_recorded(tmp_path: Path):
    src = _underworld(tmp_path)
    for k in (13, 22, 23):  # column bit 5 (LSB) inverse; row bit 4 (LSB) pair
        (src / f"{k:04d}.png").unlink()
    out = tmp_path / "session"
    import_graycode(src, out, preset="3dunderworld", projector_size=PROJECTOR, missing_bits="drop")
    session = load_session(out)
    gray = [p for p in session.patterns if p.family == "gray"]
    cols = [p.params["bit"] for p in gray if p.axis == "columns" and not p.params["inverse"]]
    rows = [p.params["bit"] for p in gray if p.axis == "rows" and not p.params["inverse"]]
    assert cols == [0, 1, 2, 3, 4] and rows == [0, 1, 2, 3]
    assert {p.params["bits"] for p in gray if p.axis == "columns"} == {6}
    assert {p.params["bits"] for p in gray if p.axis == "rows"} == {5}
    assert session.device["missing_bits"] == {
        "columns": {"bits": 6, "kept": 5, "missing": [5]}, "rows": {"bits": 5, "kept": 4, "missing": [4]},
    }
    assert len(session.views[0].images) == 2 + 10 + 8  # image 12 (column bit 5) left out too
    # the decoder reads the bits kept as a coarser code: the centre of each block of 2
    res = decode_gray(session, session.views[0])
    assert res.bits_used is not None
    col, row, inside = _truth(True)
    m = res.mask & inside
    assert m.mean() > 0.3
    assert np.mean(res.column[m] // 2 == col[m] // 2) > 0.95
    assert np.mean(res.row[m] // 2 == row[m] // 2) > 0.95
    assert np.mean(np.abs(res.column[m] - col[m]) <= 1) > 0.99
    # edges only between blocks: boundaries c | c + 1 with c = 2 k + 1 (planes u = c + 0.5)
    assert len(res.edges) > 0 and np.all((res.edges.projector_column - 0.5) % 2 == 1)


def _camera_folder(tmp_path: Path, ext: str = ".jpg") -> Path:
    """``cam/dataset1/`` (a view, 3dunderworld layout), ``cam/calib/`` (12 chessboard
    photographs numbered like the captures), ``cam/notes/`` (no images)."""
    cam = tmp_path / "cam"
    _preset_folder(cam, "3dunderworld", ext, True)
    (cam / "calib").mkdir()
    rng = np.random.default_rng(5)
    for i in range(12):
        board = np.kron((np.indices((15, 20)).sum(axis=0) % 2) * 200 + 20, np.ones((10, 10))).astype(np.uint8)
        assert cv2.imwrite(str(cam / "calib" / f"{i:04d}{ext}"), np.roll(board, rng.integers(0, 9), axis=1))
    (cam / "notes").mkdir()
    (cam / "notes" / "readme.txt").write_text("board 9x7, 20 mm")
    return cam


@pytest.mark.parametrize("missing_bits", ["error", "drop"])
def test_sub_folders_that_are_not_views_are_skipped(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                    missing_bits: str):
    cam = _camera_folder(tmp_path)
    with caplog.at_level(logging.WARNING, logger="slscan.capture.graycode_import"):
        session = import_graycode(cam, tmp_path / "session", preset="3dunderworld", projector_size=PROJECTOR,
                                  missing_bits=missing_bits)
    assert [v.name for v in session.views] == ["dataset1"]
    assert "missing_bits" not in session.device  # the board images took nothing from the view
    skipped = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(skipped) == 1 and "1 sub-folder(s) skipped" in skipped[0] and "calib/ (12 images" in skipped[0]
    assert "dataset1" not in skipped[0] and "notes" not in skipped[0]
    _check_decoded(load_session(session.root), True, exact=0.97, valid=0.6)
    # a second real view is kept
    _write_view(cam / "dataset2", SEQUENCES["3dunderworld"], [f"{i:04d}" for i in range(24)], True, ".jpg", 3)
    session = import_graycode(cam, tmp_path / "two", preset="3dunderworld", projector_size=PROJECTOR)
    assert [v.name for v in session.views] == ["dataset1", "dataset2"]


def test_no_sub_folder_that_fits_is_an_error_naming_one(tmp_path: Path):
    cam = _camera_folder(tmp_path)
    shutil.rmtree(cam / "dataset1")
    with pytest.raises(SlscanError, match=r"calib.*0012\.jpg: image not found \(12 missing"):
        import_graycode(cam, tmp_path / "session", preset="3dunderworld", projector_size=PROJECTOR)
    assert not (tmp_path / "session").exists()


def test_missing_white_cannot_be_dropped(tmp_path: Path):
    src = _underworld(tmp_path)
    (src / "0001.png").unlink()
    with pytest.raises(SlscanError, match="the black image.*missing"):
        import_graycode(src, tmp_path / "s", preset="3dunderworld", projector_size=PROJECTOR, missing_bits="drop")


def test_missing_images_in_unnumbered_names_cannot_be_told(tmp_path: Path):
    seq = SEQUENCES["opencv"][:-1]
    _write_view(tmp_path / "set", seq, [f"shot_{chr(97 + i)}" for i in range(len(seq))], False, ".png")
    with pytest.raises(SlscanError, match=r"set: found 23 images, the order .* needs 24 images "
                                          r"\(12 column, 10 row, white, black\).*cannot be told"):
        import_graycode(tmp_path / "set", tmp_path / "s", preset="opencv", projector_size=PROJECTOR)


# --- bad input ----------------------------------------------------------------------------------


def test_too_many_images(tmp_path: Path):
    src = _underworld(tmp_path)
    shutil.copy(src / "0023.png", src / "0024.png")
    with pytest.raises(SlscanError, match=r"0024\.png: unexpected image \(found 25\); expected 24 images "
                                          r"0000\.png … 0023\.png"):
        import_graycode(src, tmp_path / "s", preset="3dunderworld", projector_size=PROJECTOR)


def test_spec_for_another_projector(tmp_path: Path):
    src = _underworld(tmp_path)
    with pytest.raises(SlscanError, match=r"expected 42 images 0000\.png … 0041\.png.*needs 42"):
        import_graycode(src, tmp_path / "s", preset="3dunderworld")  # 1024 x 768 by default


def test_images_of_different_sizes_name_both(tmp_path: Path):
    src = _underworld(tmp_path)
    cv2.imwrite(str(src / "0005.png"), np.zeros((150, 199), np.uint8))
    with pytest.raises(SlscanError, match=r"0005\.png: image is 199x150.*expected 200x150.*like .*0000\.png"):
        import_graycode(src, tmp_path / "s", preset="3dunderworld", projector_size=PROJECTOR)


def test_folder_mixing_jpeg_and_png(tmp_path: Path):
    src = _underworld(tmp_path)
    image = cv2.imread(str(src / "0009.png"), cv2.IMREAD_UNCHANGED)
    (src / "0009.png").unlink()
    cv2.imwrite(str(src / "0009.jpg"), image)
    with pytest.raises(SlscanError, match=r"src/dataset1: mixes PNG \(0000\.png\) and JPEG \(0009\.jpg\)"):
        import_graycode(src, tmp_path / "s", preset="3dunderworld", projector_size=PROJECTOR)


def test_unknown_preset_lists_the_presets(tmp_path: Path):
    with pytest.raises(SlscanError, match="unknown Gray-code preset 'opencv2'; expected one of "
                                          "opencv, kamino410, 3dunderworld"):
        import_graycode(tmp_path, tmp_path / "s", preset="opencv2")


@pytest.mark.parametrize(
    ("order", "message"),
    [
        ("white,black,cols,rows,grey", "unknown item 'grey'"),
        ("white,cols,rows", "no 'black'"),
        ("white,black,cols:pairs:plain", "bad or repeated option 'plain'"),
        ("white,white,black,cols", "'white' appears twice"),
    ],
)
def test_bad_orders(order: str, message: str):
    with pytest.raises(SlscanError, match=message):
        parse_order(order)


def test_too_few_bits_for_the_projector():
    with pytest.raises(SlscanError, match="5 column bits cannot code 64 projector columns"):
        parse_order("white,black,cols:5").slots(PROJECTOR)


def test_no_images(tmp_path: Path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SlscanError, match="empty: no \\* images"):
        import_graycode(tmp_path / "empty", tmp_path / "s", preset="opencv")


# --- lossy sessions: reading, validation, the decode warning -----------------------------------------


def test_jpeg_session_validation_names_a_wrong_size(tmp_path: Path):
    src = _underworld(tmp_path, ".jpg")
    out = tmp_path / "session"
    import_graycode(src, out, preset="3dunderworld", projector_size=PROJECTOR)
    target = next(out.glob("dataset1/05_*.jpg"))
    cv2.imwrite(str(target), np.zeros((150, 201), np.uint8))
    with pytest.raises(SlscanError, match=rf"{target.name}: image is 201x150, the session's camera is 200x150"):
        load_session(out)
    target.write_bytes(target.read_bytes()[:-400])  # truncated
    with pytest.raises(SlscanError, match=rf"{target.name}: JPEG file is truncated"):
        load_session(out)


def test_old_sessions_load_as_lossless_and_upright(tmp_path: Path):
    src = _underworld(tmp_path)
    out = tmp_path / "session"
    import_graycode(src, out, preset="3dunderworld", projector_size=PROJECTOR, rotation=0)
    meta = json.loads((out / "session.json").read_text())
    del meta["camera"]["lossy"], meta["camera"]["response"], meta["projector"]["rotation"]
    (out / "session.json").write_text(json.dumps(meta))
    session = load_session(out)
    assert session.lossy is False and session.projector_rotation == 0 and session.response == "linear"


def _through_srgb(folder: Path) -> None:
    """Re-save every capture of ``folder`` as a camera applying the sRGB curve would have
    (the synthetic photographs are linear in light)."""
    v = np.arange(256) / 255
    lut = np.round(255 * np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)).astype(np.uint8)
    for path in folder.iterdir():
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix == ".jpg" else []
        assert cv2.imwrite(str(path), lut[cv2.imread(str(path), cv2.IMREAD_UNCHANGED)], params)


@pytest.mark.parametrize(("ext", "tone", "given", "expected"), [
    (".jpg", "linear", None, "linear"), (".jpg", "srgb", None, "srgb"), (".png", "linear", None, "linear"),
    (".png", "srgb", None, "srgb"), (".jpg", "linear", "srgb", "srgb"), (".png", "srgb", "linear", "linear"),
])
def test_the_camera_response_is_measured_not_assumed(tmp_path: Path, ext: str, tone: str, given, expected: str,
                                                     capsys: pytest.CaptureFixture):
    """A JPEG of grey stripes from a linear camera is linear; an sRGB camera's PNG is sRGB;
    ``--response`` overrides, recorded as given beside what was measured."""
    from slscan.cli import main

    src = _underworld(tmp_path, ext)
    if tone == "srgb":
        _through_srgb(src)
    out = tmp_path / "session"
    args = ["import", str(src), "--format", "graycode", "--preset", "3dunderworld", "--projector",
            f"{PROJECTOR[0]}x{PROJECTOR[1]}", "--out", str(out), "--quiet"]
    assert main(args + (["--response", given] if given else [])) == 0
    printed = " ".join("".join(capsys.readouterr()).split())
    session = load_session(out)
    assert session.response == expected
    camera = json.loads((out / "session.json").read_text())["camera"]
    assert camera["response"] == expected
    fit = camera["response_fit"]
    assert fit["response"] == tone and fit["measured"] and fit["views"] == ["dataset1"]
    assert fit["source"] == ("given" if given else "measured")
    assert fit["residuals"][tone] < 0.02 and fit["residuals"]["srgb" if tone == "linear" else "linear"] > 0.2
    said = f"camera response: {expected} (given; the captures measure {tone}" if given else \
        f"camera response: {tone} (measured on dataset1"
    assert said in printed
    assert main(["info", str(out)]) == 0
    assert said in " ".join("".join(capsys.readouterr()).split())
    # what decoding reads: the stored values, or their inverse sRGB as fractions of full scale
    view = session.views[0]
    stored = session.read_image(view, view.images[0])
    linear = session.read_image(view, view.images[0], linear=True)
    if expected == "linear":
        assert linear is stored or np.array_equal(linear, stored)
    else:
        assert linear.dtype == np.float32 and linear.max() <= 1.0
        assert linear[stored == 128].min() == pytest.approx(0.2158605, abs=1e-6)
    _check_decoded(session, True, exact=0.97, valid=0.6)


def test_decode_reads_through_the_response_it_is_given(tmp_path: Path, capsys: pytest.CaptureFixture):
    """``slscan decode --response``: the session read through another curve, said in the
    summary; ``measure`` measures it now (a session imported with the old JPEG default)."""
    from slscan.cli import main

    src = _underworld(tmp_path, ".jpg")
    out = tmp_path / "session"
    import_graycode(src, out, preset="3dunderworld", projector_size=PROJECTOR, response="srgb")
    capsys.readouterr()
    assert main(["decode", str(out), "--out", str(tmp_path / "codes"), "--quiet"]) == 0
    text = " ".join("".join(capsys.readouterr()).split())
    assert "camera response: srgb (given; the captures measure linear" in text and "decoded in linear light" in text
    assert main(["decode", str(out), "--out", str(tmp_path / "codes2"), "--quiet", "--response", "measure"]) == 0
    text = " ".join("".join(capsys.readouterr()).split())
    assert "camera response: linear (measured on dataset1" in text and "decoded as stored" in text
    assert main(["decode", str(out), "--out", str(tmp_path / "codes3"), "--quiet", "--gray-threshold", "opencv"]) == 0
    assert "on the captures as stored (OpenCV's rule)" in " ".join("".join(capsys.readouterr()).split())


def test_a_bad_camera_response_is_named(tmp_path: Path):
    src = _underworld(tmp_path)
    with pytest.raises(SlscanError, match="camera response must be auto or one of linear, srgb, got 'gamma'"):
        import_graycode(src, tmp_path / "s", preset="3dunderworld", projector_size=PROJECTOR, response="gamma")
    import_graycode(src, tmp_path / "ok", preset="3dunderworld", projector_size=PROJECTOR)
    meta = json.loads((tmp_path / "ok" / "session.json").read_text())
    meta["camera"]["response"] = "raw"
    (tmp_path / "ok" / "session.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match=r"session.json: camera.response must be one of linear, srgb, got 'raw'"):
        load_session(tmp_path / "ok")


def test_decode_warns_once_on_lossy_captures(tmp_path: Path, caplog: pytest.LogCaptureFixture):
    from slscan.decode.pipeline import decode_session
    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    config = VirtualCaptureConfig(scene="tile", patterns="gray", camera_scale=0.25, projector_scale=0.25,
                                  lit_images=False, views=2)
    session = capture_session(config, tmp_path / "session")
    meta = json.loads((session.root / "session.json").read_text())
    for view in meta["views"]:
        for rec in view["images"]:
            png = session.root / view["name"] / rec["file"]
            cv2.imwrite(str(png.with_suffix(".jpg")), cv2.imread(str(png), cv2.IMREAD_UNCHANGED),
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
            png.unlink()
            rec["file"] = png.with_suffix(".jpg").name
    meta["camera"]["lossy"] = True
    (session.root / "session.json").write_text(json.dumps(meta))
    lossy = load_session(session.root)
    with caplog.at_level(logging.WARNING, logger="slscan.decode.pipeline"):
        results = decode_session(lossy, tmp_path / "decoded")
    warnings = [r for r in caplog.records if "lossy" in r.getMessage()]
    assert len(warnings) == 1 and len(results) == 2


# --- the kamino410 real captures through both paths ----------------------------------------------


def test_kamino410_preset_equals_the_kamino410_importer(shared_data: Path, tmp_path: Path):
    src = shared_data / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        pytest.skip(f"real data not found: {src}")
    old = import_kamino410(src, tmp_path / "old")
    new = import_graycode(src, tmp_path / "new", preset="kamino410")
    assert [p.to_dict() for p in new.patterns] == [p.to_dict() for p in old.patterns]
    assert [v.to_dict() for v in new.views] == [v.to_dict() for v in old.views]
    old, new = load_session(old.root), load_session(new.root)
    for view in old.views:
        a, b = decode_gray(old, view.name), decode_gray(new, view.name)
        assert a.mask.mean() > 0.2
        for field in ("column", "row", "mask"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), (view.name, field)


def test_info_says_lossy_turned_and_dropped_bits(tmp_path: Path, capsys: pytest.CaptureFixture):
    from slscan.cli import main

    src = _preset_folder(tmp_path / "src", "3dunderworld", ".jpg", True)
    (src / "0023.jpg").unlink()  # row bit 4 (LSB) inverse
    out = tmp_path / "session"
    import_graycode(src, out, preset="3dunderworld", projector_size=PROJECTOR, missing_bits="drop")
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "lossy (JPEG)" in text and "turned 90 deg" in text and "cross camera columns" in text
    assert "rows 4 of 5 kept" in text
