"""The decode stage's option vocabularies: plain constants, importing nothing.

``slscan decode``'s parser takes its choices and defaults from here, so that building it
loads no decoder (OpenCV); the decoders import them from here.
"""

from __future__ import annotations

ESTIMATORS = ("centroid", "gaussian", "parabola", "blais-rioux")
"""Sub-pixel estimators of a green line's medial axis (:mod:`slscan.decode.hybrid`)."""
DEFAULT_ESTIMATOR = "gaussian"
"""The most accurate on the virtual rig (``benchmarks/stripe_axes.py``, module docstring)."""
