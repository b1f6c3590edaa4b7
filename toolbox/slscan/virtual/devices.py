"""The virtual rig as devices: a projector, camera, ring lights and turntable that share
one simulated world, so a simulated scan runs through the same driver as a real one.

:class:`VirtualRig` holds the world (scene, rig, where the object is, what the projector
shows, which lights are on); its :attr:`~VirtualRig.projector`, :attr:`~VirtualRig.camera`,
:attr:`~VirtualRig.lights` and :attr:`~VirtualRig.stage` implement
:mod:`slscan.devices.base`. The camera renders whatever the projector shows *at the
moment of capture* (after the projector's latency), lit by the lights that are on.

:class:`ScreenLoopCamera` is a **fake camera for testing a real projector back-end**: it
renders the virtual scene lit by the image it reads back from the screen (a grab of the
projector window), not by the image the driver asked for, so a closed-loop scan checks
that the projector window shows every pattern pixel for pixel.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from slscan.devices.base import Camera, DeviceError, Frame, Lights, Placement, Projector, Stage
from slscan.rig import Rig, rotation_about_axis
from slscan.virtual.render import ViewGeometry, add_light, shade_image, trace_view
from slscan.virtual.scenes import Scene
from slscan.virtual.sensor import Sensor

EXPOSURE_RANGE = (1 / 64, 64.0)  # relative exposure the virtual camera accepts
GAIN_RANGE = (1.0, 16.0)


def turntable_pose(rig: Rig, angle_deg: float, placement: np.ndarray | None = None) -> np.ndarray:
    """``rig_from_object`` of an object standing on the turntable at ``placement``
    (``turntable_from_object``; None: the identity) with the turntable turned ``angle_deg``
    about its vertical (y) axis; the turntable's centre is at the working distance on the
    camera axis (see :mod:`slscan.virtual.placement`)."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_about_axis([0, 1, 0], math.radians(angle_deg))
    pose[:3, 3] = [0.0, 0.0, rig.working_distance]
    return pose if placement is None else pose @ placement


def check_view_geometry(geom, name: str, scene_name: str) -> None:
    """Refuse a traced view (:class:`slscan.virtual.render.ViewGeometry`) in which the
    camera sees nothing, or sees nothing the projector lights."""
    if not geom.hit.any():
        raise DeviceError(f"{name}: the camera sees nothing of scene {scene_name!r}")
    if not geom.proj_lit.any():
        raise DeviceError(f"{name}: the projector lights nothing the camera sees")


def exposure_record(sensor: Sensor) -> dict:
    """The virtual camera's settings as a session records them."""
    return {"sensor": sensor.to_dict(), "camera": {"exposure": sensor.exposure, "gain": sensor.gain}}


