"""Calibration: the camera from a printed board, the projector as light planes or an inverse camera.

Modules, one per step: ``target`` (chessboard and ChArUco boards), ``camera`` (corners and
Zhang's method), ``planes`` (the paper's light planes measured on a flat panel and their
global fit), ``procam`` (the projector as an inverse camera from local homographies),
``io`` (the calibration file, OpenCV XML, and use in decoding), ``pipeline`` (a session
in, a calibration out) and ``command`` (``slscan calibrate``).
"""
