"""OpenCVCamera on real VideoCapture sources written here: a lossless FFV1 video and PNG
image sequences whose frames are known (frame i has blue 10·i, green 100, red 200)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slscan.devices.base import DeviceError
from slscan.devices.opencv_camera import OpenCVCamera, bgr_to_rgb, v4l2_range

H, W, N = 24, 32, 12


def _bgr(i: int) -> np.ndarray:
    """Frame i as OpenCV writes it (BGR): blue 10·i, green 100, red 200."""
    img = np.empty((H, W, 3), np.uint8)
    img[...] = (10 * i, 100, 200)
    return img


def _rgb_value(i: int) -> tuple[int, int, int]:
    return (200, 100, 10 * i)


@pytest.fixture
def sequence(tmp_path):
    for i in range(N):
        cv2.imwrite(str(tmp_path / f"f_{i:03d}.png"), _bgr(i))
    return str(tmp_path / "f_%03d.png")


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "scan.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 10, (W, H))
    assert writer.isOpened(), "OpenCV's FFmpeg cannot write FFV1 here"
    for i in range(N):
        writer.write(_bgr(i))
    writer.release()
    return str(path)


def _flat(frame_image: np.ndarray) -> tuple[int, ...]:
    values = frame_image.reshape(-1, frame_image.shape[-1])
    assert (values == values[0]).all(), "a flat frame came back uneven"
    return tuple(int(v) for v in values[0])


@pytest.mark.parametrize("kind", ["sequence", "video"])
def test_frames_come_back_rgb_in_order(kind, request):
    source = request.getfixturevalue(kind)
    with OpenCVCamera(source, flush_frames=0) as cam:
        assert cam.resolution == (W, H) and cam.channels == 3 and cam.bit_depth == 8
        assert cam.controls() == {}  # files have nothing settable
        for i in range(3):
            frame = cam.capture()
            assert frame.image.shape == (H, W, 3) and frame.image.dtype == np.uint8
            assert _flat(frame.image) == _rgb_value(i)  # RGB order: red first
            assert frame.metadata["frame_index"] == i
            assert frame.metadata["source"] == source
        assert cam.describe()["kind"] == "opencv"


@pytest.mark.parametrize("flush_frames", [0, 1, 4])
def test_flush_discards_the_configured_number_of_frames(sequence, flush_frames):
    with OpenCVCamera(sequence, flush_frames=flush_frames) as cam:
        k = 1
        cam.capture()
        cam.capture()  # frame k = 1 returned
        cam.flush()
        frame = cam.capture()
        expected = k + flush_frames + 1
        assert frame.metadata["frame_index"] == expected
        assert _flat(frame.image) == _rgb_value(expected)


def test_end_of_stream_is_a_device_error(video):
    with OpenCVCamera(video, flush_frames=N - 2) as cam:
        cam.capture()  # frame 0
        cam.flush()  # frames 1 .. N-2
        assert _flat(cam.capture().image) == _rgb_value(N - 1)
        with pytest.raises(DeviceError, match=r"opencv:.*no frame.*ended after 12 frame"):
            cam.capture()
        with pytest.raises(DeviceError, match="no frame"):
            cam.flush()


def test_grey_sequence_becomes_three_equal_channels(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"g_{i:02d}.png"), np.full((H, W), 40 * i + 5, np.uint8))
    with OpenCVCamera(str(tmp_path / "g_%02d.png")) as cam:
        assert cam.channels == 3
        cam.capture()
        assert _flat(cam.capture().image) == (45, 45, 45)


def test_16_bit_sequence_stays_16_bit(tmp_path):
    for i in range(3):
        img = np.zeros((H, W, 3), np.uint16)
        img[...] = (1000 * i, 30000, 65535)  # BGR
        cv2.imwrite(str(tmp_path / f"d_{i:02d}.png"), img)
    with OpenCVCamera(str(tmp_path / "d_%02d.png")) as cam:
        assert cam.bit_depth == 16
        cam.capture()
        frame = cam.capture()
        assert frame.image.dtype == np.uint16
        assert _flat(frame.image) == (65535, 30000, 1000)


def test_a_frame_of_another_size_is_a_device_error(tmp_path):
    for i in range(3):
        size = (H, W) if i != 2 else (H + 2, W)
        cv2.imwrite(str(tmp_path / f"s_{i:02d}.png"), np.full((*size, 3), 50, np.uint8))
    with OpenCVCamera(str(tmp_path / "s_%02d.png")) as cam:
        cam.capture()
        cam.capture()
        with pytest.raises(DeviceError, match=r"frame 2 is 32x26 uint8, the first frame was 32x24"):
            cam.capture()


def test_missing_sources_are_device_errors(tmp_path):
    with pytest.raises(
        DeviceError, match=r"camera opencv:63 not found: no V4L2 device /dev/video63"
    ):
        OpenCVCamera(63)
    missing = tmp_path / "nothing.avi"
    with pytest.raises(DeviceError, match=r"not found: no file .*nothing\.avi"):
        OpenCVCamera(str(missing))
    with pytest.raises(
        DeviceError, match=r"not found: no image sequence .*x_%03d\.png \(no file .*x_000\.png"
    ):
        OpenCVCamera(str(tmp_path / "x_%03d.png"))
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video at all" * 10)
    with pytest.raises(DeviceError, match=r"OpenCV cannot read .*junk\.avi"):
        OpenCVCamera(str(junk))


def test_file_sources_refuse_controls_and_close_twice(sequence):
    with pytest.raises(DeviceError, match="a file or image sequence has no exposure or gain"):
        OpenCVCamera(sequence, exposure=100, gain=2)
    cam = OpenCVCamera(sequence)
    with pytest.raises(DeviceError, match="cannot set exposure"):
        cam.set_controls(exposure=10)
    assert cam.get_controls() == {}
    cam.close()
    cam.close()
    with pytest.raises(DeviceError, match="closed"):
        cam.capture()


def test_bgr_to_rgb_conversions():
    bgra = np.zeros((2, 3, 4), np.uint8)
    bgra[...] = (1, 2, 3, 4)
    assert bgr_to_rgb(bgra, "t")[0, 0].tolist() == [3, 2, 1]
    assert bgr_to_rgb(np.full((2, 3, 1), 7, np.uint16), "t").shape == (2, 3, 3)
    with pytest.raises(DeviceError, match="float32 pixels"):
        bgr_to_rgb(np.zeros((2, 3, 3), np.float32), "t")


def test_v4l2_range_is_none_without_a_device(tmp_path):
    assert v4l2_range(tmp_path / "video99", 0x009A0902) is None
    assert v4l2_range("/dev/null", 0x009A0902) is None  # not a V4L2 device: the ioctl fails
