"""Devices: the projector, camera, lights and stage a scan runs through.

:mod:`.base` defines the interfaces; the back-ends are

==========================  ===============================================  ==============
spec (``slscan scan``)      class                                            extra
==========================  ===============================================  ==============
``--projector screen[:N]``  :class:`.screen.ScreenProjector` (pyglet)        ``slscan[screen]``
``--camera opencv[:N]``     :class:`.opencv_camera.OpenCVCamera`             (core)
``--camera gphoto2``        :class:`.gphoto.GPhoto2Camera` (python-gphoto2)  ``slscan[gphoto2]``
``--camera folder:DIR``     :class:`.folder.FolderCamera` (watch folder)     (core)
lights ``manual``           :class:`.lights.ManualLights` (operator)         (core)
``virtual``                 :mod:`slscan.virtual.devices` (the virtual rig)  (core)
==========================  ===============================================  ==============

Back-end modules import their optional library only when a device is opened, so
``import slscan.devices`` never needs an extra.
"""

from slscan.devices.base import (
    Camera,
    Device,
    DeviceError,
    Frame,
    Lights,
    NoLights,
    Placement,
    Projector,
    Stage,
)

__all__ = [
    "Camera", "Device", "DeviceError", "Frame", "Lights", "NoLights", "Placement", "Projector", "Stage",
]
