"""Decoding: from captured patterns to sub-pixel samples of known light planes, then to range maps.

Stages, one module each: ``masks`` (shadow, contrast, saturation); one decoder per pattern
family, each offering the plug-in functions of ``family`` (``decode``, and where it can
``projector_codes`` and ``projector_constraints``): ``hybrid`` (the paper's green lines
indexed by red/blue bands), ``graycode`` (black/white stripes and their edges), ``phase``
(N-step fringes: a projector column and row at every pixel; ``phase_gamma`` the projector's
response); ``triangulate`` (camera rays against the projector's planes or its whole model),
``rangemap`` (meshing and PLY), ``codes`` (projector codes without a calibration),
``stereo`` (two cameras matched through the projector's codes), ``pipeline`` (the stage).
"""
