"""Tests for the kamino410/procam-calibration importer: real captures and synthetic folders."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from slscan.capture.kamino410 import capture_sequence, import_kamino410
from slscan.capture.session import load_session
from slscan.errors import SlscanError
from slscan.fsio import write_png
from slscan.patterns import graycode, render

CAMERA = (32, 24)  # synthetic camera (width, height) px


def _sample_data(shared_data: Path) -> Path:
    path = shared_data / "procam_graycode_kamino410" / "sample_data"
    if not path.is_dir():
        pytest.skip(f"real data not found: {path}")
    return path


# --- real captures ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def real_session(shared_data: Path, tmp_path_factory: pytest.TempPathFactory):
    src = _sample_data(shared_data)
    out = tmp_path_factory.mktemp("kamino410") / "session"
    calls = []
    import_kamino410(src, out, progress=lambda done, total: calls.append((done, total)))
    return load_session(out), calls  # load_session checks every image's PNG header


def test_real_import_layout(real_session):
    session, calls = real_session
    assert [v.name for v in session.views] == [f"capture_{i}" for i in range(5)]
    assert all(len(v.images) == 42 for v in session.views)
    assert session.camera_size == (1280, 1024)
    assert (session.channels, session.bit_depth) == (1, 8)
    assert session.projector_size == (1024, 768)
    assert session.calibration is None
    assert session.device["tool"] == "kamino410/procam-calibration"
    assert calls[-1] == (210, 210) and len(calls) == 210


def test_real_images_copied_byte_for_byte(real_session, shared_data: Path):
    session, _ = real_session
    view = session.view("capture_3")
    rec = view.image_for("gray-row-04-inv")
    assert rec.file == "29_gray-row-04-inv.png"
    source = _sample_data(shared_data) / "capture_3" / "graycode_29.png"
    assert session.image_path(view, rec).read_bytes() == source.read_bytes()


def test_real_white_black_and_pair_sum(real_session):
    session, _ = real_session
    view = session.view("capture_0")
    white = session.read_image(view, view.image_for("white")).astype(float)
    black = session.read_image(view, view.image_for("black")).astype(float)
    assert white.mean() > black.mean() + 20
    lit = white - black > 40
    assert lit.mean() > 0.3
    pattern = session.read_image(view, view.image_for("gray-col-00")).astype(float)
    inverse = session.read_image(view, view.image_for("gray-col-00-inv")).astype(float)
    assert np.corrcoef((pattern + inverse)[lit], white[lit])[0, 1] > 0.9


def test_real_decoded_codes_follow_the_camera_axes(real_session):
    """The strongest check of the mapping: decoded projector columns grow with camera x
    and rows with camera y (a swapped bit order, axis or inverse would break this)."""
    session, _ = real_session
    view = session.view("capture_0")

    def read(pattern_id: str) -> np.ndarray:
        return session.read_image(view, view.image_for(pattern_id)).astype(np.int16)

    lit = read("white") - read("black") > 40
    rows, cols = np.nonzero(lit)
    for tag, camera_coord in (("col", cols), ("row", rows)):
        code = np.zeros(lit.shape, dtype=np.int64)
        for bit in range(10):
            code = code * 2 + (read(f"gray-{tag}-{bit:02d}") > read(f"gray-{tag}-{bit:02d}-inv"))
        value = graycode.inverse_gray(code)[lit]
        assert np.corrcoef(value, camera_coord)[0, 1] > 0.95, tag


# --- synthetic captures -----------------------------------------------------------------------


def _fake_capture(folder: Path, projector: tuple[int, int] = (1024, 768)) -> list[Path]:
    """A capture folder of small grey PNGs: each pattern sampled on a CAMERA-sized grid."""
    folder.mkdir(parents=True)
    ys = np.linspace(0, projector[1] - 1, CAMERA[1]).astype(int)
    xs = np.linspace(0, projector[0] - 1, CAMERA[0]).astype(int)
    paths = []
    for i, desc in enumerate(capture_sequence(*projector)):
        image = render(desc)[np.ix_(ys, xs)][..., 0]
        path = folder / f"graycode_{i:02d}.png"
        write_png(path, image)
        paths.append(path)
    return paths


def _pattern_folder(folder: Path, projector: tuple[int, int]) -> None:
    folder.mkdir(parents=True)
    for i, desc in enumerate(capture_sequence(*projector)):
        write_png(folder / f"pattern_{i:02d}.png", render(desc)[..., 0])


def _leftovers(out: Path) -> list[Path]:
    return [out] if out.exists() else list(out.parent.glob(f".{out.name}.*"))


def test_synthetic_single_capture(tmp_path: Path):
    paths = _fake_capture(tmp_path / "capture_7")
    out = tmp_path / "session"
    session = import_kamino410(tmp_path / "capture_7", out)
    loaded = load_session(out)
    assert [v.name for v in loaded.views] == ["capture_7"]
    assert loaded.camera_size == CAMERA and loaded.projector_size == (1024, 768)
    assert (loaded.channels, loaded.bit_depth) == (1, 8)
    assert [p.id for p in loaded.patterns[:2]] == ["white", "black"] and len(loaded.patterns) == 42
    assert session.to_dict()["views"] == loaded.to_dict()["views"]
    view = loaded.views[0]
    assert view.rig_from_object is None and view.exposure == {}
    assert [r.file for r in view.images][40:] == ["40_white.png", "41_black.png"]
    for rec, path in zip(view.images, paths):
        assert loaded.image_path(view, rec).read_bytes() == path.read_bytes()
    assert loaded.device["source"] == str((tmp_path / "capture_7").resolve())


def test_synthetic_views_in_numeric_order_with_pattern_folder(tmp_path: Path):
    projector = (16, 8)  # 4 column bits + 3 row bits: 16 images per capture
    src = tmp_path / "sample_data"
    _pattern_folder(src / "graycode_pattern", projector)
    for n in (10, 2):
        _fake_capture(src / f"capture_{n}", projector)
    (src / "capture_2" / "notes.txt").write_text("ignored")
    out = tmp_path / "session"
    import_kamino410(src, out)
    session = load_session(out)
    assert [v.name for v in session.views] == ["capture_2", "capture_10"]
    assert session.projector_size == projector
    assert all(len(v.images) == 16 for v in session.views)
    assert session.views[0].image_for("gray-row-02-inv").file == "13_gray-row-02-inv.png"


def test_synthetic_pattern_folder_found_beside_single_capture(tmp_path: Path):
    projector = (16, 8)
    _pattern_folder(tmp_path / "graycode_pattern", projector)
    _fake_capture(tmp_path / "capture_0", projector)
    import_kamino410(tmp_path / "capture_0", tmp_path / "session")
    assert load_session(tmp_path / "session").projector_size == projector


def test_synthetic_pattern_mismatch_names_the_file(tmp_path: Path):
    projector = (16, 8)
    _pattern_folder(tmp_path / "graycode_pattern", projector)
    _fake_capture(tmp_path / "capture_0", projector)
    pats = tmp_path / "graycode_pattern"
    shutil.copy(pats / "pattern_02.png", pats / "pattern_01.png")
    out = tmp_path / "session"
    with pytest.raises(SlscanError, match="pattern_01.png"):
        import_kamino410(tmp_path / "capture_0", out)
    assert not _leftovers(out)


def test_synthetic_missing_image(tmp_path: Path):
    _fake_capture(tmp_path / "capture_0")
    (tmp_path / "capture_0" / "graycode_17.png").unlink()
    out = tmp_path / "session"
    with pytest.raises(SlscanError, match="graycode_17.png"):
        import_kamino410(tmp_path, out)
    assert not _leftovers(out)


def test_synthetic_wrong_size_names_the_file(tmp_path: Path):
    _fake_capture(tmp_path / "capture_0")
    write_png(tmp_path / "capture_0" / "graycode_23.png", np.zeros((24, 33), np.uint8))
    out = tmp_path / "session"
    with pytest.raises(SlscanError, match=r"graycode_23\.png.*33x24.*expected 32x24"):
        import_kamino410(tmp_path / "capture_0", out)
    assert not _leftovers(out)


def test_synthetic_extra_image(tmp_path: Path):
    _fake_capture(tmp_path / "capture_0")
    shutil.copy(
        tmp_path / "capture_0" / "graycode_41.png", tmp_path / "capture_0" / "graycode_42.png"
    )
    with pytest.raises(SlscanError, match="expected 42 images"):
        import_kamino410(tmp_path / "capture_0", tmp_path / "session")


def test_synthetic_no_images(tmp_path: Path):
    (tmp_path / "capture_0").mkdir()
    with pytest.raises(SlscanError, match="capture_0.*no graycode_"):
        import_kamino410(tmp_path, tmp_path / "session")
    with pytest.raises(SlscanError, match="no graycode_.*capture_"):
        import_kamino410(tmp_path / "capture_0", tmp_path / "session")


def test_failure_while_copying_leaves_nothing(tmp_path: Path):
    _fake_capture(tmp_path / "src" / "capture_0")
    out = tmp_path / "session"

    def stop(done: int, total: int) -> None:
        if done == 10:
            raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError):
        import_kamino410(tmp_path / "src", out, progress=stop)
    assert not _leftovers(out)


@pytest.mark.parametrize(
    ("src", "out"),
    [("data", "data"), ("data", "."), ("data", "data/capture_0"), ("data/capture_0", "data")],
)
def test_refuses_to_overwrite_the_source(tmp_path: Path, src: str, out: str):
    _fake_capture(tmp_path / "data" / "capture_0")
    with pytest.raises(SlscanError, match="outside the source"):
        import_kamino410(tmp_path / src, tmp_path / out, overwrite=True)
    assert (tmp_path / "data" / "capture_0" / "graycode_00.png").is_file()


def test_session_may_sit_beside_the_captures(tmp_path: Path):
    _fake_capture(tmp_path / "capture_0")
    import_kamino410(tmp_path, tmp_path / "session")
    assert [v.name for v in load_session(tmp_path / "session").views] == ["capture_0"]
