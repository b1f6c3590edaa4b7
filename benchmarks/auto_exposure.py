"""Auto-exposure on the virtual rig: where ``find_exposure`` stops, from several start exposures.

    .venv/bin/python benchmarks/auto_exposure.py

One row per (camera scale, start exposure): the trials it took, the exposure it chose, the
peak (99.9th percentile of the lit channels of the white frame and the finest green lines,
% of full scale) and the clipped share. The target is 85 % (``target_peak``), reached
when the peak is at least ``PEAK_NEAR`` of it with nothing clipped.
"""

from __future__ import annotations

import sys


def main() -> int:
    from slscan.capture.driver import PEAK_NEAR, find_exposure
    from slscan.virtual.device import VirtualCaptureConfig, virtual_devices
    from slscan.virtual.sensor import Sensor

    print(f"# target peak 85 %, stop at >= {PEAK_NEAR * 85:.1f} % unclipped")
    print("scale  start exposure  trials  chosen exposure  peak %  clipped %  ok")
    for scale in (0.25, 0.5):
        for exposure in (0.3, 1.0, 6.0, 40.0):
            config = VirtualCaptureConfig(views=1, camera_scale=scale, projector_scale=scale, levels=7,
                                          sensor=Sensor(exposure=exposure), lit_images=False)
            world = virtual_devices(config)
            world.stage.move_to(0, 1)
            r = find_exposure(world.projector, world.camera, config.pattern_set(world.rig))
            print(f"{scale:>5}  {exposure:>14}  {len(r.trials):>6}  {r.controls['exposure']:>15.4g}  "
                  f"{100 * r.peak:>6.1f}  {100 * r.clipped_share:>9.3f}  {r.ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
