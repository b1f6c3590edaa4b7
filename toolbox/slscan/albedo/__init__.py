"""Colour: illumination-invariant albedo from the ring of lights (paper §3.4).

Modules: ``radiometry`` (camera response and the point-light Lambertian model),
``lights`` (light calibration from a matte panel), ``surface`` (the range map seen from
the camera, shadow rays), ``unshade`` (per-pixel albedo and the view/session pipeline),
``command`` (``slscan capture-lights``, ``calibrate-lights`` and ``albedo``).
"""
