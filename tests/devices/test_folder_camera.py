"""FolderCamera against a writer thread that saves files the way tethering software does:
late, in pieces, rewritten, several at once; pre-existing files and the user's bytes untouched."""

from __future__ import annotations

import os
import threading
import time

import cv2
import numpy as np
import pytest

from slscan.devices.base import DeviceError
from slscan.devices.folder import FolderCamera, decode_complete

H, W = 48, 64


def _image(seed: int, size: tuple[int, int] = (H, W)) -> np.ndarray:
    """(h, w, 3) uint8 RGB noise: incompressible, so half a file is half the pixels."""
    return np.random.default_rng(seed).integers(0, 256, (*size, 3), dtype=np.uint8)


def _encode(rgb: np.ndarray, ext: str = ".png") -> bytes:
    ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    return buf.tobytes()


def _later(*steps):
    """Run (delay_s, callable) steps in a writer thread; returns (thread, times each started).

    The start, not the end: the camera may read a file the step has just completed before
    the thread, on a loaded machine, gets to note the time (a flaky failure seen in CI)."""
    times: list[float] = []

    def run():
        for delay, step in steps:
            time.sleep(delay)
            times.append(time.monotonic())
            step()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread, times


def _write(path, data: bytes, mode: str = "wb"):
    def step():
        with open(path, mode) as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())

    return step


def test_pre_existing_files_are_ignored_and_a_late_file_is_returned(tmp_path):
    old = _image(1)
    (tmp_path / "old.png").write_bytes(_encode(old))
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in tmp_path.iterdir()}
    cam = FolderCamera(tmp_path, timeout_s=5, stable_s=0.05, poll_s=0.01)
    assert cam.resolution == (W, H)  # learnt from the file already there
    new = _image(2)
    start = time.monotonic()
    thread, times = _later((0.2, _write(tmp_path / "IMG_0002.PNG", _encode(new))))  # upper case too
    frame = cam.capture()
    thread.join()
    assert frame.timestamp >= times[0] > start
    assert frame.metadata == {"file": "IMG_0002.PNG", "pending": 0}
    assert frame.image.dtype == np.uint8 and np.array_equal(frame.image, new)
    for name, (data, mtime) in before.items():  # the user's files are untouched
        assert (tmp_path / name).read_bytes() == data and (
            tmp_path / name
        ).stat().st_mtime_ns == mtime
    assert sorted(p.name for p in tmp_path.iterdir()) == ["IMG_0002.PNG", "old.png"]


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_a_half_written_file_is_not_returned(tmp_path, ext):
    """The writer stalls half-way for longer than stable_s: the size is stable, so only the
    decode check keeps the half file back."""
    rgb = _image(3)
    data = _encode(rgb, ext)
    half = len(data) // 2
    cam = FolderCamera(tmp_path, timeout_s=5, stable_s=0.05, poll_s=0.01, resolution=(W, H))
    path = tmp_path / f"shot{ext}"
    thread, times = _later(
        (0.05, _write(path, data[:half])), (0.4, _write(path, data[half:], "ab"))
    )
    frame = cam.capture()
    thread.join()
    assert frame.timestamp >= times[1]  # not before the second half was written
    expected = cv2.cvtColor(
        cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
    )
    assert np.array_equal(frame.image, expected)


def test_a_file_still_changing_waits_for_stable_s(tmp_path):
    """A complete image rewritten with another one within stable_s: both decode, so only the
    size/time stability keeps the first one back."""
    first, second = _image(4), _image(5)
    stable_s = 0.5
    cam = FolderCamera(tmp_path, timeout_s=5, stable_s=stable_s, poll_s=0.01, resolution=(W, H))
    path = tmp_path / "shot.png"
    thread, times = _later(
        (0.05, _write(path, _encode(first))), (0.05, _write(path, _encode(second) + b"\0" * 64))
    )
    frame = cam.capture()
    thread.join()
    assert np.array_equal(frame.image, second)
    assert frame.timestamp >= times[1] + stable_s


def test_several_new_files_come_one_per_capture_oldest_first(tmp_path):
    cam = FolderCamera(tmp_path, timeout_s=5, stable_s=0.05, poll_s=0.01)
    images = {
        "b.png": _image(6),
        "a.png": _image(7),
        "c.jpg.tmp": _image(8),
        ".hidden.png": _image(9),
    }
    for name, rgb in images.items():
        (tmp_path / name).write_bytes(_encode(rgb))
    now = time.time_ns()
    os.utime(tmp_path / "b.png", ns=(now - 2_000_000_000, now - 2_000_000_000))  # b is older than a
    os.utime(tmp_path / "a.png", ns=(now - 1_000_000_000, now - 1_000_000_000))
    first, second = cam.capture(), cam.capture()
    assert first.metadata == {"file": "b.png", "pending": 1}
    assert second.metadata == {"file": "a.png", "pending": 0}
    assert np.array_equal(first.image, images["b.png"]) and np.array_equal(
        second.image, images["a.png"]
    )
    cam.timeout_s = 0.2
    with pytest.raises(DeviceError, match="no new image within 0.2 s"):
        cam.capture()  # neither the .tmp nor the hidden file counts


def test_timeout_and_unknown_size_are_device_errors(tmp_path):
    cam = FolderCamera(tmp_path, timeout_s=0.2, poll_s=0.01)
    with pytest.raises(DeviceError, match="image size is not known before the first image"):
        _ = cam.resolution
    t = time.monotonic()
    with pytest.raises(
        DeviceError,
        match=r"folder camera .*: no new image within 0.2 s \(is the tethering software saving there\?\)",
    ):
        cam.capture()
    assert 0.2 <= time.monotonic() - t < 2
    with pytest.raises(DeviceError, match="not a folder"):
        FolderCamera(tmp_path / "missing")


