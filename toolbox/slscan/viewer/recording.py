"""Rerun recording streams for slscan: open the sinks a command asks for, close them cleanly.

Library code never touches Rerun's global recording: every ``log_*`` function takes the
stream returned by :func:`open_recording` (or ``None``, which turns logging off)::

    with open_recording(save="scan.rrd", spawn=True, recording_name="capture") as rec:
        log_rig(rec, rig)

Timelines (the layouts in ``viewer_layouts/`` open on them):

- :data:`VIEW_TIMELINE` — the view (range map) index;
- :data:`FRAME_TIMELINE` — the pattern / frame index within a view;
- :data:`STAGE_TIMELINE` — the pipeline stage.

A second session logged into the same recording (the light-calibration panel beside the
scanned object) goes through :func:`session_stream`: its own entity subtree, its own
timelines, its own static intrinsics.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import shutil
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from slscan.errors import SlscanError
from slscan.fsio import atomic_output_file

if TYPE_CHECKING:
    import rerun as rr  # imported where a stream is opened: building a command's options needs no Rerun

VIEW_TIMELINE = "view"
FRAME_TIMELINE = "frame"
STAGE_TIMELINE = "stage"

LOSSLESS_ATTR = "slscan_lossless_images"
"""Attribute of a recording stream opened here: log camera frames losslessly."""
STATIC_LOGGED_ATTR = "slscan_static_logged"
"""Attribute of a recording stream: what static data it has been sent, by entity path."""
DEFAULT_PORT = 9876
DEFAULT_CONNECT_URL = f"rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy"

logger = logging.getLogger(__name__)


CONNECT_TIMEOUT_S = 3.0
"""How long ``--connect`` waits for the viewer's port to answer before giving up."""
SPAWN_TIMEOUT_S = 20.0
"""How long ``--spawn`` waits for the viewer it started to listen (a cold start with a
software rasteriser takes a few seconds)."""
FLUSH_TIMEOUT_S = 120.0
"""How long closing a recording waits for its data to reach a viewer or a file."""


