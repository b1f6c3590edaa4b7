"""GPhoto2Camera against libgphoto2's virtual PTP camera (vcamera), which the python-gphoto2
wheel ships in ``gphoto2/libgphoto2/vusb`` and switches on through the environment
(``IOLIBS`` = that folder, ``VCAMERADIR`` = a folder of JPEGs it "shoots"). libgphoto2 reads
``IOLIBS`` whenever it lists ports, so each test points it there and back with monkeypatch.

The virtual camera answers as a "Nikon DSC D750" on ``usb:001,001``, returns the JPEG in
``VCAMERADIR`` for every shot, has ``shutterspeed`` choices from 0.0001 s to 1 s and no ISO.
Nothing here has run on a real camera."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import gphoto2 as gp
import numpy as np
import pytest

from slscan.devices.base import DeviceError
from slscan.devices.gphoto import (
    GPhoto2Camera,
    decode_camera_file,
    nearest_choice,
    parse_iso,
    parse_shutter,
)

H, W = 48, 64
RGB = (200, 60, 20)
GP_DIR = Path(gp.__file__).parent / "libgphoto2"


@pytest.fixture
def card(tmp_path, monkeypatch):
    """The virtual camera's folder, holding one flat JPEG of colour RGB."""
    vusb = GP_DIR / "vusb"
    assert vusb.is_dir(), (
        f"this python-gphoto2 ({gp.__version__}) has no virtual camera ({vusb} is missing): "
        "install a binary wheel of gphoto2 >= 2.5 from PyPI"
    )
    folder = tmp_path / "card"
    folder.mkdir()
    bgr = np.empty((H, W, 3), np.uint8)
    bgr[...] = RGB[::-1]
    assert cv2.imwrite(str(folder / "shot.jpg"), bgr)
    monkeypatch.setenv("IOLIBS", str(vusb))
    monkeypatch.setenv("VCAMERADIR", str(folder))
    return folder


def test_capture_downloads_decodes_and_deletes(card):
    before = {p.name: p.read_bytes() for p in card.iterdir()}
    with GPhoto2Camera(timeout_s=10) as cam:
        assert cam.model == "Nikon DSC D750" and cam.port == "usb:001,001"
        frame = cam.capture()
        assert frame.image.shape == (H, W, 3) and frame.image.dtype == np.uint8
        assert np.abs(frame.image.astype(int) - RGB).max() <= 3  # RGB order, JPEG-close
        assert frame.metadata["file"].startswith("/store_") and frame.metadata["file"].endswith(
            ".JPG"
        )
        assert frame.metadata["shutterspeed"] == "0.0100s" and frame.metadata["exposure_s"] == 0.01
        assert frame.timestamp <= time.monotonic()
        assert cam.resolution == (W, H)
        folder, name = frame.metadata["file"].rsplit("/", 1)
        files = cam._camera.folder_list_files(folder)  # the library's own view of the card
        assert name not in [files.get_name(i) for i in range(files.count())]
        assert cam.describe()["kind"] == "gphoto2"
    cam.close()  # twice is fine
    assert {p.name: p.read_bytes() for p in card.iterdir()} == before


def test_keep_on_camera_leaves_the_shot(card):
    with GPhoto2Camera(keep_on_camera=True) as cam:
        folder, name = cam.capture().metadata["file"].rsplit("/", 1)
        files = cam._camera.folder_list_files(folder)
        assert name in [files.get_name(i) for i in range(files.count())]


def test_resolution_before_any_capture_takes_a_test_shot(card):
    with GPhoto2Camera() as cam:
        assert cam.resolution == (W, H)


def test_exposure_is_the_shutter_speed_in_seconds(card):
    with GPhoto2Camera(model="d750") as cam:
        assert cam.controls() == {"exposure": (0.0001, 1.0)}  # no ISO on the virtual camera
        assert cam.get_controls() == {"exposure": 0.01}
        assert cam.set_controls(exposure=0.03) == {"exposure": 0.02}  # nearest in stops
        assert cam.get_controls() == {"exposure": 0.02}
        assert cam.capture().metadata["exposure_s"] == 0.02
        assert cam.set_controls(exposure=5) == {"exposure": 1.0}
        with pytest.raises(DeviceError, match=r"cannot set gain \(settable: exposure\)"):
            cam.set_controls(gain=400)


