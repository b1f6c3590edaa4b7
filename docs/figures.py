"""Regenerate the pictures in docs/images from a full-size capture session of the figurine
(1440x960, as ``slscan capture --out SESSION`` writes by default; the demo captures at half
size, which the crops below do not fit): .venv/bin/python docs/figures.py SESSION

The scan_*.png of docs/scanning.md need no session (they scan the virtual rig, and open the
projector window on a private Xvfb): .venv/bin/python docs/figures.py scan

codes_kamino410.png of docs/reconstruction.md decodes the kamino410 capture_0 in
../shared/data (or $SLSCAN_DATA): .venv/bin/python docs/figures.py codes

The effect_*.png of docs/virtual-rig.md render the virtual rig at half size, each effect
off and on: .venv/bin/python docs/figures.py optics
The effect_*.png and scene_*.png of docs/virtual-rig.md render the light-transport scenes
at half size with each effect off and on: .venv/bin/python docs/figures.py transport

paper_scale_views.png and paper_scale_model.png of docs/paper-scale.md show a
``benchmarks/paper_scale.py`` run's campaign and its textured model:
.venv/bin/python docs/figures.py paper-scale WORK"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from slscan.capture.session import load_session
from slscan.viewer.log import projector_column_image

CROP = (slice(190, 770), slice(410, 1010))  # the figurine in the default 1440x960 view


def save(name: str, rgb: np.ndarray) -> None:
    out = Path(__file__).parent / "images" / name
    small = cv2.resize(rgb[CROP], None, fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(out), np.ascontiguousarray(small[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def main(session_dir: str) -> None:
    s = load_session(session_dir)
    view = s.views[0]
    for pid, name in (("white", "capture_white.png"), ("hybrid-04", "capture_hybrid_level4.png")):
        save(name, s.read_image(view, view.image_for(pid)))
    save("capture_lit_0.png", s.read_image(view, view.lit_images()[0]))
    truth = s.load_ground_truth(view)
    save("truth_projector_column.png", projector_column_image(truth.projector_uv[..., 0], s.projector_size[0]))
    vis = np.array([[0, 0, 0], [60, 60, 150], [255, 210, 60]], np.uint8)[truth.visibility]
    save("truth_visibility.png", vis)
    crop = s.read_image(view, view.image_for("hybrid-09"))[430:490, 700:760]
    zoom = cv2.resize(crop, None, fx=6, fy=6, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(Path(__file__).parent / "images" / "capture_hybrid_level9_zoom.png"), zoom[..., ::-1])


# --- slscan scan (docs/scanning.md) ------------------------------------------------------

IMAGES = Path(__file__).parent / "images"
LOOP_PATTERN = "hybrid-04"  # coarse enough to read when the 1024 px window is shown 480 px wide
LOOP_ZOOM = (slice(380, 404), slice(436, 460))  # around the green line at projector column 448
PANEL_HEIGHT = 360  # px, each panel of a side-by-side figure
PROFILE_ROW, PROFILE_COLS = 520, slice(750, 790)  # camera px across the finest green lines (full size)
MAGENTA = np.array([255, 40, 200], np.uint8)  # holes, as slscan.viewer.log_scan.HOLE_COLOR
RED = np.array([255, 0, 0], np.uint8)


def _write(name: str, rgb: np.ndarray) -> None:
    cv2.imwrite(str(IMAGES / name), np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def _to_height(rgb: np.ndarray, height: int, interpolation: int = cv2.INTER_AREA) -> np.ndarray:
    return cv2.resize(rgb, (round(rgb.shape[1] * height / rgb.shape[0]), height), interpolation=interpolation)


def _titled(rgb: np.ndarray, *lines: str, scale: float = 0.5) -> np.ndarray:
    """``rgb`` under a white band holding ``lines`` of black text."""
    step = round(40 * scale) + 4
    band = np.full((step * len(lines) + 6, rgb.shape[1], 3), 255, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(band, line, (6, step * (i + 1) - 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([band, rgb])


def _side_by_side(*panels: np.ndarray, gap: int = 10) -> np.ndarray:
    height = max(p.shape[0] for p in panels)
    padded = [np.pad(p, ((0, height - p.shape[0]), (0, 0), (0, 0)), constant_values=255) for p in panels]
    spacer = np.full((height, gap, 3), 255, np.uint8)
    out = [padded[0]]
    for p in padded[1:]:
        out += [spacer, p]
    return np.hstack(out)


class _PrivateXvfb:
    """``Xvfb :N -screen 0 WxHx24`` on a free display number, as ``$DISPLAY`` while in use."""

    def __init__(self, width: int, height: int, first: int = 80) -> None:
        self.size, self.first = (width, height), first

    def __enter__(self) -> str:
        import os
        import subprocess
        import time

        n = next(n for n in range(self.first, self.first + 100)
                 if not Path(f"/tmp/.X11-unix/X{n}").exists() and not Path(f"/tmp/.X{n}-lock").exists())
        self.name = f":{n}"
        w, h = self.size
        self.proc = subprocess.Popen(["Xvfb", self.name, "-screen", "0", f"{w}x{h}x24", "-nolisten", "tcp"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 20
        while not Path(f"/tmp/.X11-unix/X{n}").exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"Xvfb {self.name} did not start")
            time.sleep(0.05)
        time.sleep(0.2)
        self.saved = os.environ.get("DISPLAY")
        os.environ["DISPLAY"] = self.name
        return self.name

    def __exit__(self, *exc: object) -> None:
        import os

        if self.saved is None:
            os.environ.pop("DISPLAY", None)
        else:
            os.environ["DISPLAY"] = self.saved
        self.proc.terminate()
        self.proc.wait(timeout=10)


def scan_loop_figure() -> None:
    """scan_loop.png: the projector window as the X server shows it (a screen grab of a hybrid
    pattern on a private Xvfb), and the closed loop's camera frame of the figurine lit by that grab."""
    from slscan.devices.screen import ScreenProjector, grab_screen
    from slscan.patterns import render
    from slscan.virtual.device import VirtualCaptureConfig, virtual_devices
    from slscan.virtual.devices import ScreenLoopCamera

    config = VirtualCaptureConfig()  # full size: the 1024x768 projector fits the 1024x768 screen
    world = virtual_devices(config)
    pattern = next(p for p in config.pattern_set(world.rig) if p.id == LOOP_PATTERN)
    with _PrivateXvfb(1024, 768), ScreenProjector(0) as projector:
        projector.show(render(pattern))
        screen = grab_screen(projector)
        world.stage.move_to(0, 1)
        camera = ScreenLoopCamera(world, lambda: grab_screen(projector), world.camera.sensor)
        frame = camera.capture().image
    exact = "pixel for pixel the pattern" if np.array_equal(screen, render(pattern)) else "NOT the pattern"
    left = _to_height(screen, PANEL_HEIGHT)
    zoom = cv2.resize(screen[LOOP_ZOOM], None, fx=6, fy=6, interpolation=cv2.INTER_NEAREST)
    zoom = _titled(zoom, "6x: the 1 px", "green line", scale=0.4)
    zh, zw = zoom.shape[:2]
    left[-zh - 12:-12, 10:10 + zw] = np.pad(zoom, ((2, 2), (2, 2), (0, 0)), constant_values=255)[2:-2, 2:-2]
    cv2.rectangle(left, (8, left.shape[0] - zh - 14), (11 + zw, left.shape[0] - 11), (255, 255, 255), 2)
    left = _titled(left, f"projector window, screen grab ({LOOP_PATTERN})", f"1024x768 on Xvfb: {exact}")
    right = _titled(_to_height(frame[CROP], PANEL_HEIGHT), "fake camera (--camera loop): the figurine",
                    "lit by that grab (1440x960 frame, cropped)")
    _write("scan_loop.png", _side_by_side(left, right))