def display_problem() -> str | None:
    """Why a viewer window cannot open here (Linux with no X11 or Wayland display), or None."""
    if not sys.platform.startswith("linux"):
        return None
    if any(os.environ.get(name) for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")):
        return None
    return "no display to open it on (DISPLAY and WAYLAND_DISPLAY are not set)"


def _host_port(url: str) -> tuple[str, int] | None:
    """(host, port) of a ``rerun+http://host:port/proxy`` URL (default port 9876), or None."""
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    if not parts.hostname:
        return None
    try:
        port = parts.port
    except ValueError:
        return None
    default = 443 if parts.scheme.endswith("https") else DEFAULT_PORT
    return parts.hostname, port or default


def _listening(host: str, port: int, timeout: float) -> str | None:
    """None when something accepts TCP connections at ``host:port`` within ``timeout`` s,
    else why not."""
    import socket

    try:
        with socket.create_connection((host, port), timeout=timeout):
            return None
    except OSError as exc:
        return exc.strerror or type(exc).__name__


def _check_reachable(url: str) -> None:
    """Raise :class:`SlscanError` when no viewer or server listens at ``url``: Rerun's
    gRPC sink would drop the data without a word."""
    address = _host_port(url)
    if address is None:
        return  # _grpc_sink says what is wrong with the URL
    problem = _listening(*address, CONNECT_TIMEOUT_S)
    if problem is not None:
        raise SlscanError(
            f"--connect {url}: no Rerun viewer is listening at {address[0]}:{address[1]} ({problem}); "
            "start one (`rerun`), or use --spawn or --save FILE.rrd"
        )


def _grpc_sink(url: str) -> rr.GrpcSink:
    import rerun as rr

    try:
        return rr.GrpcSink(url)
    except RuntimeError as exc:
        raise SlscanError(
            f"--connect {url!r}: not a Rerun viewer URL ({_first_line(exc)}); "
            f"expected e.g. {DEFAULT_CONNECT_URL}"
        ) from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _rerun_executable() -> str | None:
    """Path of the ``rerun`` viewer, also when the venv's ``bin`` is not on ``PATH``."""
    if shutil.which("rerun"):
        return None  # let rerun search PATH itself
    beside = Path(sys.executable).with_name("rerun.exe" if os.name == "nt" else "rerun")
    return str(beside) if beside.is_file() else None


def _spawn_viewer(rec: rr.RecordingStream, port: int) -> str:
    """Start a viewer on ``port`` (or reuse one already there); return its gRPC URL.

    Raises :class:`SlscanError` at once when no viewer can show anything here (no display,
    and none listening on ``port`` already), and when the one started is not listening
    after :data:`SPAWN_TIMEOUT_S` or has gone (e.g. its window could not open): streaming
    to it would hang, then lose the data.
    """
    import time

    import rerun as rr

    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if _listening("127.0.0.1", port, 0.5) is None:
        return url  # a viewer (or server) is there already: rr.spawn would reuse it too
    problem = display_problem()
    if problem is not None:
        raise SlscanError(f"--spawn: cannot start the Rerun viewer: {problem}; "
                          "write a recording with --save FILE.rrd and open it where there is a display")
    try:
        rr.spawn(port=port, connect=False, executable_path=_rerun_executable(), recording=rec)
    except RuntimeError as exc:
        reason = _first_line(exc)
        raise SlscanError(f"--spawn: could not start the Rerun viewer ({reason})") from None
    # the viewer listens before it opens its window; a window that fails takes it down
    # within a second or two, so it must still be listening a little later
    deadline = time.monotonic() + SPAWN_TIMEOUT_S
    seen = 0
    while time.monotonic() < deadline:
        if _listening("127.0.0.1", port, 0.5) is None:
            seen += 1
            if seen >= 3:
                return url
        else:
            seen = 0
        time.sleep(0.5)
    raise SlscanError(f"--spawn: the Rerun viewer started on port {port} is not listening after "
                      f"{SPAWN_TIMEOUT_S:.0f} s (could its window open?); use --save FILE.rrd instead")


def _close(rec: rr.RecordingStream, urls: Sequence[str] = ()) -> None:
    """Flush every sink and close them; files are complete on disk when this returns.

    The flush waits at most :data:`FLUSH_TIMEOUT_S`. Raises :class:`SlscanError` when it
    failed because the viewer at ``urls`` went away (the data did not all reach it).
    """
    failed = None
    try:
        rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
    except RuntimeError as exc:  # e.g. the viewer went away; the file sink is still flushed below
        failed = _first_line(exc)
        logger.warning("rerun: %s", failed)
    finally:
        rec.disconnect()
    if failed is None:
        return
    gone = [url for url in urls if (address := _host_port(url)) and _listening(*address, 1.0) is not None]
    if gone:
        raise SlscanError(f"rerun: the viewer at {', '.join(gone)} went away before it had everything "
                          f"({failed}); use --save FILE.rrd to keep a recording")


@contextlib.contextmanager
def open_recording(
    *,
    save: str | os.PathLike | None = None,
    spawn: bool = False,
    connect: str | None = None,
    application_id: str = "slscan",
    recording_name: str | None = None,
    blueprint: rr.blueprint.BlueprintLike | None = None,
    lossless_images: bool = False,
) -> Iterator[rr.RecordingStream | None]:
    """Yield a recording stream sending to every sink asked for, or ``None`` if none is.

    save : path of an ``.rrd`` file. It is written beside the target as
        ``.NAME.partial-*.rrd`` and renamed into place only when the block succeeds; if the
        block raises, the partial file is removed and an existing ``save`` is left as it was.
    spawn : start a Rerun viewer (or reuse the one on port 9876) and stream to it; an
        error at once when there is no display to show it on.
    connect : stream to a running viewer or server at this URL, e.g.
        ``rerun+http://127.0.0.1:9876/proxy``; ``""`` means that default URL; an error at
        once when nothing listens there.
    application_id : groups recordings in the viewer; blueprints (``viewer_layouts/``) are
        saved for ``"slscan"``.
    recording_name : shown in the viewer's recording list.
    blueprint : default layout sent with the recording (e.g.
        :func:`slscan.viewer.layouts.capture_blueprint`).
    lossless_images : log camera frames as they are (8 or 16 bit) instead of as JPEG; a
        paper-scale session has 2,500 images, so JPEG is the default for live viewing.
        Carried by the stream as ``LOSSLESS_ATTR`` for the loggers.

    Several sinks at once work (``save`` with ``spawn`` and/or ``connect``). The stream is
    never made the global or thread default. Raises :class:`SlscanError` for a bad URL, a
    viewer that cannot be started or a path that cannot be written.
    """
    if save is None and not spawn and connect is None:
        yield None
        return
    import rerun as rr

    urls: list[str] = []
    if connect is not None:
        urls.append(connect.strip() or DEFAULT_CONNECT_URL)
    sinks: list = [_grpc_sink(url) for url in urls]  # validate URLs before any side effect
    for url in urls:
        _check_reachable(url)

    if save is not None:
        target = Path(save)
        if target.is_dir():
            raise SlscanError(f"{target}: is a folder; expected a recording file such as scan.rrd")

    with contextlib.ExitStack() as stack:
        tmp = stack.enter_context(atomic_output_file(save)) if save is not None else None
        rec = rr.RecordingStream(application_id, make_default=False, make_thread_default=False)
        if spawn:
            url = _spawn_viewer(rec, DEFAULT_PORT)
            if url not in urls:  # --spawn with the default --connect: one sink, not two
                urls.append(url)
                sinks.append(_grpc_sink(url))
        if tmp is not None:
            sinks.append(rr.FileSink(tmp))
        try:
            rec.set_sinks(*sinks, default_blueprint=blueprint)
        except (RuntimeError, ValueError) as exc:
            rec.disconnect()
            reason = _first_line(exc)
            raise SlscanError(f"rerun: cannot open the recording sinks ({reason})") from None
        if recording_name:
            rec.send_recording_name(recording_name)
        setattr(rec, LOSSLESS_ATTR, bool(lossless_images))
        try:
            yield rec
        except BaseException:
            with contextlib.suppress(SlscanError):  # the error that stopped the block comes first
                _close(rec, urls)
            raise
        _close(rec, urls)
        if tmp is not None:
            if not os.path.getsize(tmp):
                raise SlscanError(f"{save}: Rerun wrote nothing (is the folder writable?)")
            _check_rrd(tmp, save)


def first_static(rec, path: str, key: object = None) -> bool:
    """True when static data ``key`` at ``path`` is new on ``rec`` (the caller then logs it).

    Static data is logged once per recording: a stage that logs the same thing again (the
    object frame, an annotation context, the rig) is a no-op. ``key`` tells contents apart
    (e.g. the lens of a camera): a different key at the same path is logged, and replaces
    the earlier one, as Rerun's static data does.
    """
    done = getattr(rec, STATIC_LOGGED_ATTR, None)
    if done is None:
        done = {}
        setattr(rec, STATIC_LOGGED_ATTR, done)
    if path in done and done[path] == key:
        return False
    done[path] = key
    return True


class SessionStream:
    """A recording stream seen through a session's own subtree and timelines.

    ``log("world/camera/image", ...)`` goes to ``world/<name>/camera/image`` (every path
    gets ``name`` after its first part: ``log/<name>/capture``, ``plot/<name>/...``), and
    ``set_time("view", ...)`` sets ``<name>_view``: a session logged beside another (the
    light-calibration panel beside the scanned object) never writes into its entities or
    onto its timeline values, and keeps its own static intrinsics. Other attributes are
    the wrapped stream's. Use it as a context manager: the time cursor is cleared on entry
    and on exit, so neither session's time leaks into the other's data.
    """

    def __init__(self, rec: rr.RecordingStream, name: str) -> None:
        if not name or "/" in name:
            raise ValueError(f"session name must be one path part, got {name!r}")
        self._rec = rec
        self.name = name
        setattr(self, STATIC_LOGGED_ATTR, {})
        setattr(self, LOSSLESS_ATTR, bool(getattr(rec, LOSSLESS_ATTR, False)))

    def entity_path(self, path: str) -> str:
        """``a/b/c`` -> ``a/<name>/b/c``."""
        head, _, rest = path.strip("/").partition("/")
        return f"{head}/{self.name}" + (f"/{rest}" if rest else "")

    def timeline(self, timeline: str) -> str:
        return f"{self.name}_{timeline}"

    def log(self, entity_path: str, *args, **kwargs) -> None:
        self._rec.log(self.entity_path(entity_path), *args, **kwargs)

    def set_time(self, timeline: str, **kwargs) -> None:
        self._rec.set_time(self.timeline(timeline), **kwargs)

    def disable_timeline(self, timeline: str) -> None:
        self._rec.disable_timeline(self.timeline(timeline))

    def __getattr__(self, name: str):
        return getattr(self._rec, name)

    def __enter__(self) -> SessionStream:
        self._rec.reset_time()
        return self

    def __exit__(self, *exc) -> None:
        self._rec.reset_time()


def session_stream(rec: rr.RecordingStream | None, name: str) -> contextlib.AbstractContextManager:
    """A context yielding ``rec`` seen through session ``name``'s subtree (:class:`SessionStream`),
    or ``None`` when ``rec`` is ``None`` (logging off)."""
    if rec is None:
        return contextlib.nullcontext(None)
    return SessionStream(rec, name)


RRD_FOOTER = b"RRF2FOOT"
"""The end of a complete .rrd (Rerun 0.41's RRF2 format): a recording cut off by a full
disk lacks it. Rerun only logs its write errors, so this is how slscan finds out."""


def _check_rrd(written: Path, save: str | os.PathLike) -> None:
    from slscan.fsio import write_error

    size = os.path.getsize(written)
    with open(written, "rb") as fh:
        head = fh.read(4)
        fh.seek(max(size - 64, 0))
        tail = fh.read()
    if head == b"RRF2" and RRD_FOOTER not in tail:
        raise write_error(save, written=size)


def add_recording_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--save FILE.rrd``, ``--spawn`` and ``--connect [URL]`` to ``parser``."""
    group = parser.add_argument_group("Rerun viewer", "stream what this command does to Rerun")
    group.add_argument(
        "--save", metavar="FILE.rrd", default=None,
        help="write a Rerun recording; view it with `rerun FILE.rrd` (a layout per stage: viewer_layouts/*.rbl)",
    )
    group.add_argument(
        "--spawn", action="store_true",
        help=f"start a Rerun viewer (or reuse the one on port {DEFAULT_PORT}) and stream to it",
    )
    group.add_argument(
        "--connect", metavar="URL", nargs="?", const=DEFAULT_CONNECT_URL, default=None,
        help=f"stream to a running Rerun viewer or server (default URL: {DEFAULT_CONNECT_URL})",
    )
    group.add_argument(
        "--lossless-images", action="store_true",
        help="log camera frames losslessly (default: JPEG, light enough to stream thousands)",
    )


def recording_from_args(
    args: argparse.Namespace,
    *,
    recording_name: str | None = None,
    blueprint: rr.blueprint.BlueprintLike | None = None,
) -> contextlib.AbstractContextManager[rr.RecordingStream | None]:
    """:func:`open_recording` for the options added by :func:`add_recording_arguments`."""
    return open_recording(
        save=getattr(args, "save", None),
        spawn=bool(getattr(args, "spawn", False)),
        connect=getattr(args, "connect", None),
        recording_name=recording_name,
        blueprint=blueprint,
        lossless_images=bool(getattr(args, "lossless_images", False)),
    )
