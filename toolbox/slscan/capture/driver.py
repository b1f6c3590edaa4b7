"""The acquisition driver: runs a pattern set and the lit images through a rig's devices
and writes a capture session view by view.

One code path for every rig: the virtual rig (:mod:`slscan.virtual.devices`) and real
hardware (:mod:`slscan.devices`) are only different :class:`ScanDevices`. For each view
the driver moves the stage, then for each pattern: show it, wait the settle time, discard
the camera's buffered frames, capture, check that the frame changed (a *stale* frame —
the camera returning an image from before the pattern change — is captured again, then
refused), write it; then, with the projector dark, one image per ring light.

Also here: :func:`measure_latency` (projector→camera delay, by flashing white) and
:func:`find_exposure` (exposure and gain that keep the green lines below saturation,
paper Fig. 9).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slscan.capture.session import ImageRecord, Session, SessionWriter, ViewRecord
from slscan.devices.base import Camera, DeviceError, Frame, Lights, Projector, Stage
from slscan.patterns import PatternImage, families_in, file_name, render

log = logging.getLogger(__name__)

STALE_ROW_STRIDE = 4  # rows compared for the stale-frame check (full resolution along rows)
STALE_LEVEL_DN8 = 8.0  # a pixel changed when it moved by more than this (8-bit DN)
STALE_SHARE = 5e-4  # a frame is stale when fewer samples than this share changed


class StaleFrameError(DeviceError):
    """The camera kept returning the image from before a pattern change."""


@dataclass
class ScanDevices:
    """The four devices a scan runs through."""

    projector: Projector
    camera: Camera
    lights: Lights
    stage: Stage

    def describe(self) -> dict:
        return {
            "kind": self.camera.describe().get("kind", "camera"),
            "projector": self.projector.describe(), "camera": self.camera.describe(),
            "lights": self.lights.describe(), "stage": self.stage.describe(),
        }

    def close(self) -> None:
        for device in (self.projector, self.camera, self.lights, self.stage):
            device.close()


@dataclass(frozen=True)
class ScanPlan:
    """What one view captures and how.

    patterns : projected in order (white, black, then the coded patterns)
    lit_images : also one image per ring light, projector dark (for albedo)
    lit_exposure : exposure of the lit images relative to the pattern images (cameras
        with an exposure control)
    settle_s : wait after each pattern or light change before capturing (the measured
        projector→camera latency, see :func:`measure_latency`)
    stale_retries : captures again this many times, waiting longer, before refusing a
        frame that did not change after a pattern change (0: no check)
    reference_frame : capture (and drop) a frame with the projector dark before each
        view's first pattern, so that the first pattern is checked for staleness too
    """

    patterns: tuple[PatternImage, ...]
    lit_images: bool = True
    lit_exposure: float = 1.0
    settle_s: float = 0.0
    stale_retries: int = 2
    reference_frame: bool = True

    def __post_init__(self) -> None:
        if not self.patterns:
            raise DeviceError("scan plan: no patterns to project")
        if not (math.isfinite(self.settle_s) and self.settle_s >= 0):
            raise DeviceError(f"settle time must be a finite number of seconds >= 0, got {self.settle_s}")
        if not (math.isfinite(self.lit_exposure) and self.lit_exposure > 0):
            raise DeviceError(f"lit exposure must be positive, got {self.lit_exposure}")


@dataclass
class ViewTiming:
    """Seconds spent on one view, by step (sums over its images)."""

    view: str
    images: int = 0
    move: float = 0.0
    show: float = 0.0
    settle: float = 0.0
    capture: float = 0.0
    write: float = 0.0
    retries: int = 0

    @property
    def total(self) -> float:
        return self.move + self.show + self.settle + self.capture + self.write


@dataclass(frozen=True)
class ScanResult:
    session: Session
    timings: tuple[ViewTiming, ...]
    resumed_views: int = 0


@dataclass(frozen=True)
class FrameCaptured:
    """What :func:`scan` reports for every frame (for live logging)."""

    view_index: int
    frame_index: int
    record: ImageRecord
    image: np.ndarray
    projected: np.ndarray | None = field(repr=False, default=None)


def _sample(image: np.ndarray) -> np.ndarray:
    return image[::STALE_ROW_STRIDE].astype(np.int32)


def changed_share(previous: np.ndarray, current: np.ndarray) -> float:
    """Share of samples (every 4th row, every column and channel) that moved by more than
    8 DN (8-bit scale) between two frames of the same shape."""
    full = 255.0 if previous.dtype == np.uint8 else 65535.0
    level = STALE_LEVEL_DN8 * full / 255.0
    return float((np.abs(_sample(current) - _sample(previous)) > level).mean())


def is_stale(previous: np.ndarray | None, current: np.ndarray, *, identical_only: bool = False) -> bool:
    """True when ``current`` shows no change from ``previous`` although what lit the scene
    changed: the camera returned a buffered frame from before the change.

    A projector pattern change moves many pixels by far more than the noise, so fewer
    than 0.05 % of the samples changing by 8 DN means a stale frame. A ring light change
    can be subtle on a small or dark object: ``identical_only`` flags only a frame that
    repeats the previous one bit for bit (the same buffer returned again)."""
    if previous is None or previous.shape != current.shape:
        return False
    if identical_only:
        return bool(np.array_equal(previous, current))
    return changed_share(previous, current) < STALE_SHARE


def _check_frame(frame: Frame, camera: Camera, where: str) -> np.ndarray:
    image = frame.image
    w, h = camera.resolution
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.shape[:2] != (h, w) or channels != camera.channels:
        raise DeviceError(f"{where}: the camera returned a {image.shape[1]}x{image.shape[0]}x{channels} frame, "
                          f"expected {w}x{h}x{camera.channels}")
    want = np.uint8 if camera.bit_depth == 8 else np.uint16
    if image.dtype != want:
        raise DeviceError(f"{where}: the camera returned {image.dtype} pixels, expected {np.dtype(want).name}")
    return image


class _Shooter:
    """Show → settle → flush → capture → stale check, with timings."""

    def __init__(self, devices: ScanDevices, plan: ScanPlan) -> None:
        self.devices, self.plan = devices, plan
        self.previous: np.ndarray | None = None

    def shoot(self, light_change: Callable[[], None], timing: ViewTiming, where: str,
              *, identical_only: bool = False, label: str = "") -> np.ndarray:
        cam = self.devices.camera
        t = time.perf_counter()
        light_change()
        timing.show += time.perf_counter() - t
        settle = self.plan.settle_s
        for attempt in range(self.plan.stale_retries + 1):
            t = time.perf_counter()
            if settle > 0:
                time.sleep(settle)
            timing.settle += time.perf_counter() - t
            t = time.perf_counter()
            cam.flush()
            if label:
                cam.about_to_capture(label if attempt == 0 else f"{label} again")
            image = _check_frame(cam.capture(), cam, where)
            timing.capture += time.perf_counter() - t
            if self.plan.stale_retries == 0 or not is_stale(self.previous, image, identical_only=identical_only):
                self.previous = image
                return image
            timing.retries += 1
            settle = max(2 * settle, 0.1)
            log.info("%s: stale frame (no change after the pattern change), capturing again", where)
        raise StaleFrameError(
            f"{where}: the camera returned the same image as before the pattern change "
            f"{self.plan.stale_retries + 1} times (stale frames): raise the settle time (--settle), "
            "or check that the camera sees the projected area"
        )


def _plan_lights(plan: ScanPlan, lights: Lights) -> int:
    if not plan.lit_images:
        return 0
    if lights.count == 0:
        log.warning("the rig has no lights: no lit images, so no albedo from this scan")
    return lights.count


def scan(
    devices: ScanDevices,
    plan: ScanPlan,
    out: str | Path,
    *,
    views: int,
    overwrite: bool = False,
    incremental: bool = True,
    resume: bool = False,
    calibration=None,
    calibration_source: str | None = None,
    device_info: dict | None = None,
    on_frame: Callable[[FrameCaptured], None] | None = None,
    after_view: Callable[[int, ViewRecord, Session], None] | None = None,
    progress: Callable[[str], None] | None = None,
) -> ScanResult:
    """Capture ``views`` views through ``devices`` into the capture session ``out``.

    incremental : write each view as it completes (a stopped scan keeps its finished
        views); False: the whole session appears at once when the scan ends
    resume : continue the session at ``out`` with its next view (same devices, patterns)
    calibration : the rig's calibration to record (:class:`slscan.rig.Rig`), or None
    on_frame : called after each frame is written (live logging)
    after_view : called with (view index, its record, the session so far) once a view is
        complete on disk (a quick decode, a prompt)
    progress : called with a short label after each image
    """
    if views < 1:
        raise DeviceError(f"views must be at least 1, got {views}")
    proj, cam, lights, stage = devices.projector, devices.camera, devices.lights, devices.stage
    for p in plan.patterns:
        if (p.width, p.height) != proj.resolution:
            raise DeviceError(
                f"{proj.name}: the projector is {proj.resolution[0]}x{proj.resolution[1]}, pattern {p.id!r} "
                f"is {p.width}x{p.height} (make the patterns for the projector's native resolution)"
            )
    n_lights = _plan_lights(plan, lights)
    images = [render(p) for p in plan.patterns]
    quality = cam.jpeg_quality
    records = capture_records(plan.patterns, n_lights, jpeg=quality is not None)
    writer = SessionWriter(
        out, camera_size=cam.resolution, projector_size=proj.resolution, channels=cam.channels,
        bit_depth=cam.bit_depth, patterns=list(plan.patterns), calibration=calibration,
        calibration_source=calibration_source, device=device_info or devices.describe(),
        overwrite=overwrite, incremental=incremental, resume=resume, jpeg_quality=quality,
        response=cam.response,
    )
    timings: list[ViewTiming] = []
    shooter = _Shooter(devices, plan)
    with writer:
        done = len(writer.views)
        if resume and done >= views:
            log.warning("%s: already has %d view(s) of %d; nothing to capture", out, done, views)
        for v in range(done, views):
            name = f"view_{v:03d}"
            timing = ViewTiming(name, len(records))
            where = f"{name} (moving the object into place)"
            try:
                t = time.perf_counter()
                placement = stage.move_to(v, views)
                timing.move = time.perf_counter() - t
                shooter.previous = None
                lights.all_off()
                if plan.reference_frame and plan.stale_retries:
                    shooter.shoot(proj.blank, timing, f"{name} reference frame (projector dark)",
                                  identical_only=True, label=f"view {v + 1}, reference frame (projector dark)")
                pattern_exposure = None  # what the lit images' exposure replaced, to restore exactly
                for frame_index, record in enumerate(records):
                    where = f"{name} image {record.file}"
                    label = f"view {v + 1}, frame {frame_index + 1} ({_frame_label(record)})"
                    if record.kind == "pattern":
                        shown = images[frame_index]
                        image = shooter.shoot(lambda img=shown: proj.show(img), timing, where, label=label)
                    else:
                        shown = None
                        if record.light == 0:
                            proj.blank()
                            pattern_exposure = _set_lit_exposure(cam, plan.lit_exposure)

                        def switch(k=record.light):
                            if k > 0:
                                lights.switch(k - 1, False)
                            lights.switch(k, True)

                        image = shooter.shoot(switch, timing, where, identical_only=True, label=label)
                    t = time.perf_counter()
                    writer.write_image(name, record, image)
                    timing.write += time.perf_counter() - t
                    if on_frame is not None:
                        on_frame(FrameCaptured(v, frame_index, record, image, shown))
                    if progress:
                        progress(f"{name} {record.file}")
                where = f"{name} (after its last image)"
                if n_lights:
                    lights.switch(n_lights - 1, False)
                    if pattern_exposure is not None:
                        cam.set_controls(exposure=pattern_exposure)
                exposure = view_exposure(cam.exposure_record(), plan)
                gt = stage.ground_truth()
                gt_file = None
                if gt is not None:
                    gt_file = "ground_truth.npz"
                    gt.save(writer.view_folder(name) / gt_file)
                record = ViewRecord(name, tuple(records), placement.rig_from_object, placement.pose_source,
                                    exposure, gt_file, placement.turntable_deg)
                t = time.perf_counter()
                writer.add_view(record)
                timing.write += time.perf_counter() - t
            except BaseException as exc:
                writer.discard_view(name)
                if not isinstance(exc, DeviceError):
                    raise
                message = str(exc) if str(exc).startswith(name) else f"{where}: {exc}"
                if incremental and v > 0:
                    message += f" ({v} finished view(s) kept in {out}; --resume continues with {name})"
                raise type(exc)(message) from None
            timings.append(timing)
            if after_view is not None:
                after_view(v, record, writer.session())
        proj.blank()
    return ScanResult(writer.session(), tuple(timings), done)


def _frame_label(record: ImageRecord) -> str:
    """What a frame shows, for the operator: the pattern's id ("white", "gray-col-3") or
    "ring light 2 on" (numbered from 1)."""
    return record.pattern if record.kind == "pattern" else f"ring light {record.light + 1} on"


def capture_records(patterns, n_lights: int, *, jpeg: bool = False) -> list[ImageRecord]:
    """The records of one view's captures: each pattern in order, then one per ring light;
    files ``.jpg`` when the camera saves JPEG."""
    records = [ImageRecord(file_name(i, p), "pattern", pattern=p.id) for i, p in enumerate(patterns)]
    records += [ImageRecord(f"{len(records) + k:02d}_lit-{k}.png", "lit", light=k) for k in range(n_lights)]
    if jpeg:
        records = [dataclasses.replace(r, file=r.file.removesuffix(".png") + ".jpg") for r in records]
    return records


def _set_lit_exposure(cam: Camera, factor: float) -> float | None:
    """Scale the camera's exposure by ``factor`` for the lit images; the exposure it had
    (to set back exactly, not divided: ``e * f / f`` drifts by an ulp view after view), or
    None when nothing changed."""
    if factor == 1.0:
        return None
    if "exposure" not in cam.controls():
        log.warning("%s: the camera's exposure cannot be set; lit images use the pattern exposure", cam.name)
        return None
    e = cam.get_controls()["exposure"]
    cam.set_controls(exposure=e * factor)
    return e


def view_exposure(camera_record: dict, plan: ScanPlan) -> dict:
    """A view's ``exposure`` record in ``session.json``: the camera's settings for the
    pattern images and how the lit images and the waits differed."""
    return {**camera_record, "lit_exposure": plan.lit_exposure, "settle_s": plan.settle_s}


# --- latency ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Latency:
    """Projector→camera delay measured by flashing white after black.

    delays : seconds from ``show`` returning to the first frame that saw the white, one
        per flash (an upper bound: it includes the capture's own duration)
    frame_s : median seconds per captured frame while waiting
    settle_s : the settle time to use: the largest delay (conservative: a frame whose
        exposure began before the change would mix the two images)
    """

    delays: tuple[float, ...]
    frame_s: float
    settle_s: float


def _grey(image: np.ndarray) -> np.ndarray:
    full = 255.0 if image.dtype == np.uint8 else 65535.0
    grey = image[::2, ::2]
    return (grey.mean(axis=2) if grey.ndim == 3 else grey).astype(np.float32) / np.float32(full)


def measure_latency(
    projector: Projector, camera: Camera, *, flashes: int = 3, timeout_s: float = 3.0, rest_s: float = 0.3,
) -> Latency:
    """Flash white after black ``flashes`` times and time when the camera first sees it.

    Only the pixels that the projector visibly lights (brighter by 10 % of full scale under
    white than under black) are watched, so a small object in a dark frame works too."""
    w, h = projector.resolution
    white = np.full((h, w, 3), 255, np.uint8)
    projector.show(white)
    time.sleep(rest_s)
    camera.flush()
    bright = _grey(camera.capture().image)
    projector.blank()
    time.sleep(rest_s)
    camera.flush()
    dark = _grey(camera.capture().image)
    lit = bright - dark > 0.1
    if lit.mean() < 1e-3:
        raise DeviceError(
            f"{camera.name}: cannot measure the projector latency: the projected white lights no part of what "
            "the camera sees; point the camera at the projected area (or give --settle SECONDS)"
        )
    middle = 0.5 * (float(bright[lit].mean()) + float(dark[lit].mean()))
    delays, frame_times = [], []
    for _ in range(flashes):
        projector.blank()
        time.sleep(rest_s)
        camera.flush()
        shown = projector.show(white)
        previous = time.monotonic()
        while True:
            frame = camera.capture()
            frame_times.append(frame.timestamp - previous)
            previous = frame.timestamp
            if float(_grey(frame.image)[lit].mean()) > middle:
                delays.append(max(0.0, frame.timestamp - shown))
                break
            if frame.timestamp - shown > timeout_s:
                raise DeviceError(f"{camera.name}: the projected white did not reach the camera within "
                                  f"{timeout_s:g} s")
    projector.blank()
    return Latency(tuple(delays), float(np.median(frame_times)), max(delays))


# --- exposure (paper Fig. 9) -------------------------------------------------------------------


@dataclass(frozen=True)
class ExposureTrial:
    controls: dict[str, float]
    clipped_share: float
    peak: float  # 99.9th percentile of the lit pixels, fraction of full scale


@dataclass(frozen=True)
class ExposureResult:
    """What :func:`find_exposure` chose and measured.

    controls : the camera controls set (empty when the camera has none)
    clipped_share : share of lit pixel channels at full scale, in the white frame and the
        green channel of the finest line pattern
    peak : 99.9th percentile of those, fraction of full scale
    ok : no setting left more than ``max_clipped`` clipped and the peak is well above the noise
    message : one line for the user
    trials : every setting tried, in order
    """

    controls: dict[str, float]
    clipped_share: float
    peak: float
    ok: bool
    message: str
    trials: tuple[ExposureTrial, ...]


def finest_pattern(patterns) -> PatternImage | None:
    """The pattern with the finest detail of the set's first family in "auto" order (the
    last hybrid level, the last Gray bit, the shortest fringe period), which exposure and
    focus checks look at."""
    for fam in families_in(patterns):
        found = fam.finest(patterns) if fam.finest is not None else None
        if found is not None:
            return found
    return None


def _exposure_stats(white: np.ndarray, lines: np.ndarray | None, dark: np.ndarray) -> tuple[float, float]:
    full = 255.0 if white.dtype == np.uint8 else 65535.0
    grey_white = white.max(axis=2) if white.ndim == 3 else white
    grey_dark = dark.max(axis=2) if dark.ndim == 3 else dark
    lit = grey_white.astype(np.float32) > grey_dark.astype(np.float32) + 0.05 * full
    if not lit.any():
        lit = np.ones_like(lit)
    values = [white[lit].ravel()]
    if lines is not None:
        values.append((lines[..., 1] if lines.ndim == 3 else lines)[lit].ravel())
    v = np.concatenate(values)
    return float((v >= full).mean()), float(np.percentile(v, 99.9)) / full


PEAK_NEAR = 0.9
"""Auto-exposure stops at an unclipped trial whose peak is at least this share of the target
(0.9 × 85 % = 76.5 %); it stopped at 0.7 (59.5 %), which left the virtual camera's default
exposure (peak 68 %) where it was, 17 points under the 85 % the docs promise."""


def shoot_once(projector: Projector, camera: Camera, image: np.ndarray | None, *, settle_s: float,
               label: str) -> np.ndarray:
    """Show ``image`` (None: blank), wait ``settle_s``, and capture one fresh frame; ``label``
    tells a camera that must be triggered by hand what the shot is. The camera's pixels."""
    projector.blank() if image is None else projector.show(image)
    if settle_s:
        time.sleep(settle_s)
    camera.flush()
    camera.about_to_capture(label)
    return camera.capture().image


