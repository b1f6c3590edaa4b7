"""The virtual rig: a ray-traced projector-camera-lights simulator that writes capture sessions."""