class VirtualRig:
    """The simulated world behind the virtual devices.

    scene : what stands on the turntable
    rig : camera, projector and lights (sizes, poses, intensities)
    sensor, optics : the camera sensor and the projector/scene light (see :mod:`.render`)
    poses : ``rig_from_object`` (4, 4) per view; None: even turntable steps over 360°
    seed : noise seed; image ``i`` of view ``v`` uses ``[seed, v, i]``, so the same scan
        gives the same images
    noise_stream : more entropy between the seed and ``v`` (``[seed, *noise_stream, v,
        i]``), e.g. ``(k,)`` for a rig's camera ``k > 0``: its noise is its own
    latency_s : projector latency: an image shown at t is seen by the camera from t + latency
    """

    def __init__(
        self,
        scene: Scene,
        rig: Rig,
        sensor: Sensor,
        optics,
        *,
        poses: list[np.ndarray] | None = None,
        seed: int = 0,
        latency_s: float = 0.0,
        noise_stream: tuple[int, ...] = (),
    ) -> None:
        if latency_s < 0:
            raise DeviceError(f"virtual rig: latency must be >= 0 s, got {latency_s}")
        self.scene, self.rig, self.optics, self.seed, self.latency_s = scene, rig, optics, seed, latency_s
        self.poses, self.noise_stream = poses, tuple(noise_stream)
        self.turntable_angles: list[float] | None = None  # degrees per view, when ``poses`` are turntable turns
        self.geometry: ViewGeometry | None = None
        self.pose: np.ndarray | None = None
        self.view_index = 0
        self.frame_index = 0
        self.shown: list[tuple[float, np.ndarray | None]] = [(-math.inf, None)]
        self.lights_on: set[int] = set()
        self.projector = VirtualProjector(self)
        self.camera = VirtualCamera(self, sensor)
        self.lights = VirtualLights(self)
        self.stage = VirtualTurntable(self)

    def place(self, view_index: int, pose: np.ndarray) -> ViewGeometry:
        """Put the object at ``pose`` for view ``view_index`` and trace the view."""
        self.geometry = trace_view(self.scene, self.rig, pose, self.optics)
        self.pose, self.view_index, self.frame_index = pose, view_index, 0
        return self.geometry

    def projected_at(self, t: float) -> np.ndarray | None:
        """The projector image the camera sees at monotonic time ``t`` (None: dark)."""
        image = None
        for shown_at, img in self.shown:
            if shown_at + self.latency_s <= t:
                image = img
        return image

    def render(self, projected: np.ndarray | None, sensor: Sensor) -> np.ndarray:
        """One camera image of the placed object under ``projected`` and the lights on."""
        if self.geometry is None:
            raise DeviceError("virtual rig: no object placed (move the stage to a view first)")
        radiance = shade_image(self.geometry, projected, self.optics)
        for k in sorted(self.lights_on):
            add_light(radiance, self.geometry, k, self.rig, self.optics)
        rng = np.random.default_rng([self.seed, *self.noise_stream, self.view_index, self.frame_index])
        self.frame_index += 1
        return sensor.expose(radiance, rng, camera=self.rig.camera)


class VirtualProjector(Projector):
    name = "virtual-projector"

    def __init__(self, world: VirtualRig) -> None:
        self.world = world

    @property
    def resolution(self) -> tuple[int, int]:
        lens = self.world.rig.projector.lens
        return lens.width, lens.height

    def show(self, image: np.ndarray) -> float:
        image = self.check_image(image)
        return self._present(image)

    def blank(self) -> float:
        """Switch the projector's light off (a real one would show black)."""
        return self._present(None)

    def _present(self, image: np.ndarray | None) -> float:
        world, now = self.world, time.monotonic()
        pending = [(t, img) for t, img in world.shown if t + world.latency_s > now]
        world.shown = [(-math.inf, world.projected_at(now)), *pending, (now, image)]
        return now

    def describe(self) -> dict:
        return {"kind": self.name, "latency_s": self.world.latency_s}


class VirtualCamera(Camera):
    """The virtual rig's camera: renders, then exposes through :class:`Sensor`.

    ``exposure`` and ``gain`` controls are the sensor's (relative exposure, analogue gain).
    """

    name = "virtual-camera"

    def __init__(self, world: VirtualRig, sensor: Sensor, *,
                 exposure_range: tuple[float, float] = EXPOSURE_RANGE) -> None:
        self.world, self.sensor, self.exposure_range = world, sensor, exposure_range

    @property
    def resolution(self) -> tuple[int, int]:
        cam = self.world.rig.camera
        return cam.width, cam.height

    @property
    def bit_depth(self) -> int:
        return self.sensor.bit_depth

    @property
    def jpeg_quality(self) -> int | None:
        return self.sensor.jpeg_quality or None

    @property
    def response(self) -> str:
        return self.sensor.response

    def controls(self) -> dict[str, tuple[float, float]]:
        return {"exposure": self.exposure_range, "gain": GAIN_RANGE}

    def get_controls(self) -> dict[str, float]:
        return {"exposure": self.sensor.exposure, "gain": self.sensor.gain}

    def set_controls(self, **values: float) -> dict[str, float]:
        import dataclasses

        ranges = self.controls()
        self.check_control_names(values, ranges)
        for key, value in values.items():
            lo, hi = ranges[key]
            if not (math.isfinite(value) and lo <= value <= hi):
                raise DeviceError(f"{self.name}: {key} {value} is outside [{lo:g}, {hi:g}]")
        self.sensor = dataclasses.replace(self.sensor, **values)
        return self.get_controls()

    def exposure_record(self) -> dict:
        return exposure_record(self.sensor)

    def capture(self) -> Frame:
        now = time.monotonic()
        image = self.world.render(self.world.projected_at(now), self.sensor)
        return Frame(image, time.monotonic(), {"exposure": self.sensor.exposure, "gain": self.sensor.gain})

    def describe(self) -> dict:
        return {"kind": self.name, "sensor": self.sensor.to_dict()}


