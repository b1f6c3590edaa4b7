"""The virtual rig with several cameras: the same views rendered from each camera, with truth.

Camera 0 is the rig's camera, at the rig origin; camera ``k`` stands on the other side of
the projector, turned ``k * spacing_deg`` about the vertical axis through the centre of
the working volume and looking at it (toe-in), at the same distance. With the default
40° and the paper's projector 20° to the right of camera 0, the projector sits halfway
between the two cameras, 20° from each; the cameras are 889 mm apart at 1.3 m.

Each camera's capture session is an ordinary one in **that camera's** frame (the
projector, lights and object re-expressed there), so every single-camera stage, ground
truth included, works on it unchanged; ``cameras.json`` gives each camera's pose in
camera 0's frame (:mod:`slscan.capture.multicam`).
"""

from __future__ import annotations

import math
import os
from dataclasses import replace

import numpy as np

from slscan.capture.multicam import CameraEntry, MultiCamSession, load_multicam, write_cameras_json
from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir
from slscan.rig import Light, PinholeModel, Projector, Rig, look_at, transform_points
from slscan.virtual.device import Progress, VirtualCaptureConfig, capture_session
from slscan.virtual.devices import turntable_pose
from slscan.virtual.scenes import Scene

DEFAULT_SPACING_DEG = 40.0
"""Angle between neighbouring cameras about the working-volume centre (twice the paper's
camera-projector angle: the projector halfway between cameras 0 and 1)."""


def camera_poses(rig: Rig, cameras: int, spacing_deg: float = DEFAULT_SPACING_DEG) -> list[np.ndarray]:
    """``rig_from_camera`` (4, 4) mm of each of ``cameras`` cameras: camera 0 at the rig
    origin, camera ``k`` turned ``k * spacing_deg`` towards +x (the projector's side)
    about the vertical axis through ``(0, 0, working_distance)``, looking at that point."""
    if cameras < 1:
        raise SlscanError(f"cameras must be at least 1, got {cameras}")
    if not 0 < abs(spacing_deg) * (cameras - 1) < 180:
        raise SlscanError(f"camera spacing {spacing_deg} degrees x {cameras - 1} must be within (0, 180)")
    wd = rig.working_distance
    target = np.array([0.0, 0.0, wd])
    poses = [np.eye(4)]
    for k in range(1, cameras):
        a = math.radians(k * spacing_deg)
        poses.append(look_at(target + wd * np.array([math.sin(a), 0.0, -math.cos(a)]), target))
    return poses


def camera_lens(camera: PinholeModel, k: int) -> PinholeModel:
    """Camera ``k``'s lens: camera 0's sensor and focal length with its own principal point
    and distortion (so that a mix-up of the cameras' intrinsics shows)."""
    if k == 0:
        return camera
    s = camera.width / 1440.0
    return replace(
        camera, cx=camera.cx - 5.3 * k * s, cy=camera.cy + 3.7 * k * s,
        dist=(-0.05 + 0.01 * k, 0.03, 0.0, 0.0, 0.0),
    )


def rig_seen_from(rig: Rig, rig_from_camera: np.ndarray, lens: PinholeModel) -> Rig:
    """``rig`` re-expressed in the frame of a camera at ``rig_from_camera`` with ``lens``:
    the projector and lights where they are, seen from there. Its working distance is the
    distance along the new camera's axis to the rig's working-volume centre."""
    cam_from_rig = np.linalg.inv(rig_from_camera)
    projector = Projector(rig.projector.lens, cam_from_rig @ rig.projector.rig_from_projector)
    lights = tuple(
        Light(tuple(float(v) for v in transform_points(cam_from_rig, np.asarray(light.position, float))),
              light.intensity)
        for light in rig.lights
    )
    centre = transform_points(cam_from_rig, np.array([0.0, 0.0, rig.working_distance]))
    return Rig(lens, projector, lights, float(centre[2]))


def capture_multicam(
    config: VirtualCaptureConfig,
    out: str | os.PathLike,
    *,
    cameras: int = 2,
    spacing_deg: float = DEFAULT_SPACING_DEG,
    overwrite: bool = False,
    rec=None,
    progress: Progress | None = None,
    scene: Scene | None = None,
    poses: list[np.ndarray] | None = None,
) -> MultiCamSession:
    """Capture ``config`` with ``cameras`` cameras into the multi-camera folder ``out``
    (``camK/`` capture sessions and ``cameras.json``), written at once when complete.

    Camera 0's session is exactly what :func:`~slscan.virtual.device.capture_session`
    writes for ``config``; camera ``k`` renders the same object poses from its own place
    (:func:`camera_poses`) with its own lens (:func:`camera_lens`) and its own noise.
    Each session records the true calibration of the projector as seen from its camera
    and per-pixel ground truth in its camera's frame.

    rec : streams camera 0's capture (the other cameras are not logged)
    poses : ``rig_from_object`` per view in camera 0's frame (default: turntable steps)
    """
    if cameras < 2:
        raise SlscanError(f"a multi-camera capture needs at least 2 cameras, got {cameras}")
    rig0 = config.rig()
    views = len(poses) if poses is not None else config.views
    if views < 1:
        raise SlscanError(f"views must be at least 1, got {views}")
    scene = scene or config.build_scene()  # once: its placement sets the default poses
    poses0 = list(poses) if poses is not None else [
        turntable_pose(rig0, 360.0 * v / views, scene.placement) for v in range(views)]
    entries = []
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        for k, rig_from_cam in enumerate(camera_poses(rig0, cameras, spacing_deg)):
            rig_k = rig0 if k == 0 else rig_seen_from(rig0, rig_from_cam, camera_lens(rig0.camera, k))
            cam_from_rig = np.linalg.inv(rig_from_cam)
            name = f"cam{k}"
            capture_session(
                config, tmp / name, rec=rec if k == 0 else None, progress=progress, scene=scene,
                poses=[cam_from_rig @ p for p in poses0], rig=rig_k, noise_stream=() if k == 0 else (k,),
            )
            entries.append(CameraEntry(name, name, rig_k.camera, rig_from_cam))
        write_cameras_json(tmp, entries, frame="camera 0", calibration_source="virtual-rig ground truth")
    return load_multicam(out, validate=False)