def test_an_unreadable_file_times_out_naming_it(tmp_path):
    cam = FolderCamera(tmp_path, timeout_s=0.3, stable_s=0.05, poll_s=0.01)
    (tmp_path / "bad.jpg").write_bytes(b"\xff\xd8 not really a jpeg \xff\xd9")
    with pytest.raises(
        DeviceError, match="bad.jpg did not become a complete, readable image within 0.3 s"
    ):
        cam.capture()


def test_an_image_of_another_size_is_an_error_naming_it(tmp_path):
    cam = FolderCamera(tmp_path, timeout_s=5, stable_s=0.05, poll_s=0.01)
    (tmp_path / "one.png").write_bytes(_encode(_image(10)))
    assert cam.capture().image.shape == (H, W, 3)
    assert cam.resolution == (W, H)  # from the first capture
    (tmp_path / "two.png").write_bytes(_encode(_image(11, (H, W + 4))))
    with pytest.raises(
        DeviceError, match=r"two\.png is 68x48 uint8, expected 64x48 uint8 \(as one\.png"
    ):
        cam.capture()


def test_grey_and_16_bit_images(tmp_path):
    cam = FolderCamera(tmp_path, timeout_s=5, stable_s=0.05, poll_s=0.01)
    deep = np.full((H, W, 3), 40000, np.uint16)
    deep[..., 2] = 1000  # BGR on disk: red 1000
    cv2.imwrite(str(tmp_path / "deep.png"), deep)
    frame = cam.capture()
    assert cam.bit_depth == 16 and frame.image.dtype == np.uint16
    assert frame.image[0, 0].tolist() == [1000, 40000, 40000]
    assert cam.describe()["kind"] == "folder"
    grey_dir = tmp_path / "grey"
    grey_dir.mkdir()
    cam3 = FolderCamera(grey_dir, timeout_s=5, stable_s=0.05, poll_s=0.01)
    cv2.imwrite(str(grey_dir / "g.png"), np.full((H, W), 77, np.uint8))
    assert cam3.capture().image[0, 0].tolist() == [77, 77, 77]


def test_decode_complete_refuses_cut_files():
    data = _encode(_image(12), ".jpg")
    assert decode_complete(data[: len(data) // 2], "x.jpg") is None
    assert decode_complete(data[:-2], "x.jpg") is None  # only the end-of-image marker missing
    assert decode_complete(data, "x.JPG").shape == (H, W, 3)
    png = _encode(_image(13))
    assert decode_complete(png[:-20], "x.png") is None
    assert decode_complete(png + b"\0" * 10, "x.png") is not None


def test_scan_asks_for_every_shot_with_a_bell_on_stderr(tmp_path, capsys):
    """A watch-folder camera in a real scan: before each frame the driver asks the operator
    (bell + "shoot view V, frame F (...) now" on stderr); a FAKE trigger answers each prompt
    by saving the virtual camera's frame into the folder, as tethering software would."""
    from slscan.capture.driver import ScanDevices, scan
    from slscan.devices.base import NoLights
    from slscan.devices.folder import bell_prompt
    from slscan.virtual.device import VirtualCaptureConfig, scan_plan, virtual_devices

    config = VirtualCaptureConfig(camera_scale=0.2, projector_scale=0.2, levels=2, lit_images=False)
    world = virtual_devices(config)
    folder = tmp_path / "tether"
    folder.mkdir()
    shots: list[str] = []

    def fake_trigger(message: str) -> None:  # FAKE: the operator pressing the shutter
        bell_prompt(message)
        shots.append(message)
        rgb = world.camera.capture().image
        (folder / f"IMG_{len(shots):04d}.png").write_bytes(_encode(rgb))

    camera = FolderCamera(folder, resolution=world.camera.resolution, stable_s=0.02, poll_s=0.005,
                          timeout_s=10, prompt=fake_trigger)
    devices = ScanDevices(world.projector, camera, NoLights(), world.stage)
    plan = scan_plan(config, world.rig)
    result = scan(devices, plan, tmp_path / "s", views=1)
    err = capsys.readouterr().err
    assert len(result.session.views) == 1
    assert "\ashoot view 1, reference frame (projector dark) now\n" in err
    assert "\ashoot view 1, frame 1 (white) now\n" in err
    assert "\ashoot view 1, frame 2 (black) now\n" in err
    assert err.count("\a") == len(shots) == len(plan.patterns) + 1


def test_preview_asks_for_its_four_shots(tmp_path, capsys):
    from slscan.capture.preview import measure_once
    from slscan.devices.folder import bell_prompt
    from slscan.virtual.device import VirtualCaptureConfig, virtual_devices

    world = virtual_devices(VirtualCaptureConfig(camera_scale=0.2, projector_scale=0.2, scene="tile"))
    world.stage.move_to(0, 1)
    folder = tmp_path / "tether"
    folder.mkdir()

    def fake_trigger(message: str) -> None:  # FAKE: the operator pressing the shutter
        bell_prompt(message)
        n = len(list(folder.iterdir()))
        (folder / f"IMG_{n:04d}.png").write_bytes(_encode(world.camera.capture().image))

    camera = FolderCamera(folder, resolution=world.camera.resolution, stable_s=0.02, poll_s=0.005, prompt=fake_trigger)
    m = measure_once(world.projector, camera)
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if line.startswith("\a")] == [
        "\ashoot preview, black now", "\ashoot preview, white now", "\ashoot preview, stripes now",
        "\ashoot preview, inverse stripes now"]
    assert m.overlap > 0.1 and m.focus > 0.2