def scan_quick_decode_figure() -> None:
    """scan_quick_decode.png: a view's white frame with the quick decode's holes (decodable
    pixels no range-map triangle covers) in magenta, the coverage in the title."""
    import tempfile

    from slscan.cli import main as slscan
    from slscan.decode.pipeline import decode_view
    from slscan.decode.rangemap import covered_pixels

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "scan"
        if slscan(["scan", "--camera", "virtual", "--scale", "0.5", "--out", str(out), "--quiet"]) != 0:
            raise RuntimeError("slscan scan --camera virtual failed")
        s = load_session(out)
        view = s.views[0]
        result = decode_view(s, view)
        white = s.read_image(view, view.image_for("white"))
    covered = covered_pixels(result.range_map, s.calibration.camera, result.mask.shape)
    holes = result.mask & ~covered
    coverage = float(covered[result.mask].mean())
    shown = white.copy()
    shown[holes] = (0.35 * shown[holes] + 0.65 * MAGENTA).astype(np.uint8)
    half = (slice(CROP[0].start // 2, CROP[0].stop // 2), slice(CROP[1].start // 2, CROP[1].stop // 2))
    panel = cv2.resize(shown[half], None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    title = (f"{view.name}: {len(result.range_map.vertices):,} vertices, {100 * coverage:.1f} % of the",
             "decodable pixels covered; magenta: holes")
    _write("scan_quick_decode.png", _titled(panel, *title))


def _profile_plot(curves: list[tuple[np.ndarray, tuple[int, int, int], str]], width: int, height: int,
                  full: float) -> np.ndarray:
    """A small line plot of (values, colour, label) curves on 0..``full``, drawn with OpenCV."""
    plot = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 46, 10, 10, 24
    x0, x1, y0, y1 = left, width - right, top, height - bottom

    def y(v):
        return np.round(y1 - (y1 - y0) * np.asarray(v, float) / full).astype(np.int32)

    cv2.rectangle(plot, (x0, y0), (x1, y1), (160, 160, 160), 1)
    cv2.line(plot, (x0, int(y(full))), (x1, int(y(full))), (200, 0, 0), 1)
    for v in (0, full / 2, full):
        cv2.putText(plot, f"{v:.0f}", (4, int(y(v)) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for k, (values, colour, label) in enumerate(curves):
        xs = np.round(np.linspace(x0, x1, len(values))).astype(np.int32)
        pts = np.stack([xs, y(values)], axis=1).reshape(-1, 1, 2)
        cv2.polylines(plot, [pts], False, colour, 2, cv2.LINE_AA)
        for (px, py) in pts[:, 0]:
            cv2.circle(plot, (int(px), int(py)), 3, colour, -1, cv2.LINE_AA)
        cv2.putText(plot, label, (x0 + 8 + k * (x1 - x0) // 2, y1 + 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1,
                    cv2.LINE_AA)
    return plot


def scan_exposure_figure() -> None:
    """scan_exposure.png: the white frame at exposure 6 with saturated pixels in red, next to
    the exposure find_exposure chose; below, the green channel across the finest lines at both
    (paper Fig. 9: clipped lines lose the profile their sub-pixel centre is found from)."""
    from slscan.capture.driver import find_exposure, finest_pattern
    from slscan.patterns import render
    from slscan.virtual.device import VirtualCaptureConfig, virtual_devices
    from slscan.virtual.sensor import Sensor

    config = VirtualCaptureConfig(sensor=Sensor(exposure=6))
    world = virtual_devices(config)
    world.stage.move_to(0, 1)
    patterns = config.pattern_set(world.rig)
    proj, cam = world.projector, world.camera
    white_img = np.full((proj.resolution[1], proj.resolution[0], 3), 255, np.uint8)
    lines_img = render(finest_pattern(patterns))

    def shoot(image):
        proj.show(image)
        return cam.capture().image

    before = shoot(white_img), shoot(lines_img)
    result = find_exposure(proj, cam, patterns)
    after = shoot(white_img), shoot(lines_img)
    full = 2**cam.bit_depth - 1
    panels = []
    for (white, _), exposure in ((before, 6.0), (after, result.controls["exposure"])):
        clipped = (white >= full).any(axis=2)
        shown = white.copy()
        shown[clipped] = RED
        share = float(clipped[white.max(axis=2) > 0.05 * full].mean())
        panels.append(_titled(_to_height(shown[CROP], PANEL_HEIGHT),
                              f"white frame at exposure {exposure:.3g}",
                              f"red: saturated ({100 * share:.1f} % of the lit pixels)"))
    top = _side_by_side(*panels)
    curves = [(before[1][PROFILE_ROW, PROFILE_COLS, 1], (220, 0, 0), "exposure 6: clipped flat tops"),
              (after[1][PROFILE_ROW, PROFILE_COLS, 1], (0, 150, 0),
               f"exposure {result.controls['exposure']:.3g}: full profiles")]
    plot = _profile_plot(curves, top.shape[1], 200, full)
    plot = _titled(plot, f"green channel of the finest lines ({finest_pattern(patterns).id}), camera row "
                   f"{PROFILE_ROW}, columns {PROFILE_COLS.start}-{PROFILE_COLS.stop - 1}; red line: full scale")
    _write("scan_exposure.png", np.vstack([top, np.full((10, top.shape[1], 3), 255, np.uint8), plot]))


def scan_board_figure() -> None:
    """scan_board.png: a calibration capture's white frame with the board corners found live
    (yellow) and the 4x4 image cells that corners have reached so far (green) or not yet (grey)."""
    import tempfile

    from slscan.calibrate.camera import detect_corners
    from slscan.calibrate.target import Board
    from slscan.cli import main as slscan

    board = Board(kind="chessboard", columns=9, rows=7, square=50.0)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "board"
        if slscan(["scan", "--camera", "virtual", "--board", "9x7", "--square", "50", "--views", "6",
                   "--out", str(out), "--quiet"]) != 0:
            raise RuntimeError("slscan scan --board failed")
        s = load_session(out)
        whites = [(v.name, s.read_image(v, v.image_for("white"))) for v in s.views]
    cover = np.zeros((4, 4), bool)
    for name, white in whites:
        found = detect_corners(white, board)
        h, w = white.shape[:2]
        cells = np.clip((found.corners / [w / 4, h / 4]).astype(int), 0, 3)
        cover[cells[:, 1], cells[:, 0]] = True
    shown = white.astype(np.float32)
    for r in range(4):
        for c in range(4):
            cell = (slice(r * h // 4, (r + 1) * h // 4), slice(c * w // 4, (c + 1) * w // 4))
            tint = np.array([60, 200, 60] if cover[r, c] else [120, 120, 120], np.float32)
            shown[cell] = 0.7 * shown[cell] + 0.3 * tint
    shown = shown.astype(np.uint8)
    for k in range(1, 4):
        cv2.line(shown, (k * w // 4, 0), (k * w // 4, h - 1), (255, 255, 255), 1)
        cv2.line(shown, (0, k * h // 4), (w - 1, k * h // 4), (255, 255, 255), 1)
    for x, y in found.corners:
        cv2.circle(shown, (round(x), round(y)), 4, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.circle(shown, (round(x), round(y)), 3, (255, 220, 0), -1, cv2.LINE_AA)
    _write("scan_board.png", _titled(shown, f"{name}: board found, {len(found.ids)} corners (yellow);",
                                     f"corners seen so far in {int(cover.sum())} of 16 image cells (green cells)"))


def scan_figures() -> None:
    scan_loop_figure()
    scan_quick_decode_figure()
    scan_exposure_figure()
    scan_board_figure()


# --- slscan decode --codes (docs/reconstruction.md) ---------------------------------------

CODES_HEIGHT = 300  # px, each panel (the maps are speckled at edges: PNG size grows fast)


def codes_figure() -> None:
    """codes_kamino410.png: the white capture of kamino410's capture_0 beside the projector
    column and row maps ``slscan decode --codes`` writes for it (Turbo, black: not decoded)."""
    import tempfile

    from slscan.capture.kamino410 import import_kamino410
    from slscan.data import shared_data_dir
    from slscan.decode.codes import decode_codes

    data = shared_data_dir()
    src = None if data is None else data / "procam_graycode_kamino410" / "sample_data" / "capture_0"
    if src is None or not src.is_dir():
        sys.exit(f"kamino410 capture_0 not found at {src}: set SLSCAN_DATA")
    with tempfile.TemporaryDirectory() as tmp:
        session = import_kamino410(src, Path(tmp) / "session")
        view = session.views[0]
        white = session.read_image(view, view.image_for("white"))
        codes = decode_codes(session, view)
    white = np.repeat(white[..., None], 3, axis=2) if white.ndim == 2 else white
    w, h = codes.projector_size
    column = projector_column_image(np.where(codes.column >= 0, codes.column, np.nan), w - 1)
    row = projector_column_image(np.where(codes.row >= 0, codes.row, np.nan), h - 1)
    panels = [
        _titled(_to_height(white, CODES_HEIGHT), "white capture (1280x1024)"),
        _titled(_to_height(column, CODES_HEIGHT), f"columns.png: projector column 0..{w - 1}"),
        _titled(_to_height(row, CODES_HEIGHT), f"rows.png: projector row 0..{h - 1}"),
    ]
    _write("codes_kamino410.png", _side_by_side(*panels))


# --- lens and sensor effects (docs/virtual-rig.md) ----------------------------------------

EFFECT_HEIGHT = 300  # px, each panel
HALF_CROP = (slice(95, 385), slice(205, 505))  # the figurine in the half-size 720x480 view


def _effect_capture(effects, pattern: str, *, scene: str = "object", optics=None, sensor=None) -> np.ndarray:
    """One half-size capture of ``pattern`` (a pattern id) with ``effects`` on."""
    import dataclasses

    from slscan.virtual.device import VirtualCaptureConfig, capture_view
    from slscan.virtual.devices import turntable_pose

    config = VirtualCaptureConfig(scene=scene, camera_scale=0.5, projector_scale=0.5, levels=8, patterns="both",
                                  lit_images=False, effects=effects)
    if optics or sensor:
        config = dataclasses.replace(config, optics=dataclasses.replace(config.optics, **(optics or {})),
                                     sensor=dataclasses.replace(config.sensor, **(sensor or {})))
    rig = config.rig()
    world = config.build_scene()
    desc = next(p for p in config.pattern_set(rig) if p.id == pattern)
    images, _ = capture_view(world, rig, turntable_pose(rig, 0.0, world.placement), [desc], config)
    return images[0][1]


def optics_figures() -> None:
    """effect_dof.png, effect_tone.png, effect_vignetting.png, effect_jpeg.png: each effect off
    and on, side by side (half-size captures)."""
    fine = "hybrid-08"  # the finest lines at half size
    zoom = (slice(190, 250), slice(330, 410))  # camera px of the half-size view: lines on the body
    off, on = _effect_capture((), fine), _effect_capture(("dof",), fine, optics={"projector_fnumber": 1.0,
                                                                                  "projector_focus_mm": 1100.0})
    panels = [_titled(_to_height(im[HALF_CROP], EFFECT_HEIGHT), t) for im, t in
              ((off, "dof off (pinhole projector)"), (on, "dof: f/1, focus 1100 mm"))]
    panels += [_titled(_to_height(im[zoom], EFFECT_HEIGHT, cv2.INTER_NEAREST), t) for im, t in
               ((off, "off, zoomed"), (on, "f/1, zoomed"))]
    _write("effect_dof.png", _side_by_side(*panels))

    pattern = "hybrid-04"
    off, on = _effect_capture((), pattern), _effect_capture(("tone",), pattern)
    _write("effect_tone.png", _side_by_side(
        _titled(_to_height(off[HALF_CROP], EFFECT_HEIGHT), "linear projector, RAW camera"),
        _titled(_to_height(on[HALF_CROP], EFFECT_HEIGHT), "tone: gamma 2.2, sRGB camera")))

    from slscan.rig import default_rig
    from slscan.virtual.sensor import Sensor, cos4_map

    camera = default_rig(scale=0.5).camera
    flat = np.full((camera.height, camera.width, 3), 1.4, np.float32)  # a uniform white wall
    sensor = Sensor(noise=False)
    on = _effect_capture(("vignetting",), "white", scene="tile")
    corner = float(cos4_map(camera)[0, 0])
    _write("effect_vignetting.png", _side_by_side(
        _titled(_to_height(sensor.expose(flat, camera=camera), EFFECT_HEIGHT), "flat field: no vignetting"),
        _titled(_to_height(Sensor(noise=False, vignetting=1.0).expose(flat, camera=camera), EFFECT_HEIGHT),
                f"vignetting: cos^4 law (corner {corner:.2f})"),
        _titled(_to_height(on, EFFECT_HEIGHT), "white frame of the tile, vignetting on")))

    off, on = _effect_capture((), fine), _effect_capture(("jpeg",), fine)
    diff = np.clip(np.abs(on.astype(np.int16) - off.astype(np.int16)) * 8, 0, 255).astype(np.uint8)
    _write("effect_jpeg.png", _side_by_side(*[
        _titled(_to_height(im[zoom], EFFECT_HEIGHT, cv2.INTER_NEAREST), t) for im, t in
        ((off, "PNG, zoomed"), (on, "JPEG quality 90"), (diff, "|difference| x 8"))]))
# --- light transport (docs/virtual-rig.md) ----------------------------------------------

TRANSPORT_SCALE = 0.5  # reduced-size captures: 720x480 camera, 512x384 projector


def _capture_images(scene: str, effects: tuple[str, ...], pattern_ids: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The named images of view 0 of ``scene`` at :data:`TRANSPORT_SCALE`, RGB uint8."""
    from slscan.virtual.device import VirtualCaptureConfig, capture_view, turntable_pose

    config = VirtualCaptureConfig(scene=scene, camera_scale=TRANSPORT_SCALE, projector_scale=TRANSPORT_SCALE,
                                  levels=8, effects=effects, lit_images=False, patterns="both")
    rig, world = config.rig(), config.build_scene()
    patterns = [p for p in config.pattern_set(rig) if p.id in pattern_ids]
    images, _ = capture_view(world, rig, turntable_pose(rig, 0.0, world.placement), patterns, config)
    return {p.id: image for p, (_, image) in zip(patterns, images)}


def _crop_box(image: np.ndarray, margin: int = 12) -> tuple[slice, slice]:
    ys, xs = np.nonzero(image.max(axis=2) > 8)
    return (slice(max(0, ys.min() - margin), ys.max() + margin),
            slice(max(0, xs.min() - margin), xs.max() + margin))


def transport_figures() -> None:
    """effect_subsurface.png, effect_interreflection.png and scene_{concave,marble,bronze}.png."""
    # subsurface: the finest hybrid lines on the marble head, zoomed 3x
    ids = ("white", "hybrid-08")
    off, on = _capture_images("marble", (), ids), _capture_images("marble", ("subsurface",), ids)
    box = (slice(95, 175), slice(300, 420))
    zoom = lambda img: cv2.resize(img[box], None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    _write("effect_subsurface.png", _side_by_side(
        _titled(zoom(off["hybrid-08"]), "marble head, hybrid level 8: direct light"),
        _titled(zoom(on["hybrid-08"]), "subsurface on (mean free path 1.5 mm)")))

    # inter-reflection: the cube corner under white and under the coarsest and finest Gray bits
    ids = ("white", "gray-col-00", "gray-col-08")
    off, on = _capture_images("concave", (), ids), _capture_images("concave", ("interreflection",), ids)
    box = _crop_box(off["white"])
    panels = []
    for pid, label in (("white", "white"), ("gray-col-00", "Gray bit 0"), ("gray-col-08", "Gray bit 8")):
        pair = np.vstack([off[pid][box], np.full((6, off[pid][box].shape[1], 3), 255, np.uint8), on[pid][box]])
        panels.append(_titled(_to_height(pair, 360), f"{label}: direct (top),", "inter-reflection (bottom)"))
    _write("effect_interreflection.png", _side_by_side(*panels))

    # the scenes, every effect on: white and a hybrid pattern
    for scene in ("concave", "marble", "bronze"):
        images = _capture_images(scene, ("subsurface", "interreflection"), ("white", "hybrid-04"))
        box = _crop_box(images["white"])
        _write(f"scene_{scene}.png", _side_by_side(
            _titled(_to_height(images["white"][box], 300), f"{scene}: white"),
            _titled(_to_height(images["hybrid-04"][box], 300), "hybrid level 4")))


# --- the paper-scale run (docs/paper-scale.md) ---------------------------------------------


def _render_mesh(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray, eye: np.ndarray, target: np.ndarray,
                 size: tuple[int, int], fov_deg: float = 40.0) -> np.ndarray:
    """A pinhole picture of a vertex-coloured mesh (ray cast, head light, Lambert), RGB uint8."""
    import open3d as o3d
    import open3d.core as o3c

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3c.Tensor(vertices.astype(np.float32)), o3c.Tensor(faces.astype(np.uint32)))
    w, h = size
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    f = 0.5 * w / np.tan(np.radians(fov_deg) / 2)
    u, v = np.meshgrid(np.arange(w) - w / 2 + 0.5, np.arange(h) - h / 2 + 0.5)
    dirs = (u[..., None] * x + v[..., None] * y + f * z).reshape(-1, 3)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rays = np.hstack([np.broadcast_to(eye, dirs.shape), dirs]).astype(np.float32)
    hit = scene.cast_rays(o3c.Tensor(rays))
    tri = hit["primitive_ids"].numpy().astype(np.int64)
    ok = np.isfinite(hit["t_hit"].numpy())
    normal = hit["primitive_normals"].numpy()
    shade = np.abs(np.sum(normal * dirs, axis=1))
    bary = hit["primitive_uvs"].numpy()
    out = np.full((h * w, 3), 255.0)
    t = faces[tri[ok]]
    b = bary[ok]
    colour = (colours[t[:, 0]] * (1 - b[:, :1] - b[:, 1:]) + colours[t[:, 1]] * b[:, :1] + colours[t[:, 2]] * b[:, 1:])
    out[ok] = 255 * np.clip(colour * (0.25 + 0.75 * shade[ok, None]), 0, 1)
    return out.reshape(h, w, 3).astype(np.uint8)


def paper_scale_figures(work: str) -> None:
    """paper_scale_views.png: the white frame of one view per ring of the campaign;
    paper_scale_model.png: the textured model (its vertex colours) from the front and
    from above."""
    import open3d as o3d

    work = Path(work)
    s = load_session(work / "capture")
    heights, picks = [], []
    for i, view in enumerate(s.views):  # the first view of each ring: where the look-at height changes
        key = round(float(view.rig_from_object[1, 3]))
        if key not in heights:
            heights.append(key)
            picks.append(i)
    panels = [_titled(_to_height(s.read_image(s.views[i], s.views[i].image_for("white")), 200), s.views[i].name)
              for i in picks]
    _write("paper_scale_views.png", _side_by_side(*panels[:4]) if len(panels) <= 4 else np.vstack([
        _side_by_side(*panels[:4]), np.full((10, _side_by_side(*panels[:4]).shape[1], 3), 255, np.uint8),
        _pad_to(_side_by_side(*panels[4:8]), _side_by_side(*panels[:4]).shape[1])]))
    mesh = o3d.io.read_triangle_mesh(str(work / "runs" / "local" / "textured" / "model_vertex_colors.ply"))
    v, f, c = np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_colors)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    height = float(v[:, 1].max() - v[:, 1].min())
    front = _render_mesh(v, f, c, centre + [0.0, 0.0, 2.6 * height], centre, (400, 720), fov_deg=15)
    above = _render_mesh(v, f, c, centre + [0.0, 1.6 * height, 1.6 * height], centre, (400, 720), fov_deg=19)
    _write("paper_scale_model.png", _side_by_side(_titled(front, "front"), _titled(above, "from above")))


def _pad_to(rgb: np.ndarray, width: int) -> np.ndarray:
    if rgb.shape[1] >= width:
        return rgb
    return np.hstack([rgb, np.full((rgb.shape[0], width - rgb.shape[1], 3), 255, np.uint8)])


if __name__ == "__main__":
    if sys.argv[1:2] == ["paper-scale"] and len(sys.argv) == 3:
        paper_scale_figures(sys.argv[2])
    elif sys.argv[1:] == ["transport"]:
        transport_figures()
    elif sys.argv[1:] == ["scan"]:
        scan_figures()
    elif sys.argv[1:] == ["codes"]:
        codes_figure()
    elif sys.argv[1:] == ["optics"]:
        optics_figures()
    else:
        main(sys.argv[1])