class VirtualLights(Lights):
    name = "virtual-lights"

    def __init__(self, world: VirtualRig) -> None:
        self.world = world

    @property
    def count(self) -> int:
        return len(self.world.rig.lights)

    def switch(self, index: int, on: bool) -> None:
        if not 0 <= index < self.count:
            raise DeviceError(f"{self.name}: no light {index} (the rig has {self.count})")
        (self.world.lights_on.add if on else self.world.lights_on.discard)(index)


class VirtualTurntable(Stage):
    """Turns the object to evenly spread angles (or to the given poses); poses are exact."""

    name = "virtual-turntable"

    def __init__(self, world: VirtualRig) -> None:
        self.world = world

    def move_to(self, view_index: int, views: int) -> Placement:
        world = self.world
        if world.poses is not None:
            if not 0 <= view_index < len(world.poses):
                raise DeviceError(f"{self.name}: no pose for view {view_index} ({len(world.poses)} given)")
            pose = world.poses[view_index]
        else:
            pose = turntable_pose(world.rig, 360.0 * view_index / views, world.scene.placement)
        check_view_geometry(world.place(view_index, pose), f"view_{view_index:03d}", world.scene.name)
        angles = world.turntable_angles
        return Placement(pose, "ground-truth", turntable_deg=None if angles is None else float(angles[view_index]))

    def ground_truth(self):
        from slscan.virtual.device import ground_truth

        return None if self.world.geometry is None else ground_truth(self.world.geometry)


class ScreenLoopCamera(Camera):
    """FAKE camera for closed-loop tests of a real projector back-end.

    It looks at the screen instead of a scene: ``grab()`` returns what the display really
    shows in the projector window (e.g. :func:`slscan.devices.screen.grab_screen`), and the
    virtual rig renders its object lit by *that* image. A window that scales, filters or
    shifts the pattern changes the range map; one that shows it exactly reproduces the
    direct virtual scan. Lights and stage are the virtual rig's.
    """

    name = "screen-loop-camera (fake)"

    def __init__(self, world: VirtualRig, grab: Callable[[], np.ndarray], sensor: Sensor) -> None:
        self.world, self.grab, self.inner = world, grab, VirtualCamera(world, sensor)
        self.dark = True  # the driver blanks the projector for lit images: the screen shows black

    @property
    def resolution(self) -> tuple[int, int]:
        return self.inner.resolution

    @property
    def bit_depth(self) -> int:
        return self.inner.bit_depth

    @property
    def jpeg_quality(self) -> int | None:
        return self.inner.jpeg_quality

    @property
    def response(self) -> str:
        return self.inner.response

    def controls(self) -> dict[str, tuple[float, float]]:
        return self.inner.controls()

    def get_controls(self) -> dict[str, float]:
        return self.inner.get_controls()

    def set_controls(self, **values: float) -> dict[str, float]:
        return self.inner.set_controls(**values)

    def exposure_record(self) -> dict:
        return self.inner.exposure_record()

    def capture(self) -> Frame:
        screen = self.grab()
        w, h = self.world.rig.projector.lens.width, self.world.rig.projector.lens.height
        if screen.shape[:2] != (h, w):
            raise DeviceError(f"{self.name}: the screen grab is {screen.shape[1]}x{screen.shape[0]}, the rig's "
                              f"projector is {w}x{h}")
        # a blanked projector is dark, not black-with-leak: a black screen while lights are on
        projected = None if self.world.lights_on and not screen.any() else screen
        image = self.world.render(projected, self.inner.sensor)
        return Frame(image, time.monotonic(), {"source": "screen grab", **self.inner.get_controls()})
