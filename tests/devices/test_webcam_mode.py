"""Choosing a webcam's mode (``--camera opencv:0:1920x1080@30``): the spec is parsed, the
driver is asked for the size and rate, and a mode the camera does not take is refused.
There is no webcam here: a FAKE ``cv2.VideoCapture`` plays a webcam with a fixed list of
modes, and the tests patch it in for the real one."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slscan.devices import opencv_camera
from slscan.devices.base import DeviceError
from slscan.devices.specs import CAMERA_KINDS, WebcamMode, open_camera, parse_spec, split_webcam_mode


class FakeWebcam:
    """FAKE cv2.VideoCapture: a webcam whose driver snaps the asked size and rate to its own
    modes (the nearest listed), as V4L2 drivers do, and delivers frames of the mode set."""

    MODES = ((640, 480, 30.0), (1280, 720, 30.0), (1920, 1080, 30.0), (1920, 1080, 15.0))
    opened: list[FakeWebcam] = []

    def __init__(self, source, *args) -> None:
        self.source, self.props = source, {}
        self.width, self.height, self.fps = 640, 480, 30.0
        FakeWebcam.opened.append(self)

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return True

    def getBackendName(self) -> str:  # noqa: N802
        return "FAKE"

    def set(self, prop, value) -> bool:
        self.props[prop] = value
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT, cv2.CAP_PROP_FPS):
            want = (self.props.get(cv2.CAP_PROP_FRAME_WIDTH, self.width),
                    self.props.get(cv2.CAP_PROP_FRAME_HEIGHT, self.height),
                    self.props.get(cv2.CAP_PROP_FPS, self.fps))
            self.width, self.height, self.fps = min(
                self.MODES, key=lambda m: (abs(m[0] - want[0]) + abs(m[1] - want[1]), abs(m[2] - want[2])))
            return True
        return False

    def get(self, prop) -> float:
        return {cv2.CAP_PROP_FRAME_WIDTH: self.width, cv2.CAP_PROP_FRAME_HEIGHT: self.height,
                cv2.CAP_PROP_FPS: self.fps}.get(prop, -1.0)

    def read(self):
        return True, np.full((self.height, self.width, 3), 128, np.uint8)

    def grab(self) -> bool:
        return True

    def release(self) -> None:
        pass


@pytest.fixture
def fake_webcam(monkeypatch):
    FakeWebcam.opened.clear()
    monkeypatch.setattr(opencv_camera.cv2, "VideoCapture", FakeWebcam)
    # not Linux's /dev/video path (there is no /dev/video0 here): OpenCV's default back-end
    monkeypatch.setattr(opencv_camera.OpenCVCamera, "_v4l2_device", staticmethod(lambda source: None))
    return FakeWebcam


@pytest.mark.parametrize("text, source, mode", [
    ("opencv:0:1920x1080@30", "0", WebcamMode(1920, 1080, 30.0)),
    ("opencv:2:1280x720", "2", WebcamMode(1280, 720, None)),
    ("opencv:0:@15", "0", WebcamMode(None, None, 15.0)),
    ("opencv:/dev/video2:640x480@29.97", "/dev/video2", WebcamMode(640, 480, 29.97)),
    ("opencv:1", "1", WebcamMode()),
    ("opencv:rtsp://host:554/stream", "rtsp://host:554/stream", WebcamMode()),
    ("opencv:frames/%03d.png", "frames/%03d.png", WebcamMode()),
])
def test_mode_specs_parse(text, source, mode):
    assert split_webcam_mode(parse_spec(text, CAMERA_KINDS, "camera")) == (source, mode)


def test_a_mode_on_a_file_is_refused():
    with pytest.raises(DeviceError, match="a mode .* is for a webcam"):
        split_webcam_mode(parse_spec("opencv:scan.avi:640x480", CAMERA_KINDS, "camera"))


def test_the_asked_mode_is_set_and_checked(fake_webcam):
    camera = open_camera(parse_spec("opencv:0:1920x1080@15", CAMERA_KINDS, "camera"))
    try:
        assert camera.resolution == (1920, 1080)
        assert camera.capture().image.shape == (1080, 1920, 3)
        cap = fake_webcam.opened[-1]
        assert cap.props[cv2.CAP_PROP_FRAME_WIDTH] == 1920 and cap.props[cv2.CAP_PROP_FRAME_HEIGHT] == 1080
        assert cap.props[cv2.CAP_PROP_FPS] == 15.0
        assert camera.describe()["fps"] == 15.0
    finally:
        camera.close()


def test_a_size_the_webcam_does_not_have_is_refused(fake_webcam):
    with pytest.raises(DeviceError, match=r"asked for 1000x1000 frames, it delivers 1280x720"):
        open_camera(parse_spec("opencv:0:1000x1000", CAMERA_KINDS, "camera"))


def test_a_rate_the_webcam_does_not_have_is_refused(fake_webcam):
    with pytest.raises(DeviceError, match=r"asked for 60 fps, the driver set 30 fps"):
        open_camera(parse_spec("opencv:0:1280x720@60", CAMERA_KINDS, "camera"))
