"""Light-calibration targets for the virtual rig: a matte panel at known poses.

:func:`capture_light_calibration` writes a capture session of the panel (every view has
its lit images and its true pose as ``rig_from_object``) plus ``light_panel.json``
describing the panel, which is what ``slscan calibrate-lights`` reads.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from slscan.albedo.lights import PANEL_FILE, LightCalibration, MattePanel
from slscan.capture.session import Session
from slscan.errors import SlscanError
from slscan.fsio import write_json
from slscan.rig import Rig, rotation_about_axis
from slscan.virtual.scenes import Scene, UniformAlbedo

DEFAULT_POSES = (
    # (distance along the camera axis mm, tilt about y deg, tilt about x deg)
    (1300.0, 0.0, 0.0),
    (1050.0, 22.0, 0.0),
    (1050.0, -18.0, 12.0),
    (1550.0, 0.0, 22.0),
    (1550.0, 16.0, -16.0),
    (1300.0, -25.0, -10.0),
)
"""Panel placements: near, far and tilted, so light distance and direction are both seen."""


def panel_scene(panel: MattePanel | None = None) -> Scene:
    """The panel (default :class:`MattePanel`) as a box mesh, Lambertian (specular 0), uniform albedo."""
    panel = panel or MattePanel()
    hx, hy, hz = panel.width / 2, panel.height / 2, panel.thickness / 2
    corners = np.array([[x, y, z] for z in (-hz, hz) for y in (-hy, hy) for x in (-hx, hx)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int32)
    v = corners[tris]
    face_n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", face_n, v.mean(axis=1)) < 0  # wind outwards
    tris[flip] = tris[flip][:, ::-1]
    return Scene(
        "light-panel",
        corners,
        tris,
        None,
        UniformAlbedo(tuple(map(float, panel.albedo))),
        specular=0.0,
    )


def panel_pose(distance: float, tilt_y_deg: float = 0.0, tilt_x_deg: float = 0.0) -> np.ndarray:
    """``rig_from_object`` (4, 4): the panel on the camera axis at ``distance`` mm, tilted."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_about_axis([0, 1, 0], math.radians(tilt_y_deg)) @ rotation_about_axis(
        [1, 0, 0], math.radians(tilt_x_deg)
    )
    pose[:3, 3] = [0.0, 0.0, distance]
    return pose


def light_calibration_poses(
    rig: Rig | None = None, *, count: int = len(DEFAULT_POSES)
) -> list[np.ndarray]:
    """The first ``count`` of :data:`DEFAULT_POSES` (scaled to ``rig.working_distance``)."""
    if not 2 <= count <= len(DEFAULT_POSES):
        raise SlscanError(
            f"light calibration needs 2 to {len(DEFAULT_POSES)} panel poses, got {count}"
        )
    scale = (rig.working_distance if rig is not None else 1300.0) / 1300.0
    return [panel_pose(d * scale, ty, tx) for d, ty, tx in DEFAULT_POSES[:count]]


def capture_light_calibration(
    out: str | os.PathLike,
    *,
    config=None,
    rig: Rig | None = None,
    panel: MattePanel | None = None,
    poses: list[np.ndarray] | None = None,
    overwrite: bool = False,
    rec=None,
    progress=None,
) -> Session:
    """Capture the matte panel at ``poses`` on the virtual rig into session folder ``out``.

    config : a :class:`~slscan.virtual.device.VirtualCaptureConfig` (sensor, optics,
        size); its lit images are always captured
    rig : default ``config.rig()``
    panel : default :class:`~slscan.albedo.lights.MattePanel` (600 x 450 mm, albedo 0.8)
    poses : ``rig_from_object`` of each view; default :func:`light_calibration_poses`
    Also writes ``out/light_panel.json`` (the panel's size and albedo).
    """
    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    config = config or VirtualCaptureConfig()
    panel = panel or MattePanel()
    if not config.lit_images:
        config = replace(config, lit_images=True)
    rig = rig or config.rig()
    poses = poses if poses is not None else light_calibration_poses(rig)
    session = capture_session(
        config,
        out,
        overwrite=overwrite,
        rec=rec,
        progress=progress,
        scene=panel_scene(panel),
        poses=list(poses),
        rig=rig,
    )
    write_json(Path(out) / PANEL_FILE, panel.to_dict())
    return session


@dataclass(frozen=True)
class LightPanelConfig:
    """A light calibration on the virtual rig: the matte panel captured, then the lights fitted."""

    poses: int = len(DEFAULT_POSES)
    """Panel poses, 2 to 6, from :data:`DEFAULT_POSES`."""
    scale: float = 0.25
    """Camera and projector resolution factor; the calibration is in mm and hardly
    depends on it (quarter size recovers the lights to under 1 mm and 0.2 %)."""
    panel_albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    """Linear reflectance of the panel; the albedo of later scans is on its scale."""

    def capture_config(self):
        """The :class:`~slscan.virtual.device.VirtualCaptureConfig` of the panel session
        (few pattern levels: the panel's pose is known, its patterns are not decoded)."""
        from slscan.virtual.device import VirtualCaptureConfig

        if not 0 < self.scale <= 2:
            raise SlscanError(f"light panel scale must be in (0, 2], got {self.scale}")
        levels = max(1, min(5, int(math.log2(max(4, round(1024 * self.scale)))) - 1))
        return VirtualCaptureConfig(
            camera_scale=self.scale, projector_scale=self.scale, levels=levels
        )


def calibrate_virtual_lights(
    config: LightPanelConfig,
    out: str | os.PathLike,
    *,
    overwrite: bool = False,
    rec=None,
    progress: Callable[[str], None] | None = None,
) -> LightCalibration:
    """Capture the panel into ``out/session`` and write the calibration to ``out/lights.json``."""
    from slscan.albedo.lights import calibrate_lights, write_lights
    from slscan.fsio import atomic_output_dir

    capture = config.capture_config()
    poses = light_calibration_poses(capture.rig(), count=config.poses)
    panel = MattePanel(albedo=tuple(config.panel_albedo))
    out = Path(out)
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        session = capture_light_calibration(
            tmp / "session", config=capture, panel=panel, poses=poses, rec=rec, progress=progress
        )
        lights = calibrate_lights(session)
        lights = replace(lights, fit={**lights.fit, "session": str((out / "session").resolve())})
        write_lights(tmp / "lights.json", lights)
    return lights
