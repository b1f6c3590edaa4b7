"""The calibrate stage's option vocabularies: plain constants, importing nothing but the pattern registry.

``slscan calibrate``'s parser takes its choices and defaults from here, so that building
it loads neither OpenCV nor SciPy; the modules that use them import them from here.
"""

from __future__ import annotations

from slscan.patterns import decodable

DISTORTION_MODELS = ("none", "radial", "radial-tangential", "full")
"""Lens models: no distortion; ``k1, k2``; ``k1, k2, p1, p2``; ``k1, k2, p1, p2, k3``."""
METHODS = ("planes", "inverse-camera", "both")
"""Projector models: the paper's light planes, an inverse camera, or both."""
PLANE_PATTERNS = ("auto", *decodable())
"""Features whose light planes are measured: "auto" (the first family captured in the
pattern registry's "auto" order: phase shifting, hybrid lines, Gray code) or a family."""
INVERSE_PATTERNS = ("auto", "phase", "gray")
"""Codes that map the board corners into the projector (auto: the first family captured
with rows of phase shifting, Gray code; the pattern registry's "auto" order)."""
CORRESPONDENCES = ("edges", "pixels")
"""Local homographies from Gray-code stripe edges or from decoded pixels."""
BOARD_KINDS = ("chessboard", "charuco")
DEFAULT_DICTIONARY = "DICT_4X4_100"
"""ChArUco marker dictionary, an OpenCV ``cv2.aruco`` name."""
IMPORT_FORMATS = ("auto", "opencv", "bouguet", "text", "3dunderworld")
"""Formats ``slscan calibrate --import`` reads (``slscan.calibrate.importers``)."""
SECOND_KINDS = ("projector", "camera")
"""What the second device of an imported calibration is."""
