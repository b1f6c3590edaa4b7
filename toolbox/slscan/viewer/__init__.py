"""Streaming to the Rerun viewer: recording streams, per-stage loggers and blueprints."""
