"""TEST-ONLY STAND-IN for global light (inter-reflections, subsurface scattering).

Not a model of light transport: until the virtual rig renders real inter-reflections
(``virtual/effects.py``'s ``interreflection``), the decoders' robustness is tested on
captures whose radiance gets a smooth global term added,

    radiance + beta * albedo * GaussianBlur(radiance, sigma_px)      (on surface pixels)

the direct radiance of the same pattern spread over ``sigma_px`` camera pixels, scaled by
``beta`` and by the receiving pixel's albedo. Like real global light it falls unevenly under
a low-frequency pattern (pixels near its lit half receive more than those near its dark
half) and evenly under a high-frequency one (half of what white gives). Used by
``tests/decode/test_graycode_global.py`` and ``benchmarks/graycode_global.py``.
"""

from __future__ import annotations

import cv2
import numpy as np

from slscan.patterns import PatternImage
from slscan.virtual.device import VirtualCaptureConfig, ground_truth
from slscan.virtual.devices import turntable_pose
from slscan.virtual.render import shade_pattern, trace_view


def capture_with_global_stand_in(
    config: VirtualCaptureConfig, *, beta: float, sigma_px: float, view_index: int = 0,
) -> tuple[dict[str, np.ndarray], list[PatternImage], np.ndarray, np.ndarray, np.ndarray]:
    """One view of ``config`` with the stand-in global term: ``(images by pattern id, the
    pattern descriptions, white, black, true projector_uv (h, w, 2))``."""
    rig, scene = config.rig(), config.build_scene()
    pose = turntable_pose(rig, 360.0 * view_index / config.views, scene.placement)
    geom = trace_view(scene, rig, pose)
    descs = config.pattern_set(rig)
    grey_albedo = np.where(geom.hit, np.nan_to_num(geom.albedo.mean(axis=2)), 0.0)[..., None].astype(np.float32)
    images = {}
    for i, desc in enumerate(descs):
        radiance = np.nan_to_num(shade_pattern(geom, desc, config.optics))
        if beta > 0:
            spread = cv2.GaussianBlur(radiance, (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)
            radiance = radiance + np.float32(beta) * grey_albedo * spread
        rng = np.random.default_rng([config.seed, view_index, i])
        images[desc.id] = config.sensor.expose(radiance, rng)
    truth = ground_truth(geom)
    return images, descs, images["white"], images["black"], truth.projector_uv
