"""What decoding a session asks of the machine: memory per view, workers that fit, and
a warning when lossy captures will cost decoded pixels. Shared by the range-map run
(:mod:`slscan.decode.pipeline`) and the codes-only run (:mod:`slscan.decode.codes`)."""

from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path

from slscan.capture.session import Session
from slscan.executor import Executor

log = logging.getLogger(__name__)


def warn_if_lossy(session: Session) -> None:
    """One warning when the session's captures are lossy (JPEG)."""
    if session.lossy:
        log.warning("%s: the captures are lossy (JPEG): compression noise lowers the share of "
                    "pixels decoded and moves stripe edges slightly", session.root)


VIEW_BYTES_PER_PIXEL = 75.0
"""Peak memory of decoding one view, bytes per camera pixel (Gray code, 8-bit grey, 10 + 10
bits: 1.3 GB for 16 MP, ``benchmarks/decode_memory.py``), plus ``IMAGE_BYTES_PER_PIXEL``
for the captures the reader holds."""

IMAGE_BYTES_PER_PIXEL = 4.0
"""Captures held at once while a view decodes (the reader's look-ahead and the pair in
use), bytes per camera pixel per channel and byte of depth."""


def view_memory_bytes(session: Session) -> int:
    """Estimated peak memory of decoding one view of ``session``, bytes."""
    w, h = session.camera_size
    depth = 2 if session.bit_depth == 16 else 1
    return int(w * h * (VIEW_BYTES_PER_PIXEL + IMAGE_BYTES_PER_PIXEL * session.channels * depth))


def available_memory_bytes() -> int | None:
    """``MemAvailable`` of /proc/meminfo, bytes (None where unknown)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def fit_workers(executor: Executor, session: Session, available: int | None = None) -> Executor:
    """``executor`` with no more local workers than the free memory holds views of
    ``session`` at once (at least one), saying so in a log line when it cuts them."""
    if executor.scheduler is not None:
        return executor
    available = available_memory_bytes() if available is None else available
    if available is None:
        return executor
    wanted = min(len(session.views), executor.workers or os.cpu_count() or 1)
    per_view = view_memory_bytes(session)
    fits = max(1, int(available // per_view))
    if fits >= wanted:
        return executor
    log.info("decoding with %d worker(s) instead of %d: a %dx%d view needs about %.1f GB and "
             "%.1f GB are free", fits, wanted, *session.camera_size, per_view / 1e9, available / 1e9)
    return replace(executor, workers=fits)