def test_a_camera_not_matching_port_or_model_is_named(card):
    with pytest.raises(
        DeviceError,
        match=r"no camera with port 'usb:009,009' \(libgphoto2 found: "
        r"Nikon DSC D750 on usb:001,001\)",
    ):
        GPhoto2Camera(port="usb:009,009")
    with pytest.raises(DeviceError, match="no camera with model 'canon'"):
        GPhoto2Camera(model="canon")


def test_no_camera_found_says_what_was_searched(tmp_path, monkeypatch):
    io = tmp_path / "iolibs"  # only the PTP/IP port driver: nothing to find, deterministically
    io.mkdir()
    (io / "ptpip.so").symlink_to(GP_DIR / "iolibs" / "ptpip.so")
    monkeypatch.setenv("IOLIBS", str(io))
    with pytest.raises(
        DeviceError,
        match=r"no camera found by libgphoto2 \(autodetect on ports ip:, ptpip: "
        r"found none; gp_camera_init: \[-105\] Unknown model\)",
    ):
        GPhoto2Camera()


def test_missing_python_gphoto2_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "gphoto2", None)  # import gphoto2 raises ImportError
    with pytest.raises(DeviceError, match=r"pip install 'slscan\[gphoto2\]'"):
        GPhoto2Camera()


class _SlowCameraProxy:
    """Wraps the real (virtual) camera; its capture hangs longer than the timeout."""

    def __init__(self, camera, delay_s):
        self._camera, self._delay_s = camera, delay_s

    def capture(self, kind):
        time.sleep(self._delay_s)
        return self._camera.capture(kind)

    def __getattr__(self, name):
        return getattr(self._camera, name)


def test_a_hanging_capture_times_out(card):
    cam = GPhoto2Camera(timeout_s=0.2)
    real = cam._camera
    cam._camera = _SlowCameraProxy(real, 0.6)
    with pytest.raises(DeviceError, match=r"no answer within 0.2 s while capturing"):
        cam.capture()
    with pytest.raises(DeviceError, match="still hanging"):
        cam.capture()
    hanging = cam._stuck
    cam.close()  # does not wait for the hanging call
    hanging.result()
    real.exit()


@pytest.mark.parametrize(
    ("text", "seconds"),
    [
        ("1/60", 1 / 60),
        ("1/4000", 1 / 4000),
        ("0.5", 0.5),
        ("2", 2.0),
        ('30"', 30.0),
        ('0"5', 0.5),
        ("0.0100s", 0.01),
        ("1/3s", 1 / 3),
        ("10/10", 1.0),
        ("bulb", None),
        ("Auto", None),
        ("0", None),
    ],
)
def test_parse_shutter(text, seconds):
    assert parse_shutter(text) == (pytest.approx(seconds) if seconds is not None else None)


@pytest.mark.parametrize(
    ("text", "iso"), [("100", 100.0), ("ISO 400", 400.0), ("Auto", None), ("Hi 1", None)]
)
def test_parse_iso(text, iso):
    assert parse_iso(text) == iso


def test_nearest_choice_is_nearest_in_stops():
    choices = {"1/60": 1 / 60, "1/30": 1 / 30, "1/15": 1 / 15}
    assert nearest_choice(choices, 1 / 40) == "1/30"  # 0.41 stop from 1/30, 0.58 from 1/60
    assert nearest_choice(choices, 10) == "1/15"
    assert nearest_choice(choices, 0) == "1/60"


def test_decode_camera_file_formats():
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 255
    for ext in (".png", ".tif"):
        data = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes()
        assert np.array_equal(decode_camera_file(data, f"DSC_0001{ext.upper()}"), rgb)
    with pytest.raises(
        DeviceError, match=r"DSC_0001\.NEF, a RAW file; RAW is not supported: .*JPEG only"
    ):
        decode_camera_file(b"raw bytes", "DSC_0001.NEF")
    with pytest.raises(DeviceError, match=r"could not decode x\.jpg \(4 bytes"):
        decode_camera_file(b"junk", "x.jpg")