def find_exposure(
    projector: Projector,
    camera: Camera,
    patterns,
    *,
    max_clipped: float = 1e-3,
    target_peak: float = 0.85,
    min_peak: float = 0.25,
    settle_s: float = 0.0,
    max_trials: int = 12,
    search: bool = True,
) -> ExposureResult:
    """Find an exposure (then gain) for which the white frame and the finest green lines
    stay below saturation (at most ``max_clipped`` of the lit pixel channels at full
    scale) with their peak near ``target_peak`` of full scale (at least :data:`PEAK_NEAR`
    of it, unless no unclipped setting gets there) and above ``min_peak``.

    Cameras without an exposure control, or ``search=False``, are measured as they are.
    Raises nothing: the result says whether it succeeded (``ok``) and why not.
    """
    w, h = projector.resolution
    finest = finest_pattern(patterns)
    white_img = np.full((h, w, 3), 255, np.uint8)
    lines_img = render(finest) if finest is not None else None
    controls = camera.controls()
    trials: list[ExposureTrial] = []

    def measure() -> ExposureTrial:
        shots = []
        for name, img in (("black", None), ("white", white_img), ("finest pattern", lines_img)):
            if img is None and shots:
                continue
            shots.append(shoot_once(projector, camera, img, settle_s=settle_s, label=f"exposure check, {name}"))
        dark, white = shots[0], shots[1]
        lines = shots[2] if len(shots) > 2 else None
        clipped, peak = _exposure_stats(white, lines, dark)
        trial = ExposureTrial(camera.get_controls(), clipped, peak)
        trials.append(trial)
        return trial

    trial = measure()
    if search and "exposure" in controls:
        lo, hi = controls["exposure"]
        good: ExposureTrial | None = None  # the brightest unclipped setting seen
        bad: float | None = None  # the darkest clipped exposure seen
        while len(trials) < max_trials:
            e = trial.controls["exposure"]
            if trial.clipped_share > max_clipped:
                bad = e if bad is None else min(bad, e)
                nxt = e / 4 if good is None else math.sqrt(e * good.controls["exposure"])
            else:
                if good is None or e > good.controls["exposure"]:
                    good = trial
                if trial.peak >= PEAK_NEAR * target_peak:
                    break
                scale = target_peak / max(trial.peak, 1e-3)
                nxt = e * min(scale, 8.0)
                if bad is not None:
                    nxt = min(nxt, math.sqrt(e * bad))
            nxt = min(max(nxt, lo), hi)
            if math.isclose(nxt, e, rel_tol=0.02):
                break
            camera.set_controls(exposure=nxt)
            trial = measure()
        if good is not None and good is not trial:
            camera.set_controls(exposure=good.controls["exposure"])
            trial = good
        if (trial.clipped_share <= max_clipped and trial.peak < min_peak and "gain" in controls
                and math.isclose(trial.controls["exposure"], hi, rel_tol=0.02)):
            glo, ghi = controls["gain"]
            gain = min(ghi, max(glo, trial.controls.get("gain", glo) * target_peak / max(trial.peak, 1e-3)))
            camera.set_controls(gain=gain)
            trial = measure()
    full_name = f"{camera.name} at {', '.join(f'{k} {v:g}' for k, v in trial.controls.items()) or 'its settings'}"
    if trial.clipped_share > max_clipped:
        ok = False
        if not search:
            what = "lower the exposure (--auto-exposure searches for one)"
        elif "exposure" in controls:
            what = "no exposure the camera allows avoids it"
        else:
            what = "the camera's exposure cannot be set"
        message = (f"{100 * trial.clipped_share:.2f} % of the lit pixels are saturated ({full_name}); {what}: "
                   "dim the projector or close the lens aperture (paper Fig. 9)")
    elif trial.peak < min_peak:
        ok = False
        message = (f"the brightest lit pixels reach only {100 * trial.peak:.0f} % of full scale ({full_name}): "
                   "the green lines will be close to the noise; brighten the projector or open the aperture")
    else:
        ok = True
        message = (f"{full_name}: peak {100 * trial.peak:.0f} % of full scale, "
                   f"{100 * trial.clipped_share:.3f} % clipped")
    projector.blank()
    return ExposureResult(trial.controls, trial.clipped_share, trial.peak, ok, message, tuple(trials))
