"""Projector codes (``slscan decode --codes``): column/row maps as 16-bit PNG, read back,
streamed to Rerun, written without a calibration; what limited the valid share."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from slscan.capture.session import load_session
from slscan.cli import main
from slscan.data import shared_data_dir
from slscan.decode.codes import INVALID, MANIFEST, ValidShare, read_codes, valid_share
from slscan.decode.graycode import decode_gray
from slscan.errors import SlscanError
from slscan.fsio import read_png
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor


@pytest.fixture(scope="module")
def gray_rows_session(tmp_path_factory):
    """The figurine in Gray code with row codes (half-size camera, quarter-size projector: 2-3
    camera pixels per projector pixel), with sensor noise."""
    config = VirtualCaptureConfig(
        patterns="gray", gray_rows=True, camera_scale=0.5, projector_scale=0.25, views=2,
        lit_images=False,
    )
    return capture_session(config, tmp_path_factory.mktemp("gray_rows") / "session")


def _uncalibrated(session, folder: Path) -> Path:
    """A copy of ``session`` whose session.json has no calibration."""
    shutil.copytree(session.root, folder)
    meta = json.loads((folder / "session.json").read_text())
    meta["calibration"] = None
    (folder / "session.json").write_text(json.dumps(meta))
    return folder


def _entities(rrd: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {chunk.entity_path.strip("/") for chunk in RrdReader(rrd).stream().to_chunks()}


def test_codes_equal_decode_gray_and_match_the_truth(gray_rows_session, tmp_path):
    out = tmp_path / "maps"
    rrd = tmp_path / "decode.rrd"
    assert main(["decode", str(gray_rows_session.root), "--out", str(out), "--codes", "--quiet",
                 "--save", str(rrd)]) == 0
    assert (out / "range_maps.json").is_file() and (out / "view_000.ply").is_file()
    manifest = json.loads((out / MANIFEST).read_text())
    assert [v["view"] for v in manifest["views"]] == ["view_000", "view_001"]
    assert manifest["invalid"] == INVALID
    w, h = gray_rows_session.projector_size
    for view in gray_rows_session.views:
        ref = decode_gray(gray_rows_session, view)
        codes = read_codes(out, view.name)
        np.testing.assert_array_equal(codes.column, ref.column)
        np.testing.assert_array_equal(codes.row, ref.row)
        np.testing.assert_array_equal(codes.mask, ref.mask)
        assert codes.projector_size == (w, h) and codes.bits == (int(np.ceil(np.log2(w))), int(np.ceil(np.log2(h))))
        # the stored files: 16-bit, the sentinel where not decoded, 0/255 mask
        columns = read_png(out / view.name / "columns.png")
        assert columns.dtype == np.uint16 and (columns[ref.column < 0] == INVALID).all()
        assert set(np.unique(read_png(out / view.name / "mask.png"))) <= {0, 255}
        # against the ground truth: the projector pixel seen at each camera pixel centre
        truth = gray_rows_session.load_ground_truth(view)
        lit = truth.visibility == 2
        assert codes.mask[lit].mean() > 0.7  # the others lie on a stripe edge of some bit
        both = lit & codes.mask
        # (integer u at a projector pixel's centre: a right code is within 0.5 of it)
        du = np.abs(codes.column[both] - truth.projector_uv[..., 0][both])
        dv = np.abs(codes.row[both] - truth.projector_uv[..., 1][both])
        assert np.mean(du <= 1.0) > 0.98 and np.mean(dv <= 1.0) > 0.98, (np.mean(du <= 1), np.mean(dv <= 1))
        assert np.median(du) < 0.35 and np.median(dv) < 0.35, (np.median(du), np.median(dv))
        # background at the pixel centre: only silhouette pixels, partly on the object
        assert (truth.visibility == 0)[codes.mask].mean() < 0.01
    entities = _entities(rrd)
    for name in ("columns", "rows", "mask", "codes"):
        assert f"world/camera/image/decode/{name}" in entities, sorted(entities)


def test_a_session_without_calibration_writes_codes_only(gray_rows_session, tmp_path, caplog):
    session = _uncalibrated(gray_rows_session, tmp_path / "copy")
    out, rrd = tmp_path / "codes", tmp_path / "codes.rrd"
    with caplog.at_level("WARNING"):
        assert main(["decode", str(session), "--out", str(out), "--quiet", "--save", str(rrd)]) == 0
    assert "no calibration: writing projector codes only" in caplog.text
    assert not list(out.glob("*.ply")) and not (out / "range_maps.json").exists()
    ref = decode_gray(load_session(session), "view_001")
    codes = read_codes(out / "view_001")  # a view's folder directly
    np.testing.assert_array_equal(codes.column, ref.column)
    np.testing.assert_array_equal(codes.row, ref.row)
    entities = _entities(rrd)
    assert {"world/camera/image/decode/columns", "world/camera/image/decode/rows",
            "world/camera/image/decode/mask", "world/camera/image/capture"} <= entities


def test_hybrid_sets_have_no_codes(tmp_path, capsys):
    session = capture_session(
        VirtualCaptureConfig(scene="tile", patterns="hybrid", camera_scale=0.25, projector_scale=0.25,
                             levels=6, views=1, lit_images=False, sensor=Sensor(noise=False)),
        tmp_path / "hybrid",
    )
    assert main(["decode", str(session.root), "--out", str(tmp_path / "x"), "--codes", "--quiet"]) == 2
    assert "codes are written for Gray-code and phase-shifting pattern sets only" in capsys.readouterr().err
    copy = _uncalibrated(session, tmp_path / "copy")
    assert main(["decode", str(copy), "--out", str(tmp_path / "y"), "--quiet"]) == 2
    assert "codes are written for Gray-code and phase-shifting pattern sets only" in capsys.readouterr().err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_codes_beside_hybrid_range_maps_come_from_the_gray_set(tmp_path):
    """A session with both pattern sets: range maps from the hybrid, codes from the Gray code."""
    from slscan.decode.pipeline import DecodeConfig, decode_session

    session = capture_session(
        VirtualCaptureConfig(scene="tile", patterns="both", camera_scale=0.25, projector_scale=0.25,
                             levels=6, views=1, lit_images=False, sensor=Sensor(noise=False)),
        tmp_path / "both",
    )
    out = tmp_path / "maps"
    [result] = decode_session(session, out, DecodeConfig(method="hybrid"), codes=True)
    assert result.method == "hybrid" and result.valid_share is not None
    ref = decode_gray(session, "view_000")
    codes = read_codes(out)
    np.testing.assert_array_equal(codes.column, ref.column)
    np.testing.assert_array_equal(codes.mask, ref.mask)
    assert codes.row is None and codes.bits[1] == 0 and not (out / "view_000" / "rows.png").exists()
    assert json.loads((out / "range_maps.json").read_text())["views"][0]["method"] == "hybrid"


def test_the_reader_names_what_is_wrong(gray_rows_session, tmp_path):
    out = tmp_path / "codes"
    session = _uncalibrated(gray_rows_session, tmp_path / "copy")
    assert main(["decode", str(session), "--out", str(out), "--quiet"]) == 0
    with pytest.raises(SlscanError, match="2 views .*name one"):
        read_codes(out)
    with pytest.raises(SlscanError, match="no view 'nope'"):
        read_codes(out, "nope")
    with pytest.raises(SlscanError, match="expected the output of slscan decode --codes"):
        read_codes(tmp_path)
    (out / "view_000" / "rows.png").write_bytes(read_png(out / "view_000" / "mask.png").tobytes()[:10])
    with pytest.raises(SlscanError, match="rows.png"):
        read_codes(out, "view_000")


def test_the_valid_share_says_what_limited_it(gray_rows_session):
    view = gray_rows_session.views[0]
    res = decode_gray(gray_rows_session, view)
    share = valid_share(res)
    # the decoder's own counts (GrayResult.diagnostics): every lit pixel is decoded or lost to one cause
    assert share.source == "decoder" and share.decoded == pytest.approx(res.mask.mean())
    assert share.noise_dn == pytest.approx(res.noise * 255)
    lit = res.contrast > 0.03
    assert share.lit == pytest.approx(lit.mean())
    assert share.low_contrast + share.weak_bits + share.out_of_range + share.unreliable == pytest.approx(
        1 - (res.mask & lit).sum() / lit.sum())
    # a 10x noisier decode: dark lit pixels fall under 3 sigma, low contrast grows
    noisy = decode_gray(gray_rows_session, view, noise=res.noise * 10)
    worse = valid_share(noisy)
    assert worse.low_contrast > share.low_contrast and worse.decoded < share.decoded
    assert "noise" in share.describe() and "DN" in share.describe()
    # without the decoder's counts: estimated from contrast, noise and mask
    bare = SimpleNamespace(mask=noisy.mask, contrast=noisy.contrast, noise=noisy.noise, white=noisy.white)
    estimated = valid_share(bare)
    assert estimated.source == "estimated"
    assert estimated.low_contrast == pytest.approx(worse.low_contrast, abs=0.01)
    assert estimated.low_contrast + estimated.weak_bits == pytest.approx(
        1 - (noisy.mask & (noisy.contrast > 0.03)).sum() / (noisy.contrast > 0.03).sum())
    # counts reported by a decoder: shares of the pixels that passed the minimum contrast
    with_diagnostics = SimpleNamespace(
        mask=res.mask, contrast=res.contrast, noise=res.noise, white=res.white,
        diagnostics={"noise_dn": 4.5, "pixels": 2000, "dark": 1000, "lit": 880, "low_contrast": 1120,
                     "weak_bit_noise": 50, "weak_bit_ratio": 150, "out_of_range": 10, "valid": 670,
                     "threshold_mode": "adaptive"},
    )
    reported = valid_share(with_diagnostics)
    assert reported == ValidShare(decoded=float(res.mask.mean()), lit=0.5, noise_dn=4.5,
                                  low_contrast=0.12, weak_bits=0.2, out_of_range=0.01, source="decoder")
    assert replace(reported, weak_bits=0.0).limited_by == "low contrast"


@pytest.fixture(scope="module")
def kamino410_session(tmp_path_factory):
    src = shared_data_dir() / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        pytest.skip(f"kamino410 captures not found at {src} (set SLSCAN_DATA or clone ../shared/data)")
    from slscan.capture.kamino410 import import_kamino410

    return import_kamino410(src / "capture_0", tmp_path_factory.mktemp("kamino") / "session")


def test_real_captures_without_calibration_decode_to_codes(kamino410_session, tmp_path):
    out = tmp_path / "codes"
    assert main(["decode", str(kamino410_session.root), "--out", str(out), "--quiet"]) == 0
    codes = read_codes(out)
    ref = decode_gray(kamino410_session, kamino410_session.views[0])
    np.testing.assert_array_equal(codes.column, ref.column)
    np.testing.assert_array_equal(codes.row, ref.row)
    assert codes.projector_size == (1024, 768) and codes.bits == (10, 10)
    assert 0.3 < codes.valid_share.decoded < 0.6
    assert 1.0 < codes.valid_share.noise_dn < 4.0
