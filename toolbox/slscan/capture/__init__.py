"""Capture: the session format every rig writes, and importers for other tools' captures."""
