"""File helpers shared by every stage: atomic output folders and files, PNG and JSON I/O.

Nothing half-written is left where a later stage would trust it: outputs are written to
a temporary name beside the target, flushed to disk (``fsync``), checked where its size
is known, and renamed into place only when complete. A full disk or a failing device
(``ENOSPC``, ``EDQUOT``, ``EIO``) is one :class:`SlscanError` naming the file and the free
space left (:func:`write_error`); the temporary is removed and nothing is renamed.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Hashable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any, Self

import cv2
import numpy as np

from slscan.errors import SlscanError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _make_public(path: Path, mode: int) -> None:
    """mkstemp/mkdtemp create private entries; give them the usual permissions."""
    os.chmod(path, mode & ~_umask())


WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EFBIG})
"""Errors that mean the data did not reach the disk: full disk, quota, device error, too big."""

PARTIAL = ".partial-"
"""In the names of temporaries (files and folders) before they are renamed into place."""


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """Silence what C libraries print straight to file descriptor 2 (Open3D's RPly prints
    "RPly: Error reading ..." for every bad PLY) while a file is read or written: slscan
    says what went wrong in its own one line. Python's own ``sys.stderr`` is flushed first;
    output of other threads during the call is lost, so keep the block short."""
    import sys

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no real fd 2 (embedded, pytest capture)
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def human_size(n: float) -> str:
    """``1536`` → ``1.5 KiB``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError  # unreachable


def _mount_point(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    while not os.path.ismount(path) and path != path.parent:
        path = path.parent
    return path


def write_error(
    path: str | os.PathLike, exc: OSError | None = None, *, needed: int | None = None,
    written: int | None = None, kept: bool = True,
) -> SlscanError:
    """The one-line error for an output that did not reach the disk whole.

    ``exc`` is the OSError (``ENOSPC``, ``EIO``, …), or None when a writer reported success
    but the file came out short (``written`` of ``needed`` bytes). The line names the file,
    the reason, the size needed where known, and the space left on the file's filesystem;
    ``kept``: and that nothing was renamed into place (the atomic writers' promise).
    """
    mount = _mount_point(Path(path).parent)
    path = final_path(path)
    try:
        left = shutil.disk_usage(mount).free
        free = f"{human_size(left)} free on {mount}"
    except OSError:
        left, free = None, f"free space on {mount} unknown"
    size = f"{human_size(needed)} needed, " if needed is not None else ""
    if exc is not None:
        reason = (exc.strerror or str(exc)).lower()
    else:  # the writer said it succeeded
        short = needed is None or left is None or left < needed - (written or 0) + (1 << 20)
        reason = "the file came out short" + (", the disk is probably full" if short else "")
        size = f"{human_size(written or 0)} written of {size}" if needed is not None else size
    kept_note = "; nothing was replaced" if kept else ""
    return SlscanError(f"{path}: could not write it: {reason} ({size}{free}){kept_note}")


def final_path(path: str | os.PathLike) -> Path:
    """``path`` with each temporary folder or file in it named as it will be once renamed
    (``run/.decode.partial-x1y2/view.ply`` → ``run/decode/view.ply``), for messages."""
    parts = [part[1:part.index(PARTIAL)] if part.startswith(".") and PARTIAL in part else part
             for part in Path(path).parts]
    return Path(*parts) if parts else Path(path)


def _final_name(name: str | os.PathLike | None, tmp: Path, target: Path) -> Path:
    """The final path of ``name`` written under the temporary ``tmp`` of ``target``."""
    if not name:
        return target
    try:
        rel = Path(os.fsdecode(name)).relative_to(tmp)
    except ValueError:
        return Path(os.fsdecode(name))
    return target / rel if str(rel) != "." else target


def fsync_path(path: Path, *, directory: bool = False) -> None:
    """Flush ``path`` (a file, or a folder's entries) to the disk.

    A folder's flush is best effort (some filesystems refuse it); a file's ``EIO`` or
    ``ENOSPC`` (deferred allocation, network filesystems) is raised."""
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        if directory:
            return
        raise
    try:
        os.fsync(fd)
    except OSError as exc:
        if not directory and exc.errno in WRITE_ERRNOS:
            raise OSError(exc.errno, exc.strerror, os.fspath(path)) from None
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    for folder, _, files in os.walk(root):
        for name in files:
            path = Path(folder) / name
            if not path.is_symlink():
                fsync_path(path)
        fsync_path(Path(folder), directory=True)


def _inside_partial(path: Path) -> bool:
    """Whether ``path`` lies in a temporary folder (whose own rename is flushed later)."""
    return any(PARTIAL in part for part in path.parts)


LEGACY_LEFTOVER_AGE_S = 3600.0
"""A leftover temporary with no owner in its name (slscan 0.1 and earlier) is removed once
it is this old (seconds since last modified)."""

_LEFTOVER_RE = re.compile(r"\.(?P<name>.+)\.(?:partial-(?:(?P<pid>\d+)-)?[a-z0-9_]+(?:\.[^.]*)?|old-(?P<old>\d+))")


def _partial_prefix(target: Path) -> str:
    """``.NAME.partial-PID-``: the writer's process id names who owns a temporary."""
    return f".{target.name}{PARTIAL}{os.getpid()}-"


def _process_start(pid: int) -> float | None:
    """When process ``pid`` started (seconds since the epoch; Linux), or None if unknown."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        return boot + int(fields[19]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def _owner_alive(pid: int, changed: float) -> bool:
    """Whether the writer ``pid`` of a temporary last changed at ``changed`` (its ctime,
    which no one can set back) may still run here.

    A zombie counts as gone (it writes nothing more), and so does a process with that id
    that started after the temporary was last changed: the id was recycled (in a container
    each run may even get the same id as the killed one)."""
    if pid <= 0:
        return False
    start = _process_start(pid)
    if start is not None and start > changed + 2.0:  # 2 s: the boot time is whole seconds
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    except (OverflowError, ValueError, OSError):
        return False
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[:1]
    except OSError:
        return True
    return state != ["Z"]


def stale_leftovers(folder: str | os.PathLike, *, name: str | None = None) -> list[Path]:
    """The temporaries in ``folder`` (of output ``name``, or of any) whose writer is gone.

    A temporary is named for its writer's process id (``.NAME.partial-PID-XXXXXXXX``); it
    is stale when no process with that id runs here any more (a ``kill -9``, a power cut),
    or when the one that does started after the temporary last changed (the id was reused).
    A live writer's temporary (another ``slscan`` writing the same output at the same time,
    or another thread of this process) is never stale. A recycled process id only delays
    the clean-up to a later run. Temporaries of older versions, with no id in their name,
    are stale once :data:`LEGACY_LEFTOVER_AGE_S` old. The process id is only meaningful on
    this machine: two machines writing one output on a shared disk at the same time may
    remove each other's temporaries (the writer that loses then fails; the output that
    lands is whole).
    """
    folder = Path(folder)
    found = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return []
    for entry in entries:
        m = _LEFTOVER_RE.fullmatch(entry.name)
        if m is None or (name is not None and m["name"] != name):
            continue
        pid = m["pid"] or m["old"]
        if pid is not None:
            try:
                stale = not _owner_alive(int(pid), entry.stat(follow_symlinks=False).st_ctime)
            except OSError:
                continue
        else:
            try:
                stale = time.time() - entry.stat(follow_symlinks=False).st_mtime > LEGACY_LEFTOVER_AGE_S
            except OSError:
                continue
        if stale:
            found.append(Path(entry.path))
    return sorted(found)


def remove_stale_leftovers(folder: str | os.PathLike, *, name: str | None = None) -> list[Path]:
    """Remove :func:`stale_leftovers` of ``folder``; returns what was removed (best effort)."""
    removed = []
    for path in stale_leftovers(folder, name=name):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                path.unlink()
        if not os.path.lexists(path):
            removed.append(path)
    return removed


LOCK_SUFFIX = ".lock"
"""``.NAME.lock`` beside output ``NAME``: who is writing it (:func:`output_lock`)."""

_HELD_LOCKS: dict[Path, int] = {}
"""Output locks this process holds, with how many nested blocks hold each."""


def lock_path(path: str | os.PathLike) -> Path:
    """The lock file of output ``path``: ``.NAME.lock`` in the folder it is written to."""
    target = Path(path)
    return target.parent / f".{target.name}{LOCK_SUFFIX}"


def _lock_owner(lock: Path) -> tuple[dict[str, Any], int, float] | None:
    """(what the lock holds, its inode, its ctime), or None when it is gone. A lock that is
    empty or unreadable (its writer was killed between creating and filling it) holds {}."""
    try:
        with open(lock, "rb") as fh:
            stat = os.fstat(fh.fileno())
            data = fh.read(4096)
    except FileNotFoundError:
        return None
    try:
        owner = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError):
        owner = {}
    return (owner if isinstance(owner, dict) else {}), stat.st_ino, stat.st_ctime


def _lock_is_stale(owner: dict[str, Any], changed: float, host: str) -> bool:
    """Whether a lock written at ``changed`` by ``owner`` (pid, host) has no live writer: on
    this host, its process is gone or its id was recycled; a lock of another host is never
    stale (its process cannot be seen from here). An empty lock older than a minute is stale."""
    if not owner:
        return time.time() - changed > 60.0
    if owner.get("host") != host:
        return False
    pid = owner.get("pid")
    if not isinstance(pid, int):
        return True
    if pid == os.getpid():  # this process, but not in a block that holds it: left behind
        return True
    return not _owner_alive(pid, changed)


def _take_over(lock: Path, inode: int) -> None:
    """Remove the stale lock ``lock`` (inode ``inode``) unless another process took it over
    first: it is renamed aside (atomic), and put back if what was renamed is a fresh lock."""
    aside = lock.with_name(f"{lock.name}.stale-{os.getpid()}")
    try:
        os.rename(lock, aside)
    except FileNotFoundError:
        return
    if os.stat(aside).st_ino != inode:  # another process's fresh lock: give it back
        with contextlib.suppress(FileExistsError):
            os.link(aside, lock)
    aside.unlink(missing_ok=True)


@contextlib.contextmanager
def output_lock(path: str | os.PathLike, *, command: str = "") -> Iterator[Path]:
    """Hold the output ``path`` (a file or a folder) for this process while the block runs.

    A second writer of the same output (another ``slscan … --out path`` at the same time)
    fails at once, naming the output, the process that holds it and the lock file, instead
    of one result silently replacing the other. The lock is ``.NAME.lock`` beside the
    output (:func:`lock_path`), created atomically (``O_CREAT | O_EXCL``, also on NFS v3+)
    and holding the writer's process id, host, start time and ``command`` as JSON; it is
    removed when the block ends, however it ends. A lock whose process is gone (killed,
    a power cut; on the same host) is taken over; one of another host is not (remove it
    by hand when that host's run is known to be dead). Nested blocks of one process on the
    same output share the lock. Folders missing above the output are made, and removed
    again at the end when still empty.

    Raises
    ------
    SlscanError
        Another live process holds the output, or the lock cannot be created.
    """
    import socket

    target = Path(path)
    lock = lock_path(target)
    key = Path(os.path.abspath(lock))
    if key in _HELD_LOCKS:
        _HELD_LOCKS[key] += 1
        try:
            yield lock
        finally:
            _HELD_LOCKS[key] -= 1
        return
    host = socket.gethostname()
    made = []
    parent = lock.parent if str(lock.parent) else Path(".")
    for folder in reversed([parent, *parent.parents]):
        if not folder.exists():
            made.append(folder)
    record = json.dumps({"pid": os.getpid(), "host": host,
                         "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "command": command}).encode()
    try:
        parent.mkdir(parents=True, exist_ok=True)
        for _ in range(5):
            try:
                fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                found = _lock_owner(lock)
                if found is None:
                    continue
                owner, inode, changed = found
                if not _lock_is_stale(owner, changed, host):
                    who = (f"process {owner.get('pid')} on {owner.get('host')}, since {owner.get('started')}"
                           + (f": {owner['command']}" if owner.get("command") else ""))
                    raise SlscanError(
                        f"{target}: another slscan is writing it ({who}); wait for it to finish or "
                        f"choose another --out (if that run is dead, remove {lock})"
                    ) from None
                _take_over(lock, inode)
                continue
            try:
                inode = os.fstat(fd).st_ino
                os.write(fd, record)
            finally:
                os.close(fd)
            break
        else:
            raise SlscanError(f"{target}: could not take its lock {lock} (other writers keep changing it)")
    except OSError as exc:
        _remove_made(made)
        if exc.errno in WRITE_ERRNOS:
            raise write_error(lock, exc) from None
        raise SlscanError(f"{target}: cannot write here ({exc.strerror})") from None
    except BaseException:
        _remove_made(made)
        raise
    _HELD_LOCKS[key] = 1
    try:
        yield lock
    finally:
        del _HELD_LOCKS[key]
        with contextlib.suppress(OSError):
            if os.stat(lock).st_ino == inode:  # still ours
                lock.unlink()
        _remove_made(made)


def _remove_made(folders: list[Path]) -> None:
    """Remove the folders an output's lock made (deepest first), where still empty."""
    for folder in reversed(folders):
        with contextlib.suppress(OSError):
            folder.rmdir()


def glob_results(folder: str | os.PathLike, pattern: str) -> list[Path]:
    """``sorted(folder.glob(pattern))`` without hidden entries: pathlib's ``*`` matches a
    leading dot, so ``*.ply`` would also find a temporary ``.view_000.ply.partial-….ply``."""
    return sorted(p for p in Path(folder).glob(pattern) if not p.name.startswith("."))


@contextlib.contextmanager
def atomic_output_dir(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; rename it to ``path`` when the block succeeds.

    On any exception the temporary folder is removed and ``path`` is left as it was.
    An existing non-empty ``path`` is an error unless ``overwrite``.
    """
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise SlscanError(f"{target}: exists and is not a folder")
    if target.is_dir() and any(target.iterdir()) and not overwrite:
        raise SlscanError(f"{target}: folder exists and is not empty (pass --overwrite to replace it)")
    parent = target.parent if str(target.parent) else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        remove_stale_leftovers(parent, name=target.name)  # a run killed while writing it
        tmp = Path(tempfile.mkdtemp(prefix=_partial_prefix(target), dir=parent))
    except OSError as exc:
        if exc.errno in WRITE_ERRNOS:
            raise write_error(target, exc) from None
        raise SlscanError(f"{target}: cannot write here ({exc.strerror})") from None
    try:
        yield tmp
        _fsync_tree(tmp)  # a deferred write error surfaces here, before the rename
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if exc.errno in WRITE_ERRNOS:
            raise write_error(_final_name(exc.filename, tmp, target), exc) from None
        raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _make_public(tmp, 0o777)
    old = None
    if target.exists():
        old = target.with_name(f".{target.name}.old-{os.getpid()}")
        target.rename(old)
    tmp.rename(target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    if not _inside_partial(parent):
        fsync_path(parent, directory=True)


@contextlib.contextmanager
def atomic_output_file(path: str | os.PathLike, *, size: int | None = None) -> Iterator[Path]:
    """Yield a temporary file name beside ``path``; rename it to ``path`` on success.

    Before the rename the file is flushed to the disk and, when ``size`` (bytes) is given,
    its size is checked. A full disk or a device error, in the block or in the flush, is
    a :func:`write_error`; on any error the temporary is removed and ``path`` is left as
    it was.
    """
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_leftovers(target.parent, name=target.name)
        fd, name = tempfile.mkstemp(prefix=_partial_prefix(target), suffix=target.suffix, dir=target.parent)
        os.close(fd)
    except OSError as exc:
        if exc.errno in WRITE_ERRNOS:
            raise write_error(target, exc, needed=size) from None
        raise SlscanError(f"{target}: cannot write here ({exc.strerror})") from None
    tmp = Path(name)
    try:
        yield tmp
        if size is not None and (written := tmp.stat().st_size) != size:
            raise write_error(target, needed=size, written=written)
        fsync_path(tmp)
        _make_public(tmp, 0o666)
        os.replace(tmp, target)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.errno in WRITE_ERRNOS:
            raise write_error(_final_name(exc.filename, tmp, target), exc, needed=size) from None
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if not _inside_partial(target.parent):
        fsync_path(target.parent, directory=True)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically, flushed and size-checked (see :func:`atomic_output_file`)."""
    path = Path(path)
    with atomic_output_file(path, size=len(data)) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return path


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    write_bytes(path, (json.dumps(data, indent=2) + "\n").encode())


def read_json(path: str | os.PathLike, what: str = "JSON file") -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_bytes())
    except FileNotFoundError:
        raise SlscanError(f"{path}: {what} not found") from None
    except IsADirectoryError:
        raise SlscanError(f"{path}: is a folder; expected the {what}") from None
    except json.JSONDecodeError as exc:
        raise SlscanError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except UnicodeDecodeError as exc:
        raise SlscanError(f"{path}: not valid JSON (not UTF-8 text: byte {exc.start})") from None
    except RecursionError:
        raise SlscanError(f"{path}: not valid JSON (nested too deeply)") from None
    except ValueError as exc:  # an integer of more than 4,300 digits
        raise SlscanError(f"{path}: not valid JSON ({exc})") from None


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB or grey ``image`` (uint8 or uint16) as a lossless PNG, atomically."""
    if image.dtype not in (np.uint8, np.uint16):
        raise SlscanError(f"{path}: PNG needs uint8 or uint16 pixels, got {image.dtype}")
    image = np.ascontiguousarray(image)
    if image.ndim == 3:
        bgr = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA if image.shape[2] == 4 else cv2.COLOR_RGB2BGR)
    else:
        bgr = image
    # encoded in memory and written by us: cv2.imwrite does not report a short write
    ok, data = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise SlscanError(f"{path}: could not encode the PNG")
    write_bytes(path, data.tobytes())


def write_float_tiff(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write a grey ``image`` as a 32-bit float TIFF (deflate-compressed, NaN kept), atomically."""
    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise SlscanError(f"{path}: a float TIFF map needs a (h, w) array, got shape {image.shape}")
    ok, data = cv2.imencode(".tiff", image, [cv2.IMWRITE_TIFF_COMPRESSION, 8])  # 8: Adobe deflate
    if not ok:
        raise SlscanError(f"{path}: could not encode the TIFF")
    write_bytes(path, data.tobytes())


def read_float_tiff(path: str | os.PathLike) -> np.ndarray:
    """Read a TIFF as stored (a :func:`write_float_tiff` map: (h, w) float32)."""
    path = Path(path)
    if not path.is_file():
        raise SlscanError(f"{path}: image not found")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SlscanError(f"{path}: not a readable TIFF image")
    return image


def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """JPEG bytes of an RGB or grey uint8 ``image`` at ``quality`` (1–100, libjpeg through
    OpenCV, 4:2:0 chroma subsampling as cameras save)."""
    if image.dtype != np.uint8:
        raise SlscanError(f"JPEG needs uint8 pixels, got {image.dtype}")
    image = np.ascontiguousarray(image)
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise SlscanError("could not encode the JPEG")
    return data.tobytes()


def write_jpeg(path: str | os.PathLike, image: np.ndarray, quality: int) -> None:
    """Write an RGB or grey uint8 ``image`` as a JPEG at ``quality``, atomically."""
    write_bytes(path, encode_jpeg(image, quality))


def decode_image(data: bytes) -> np.ndarray:
    """An encoded image (PNG, JPEG) decoded as stored: (h, w) grey or (h, w, 3) RGB."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SlscanError("not a readable image")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return image


def read_png(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG as stored: (h, w) grey or (h, w, 3) RGB, uint8 or uint16."""
    path = Path(path)
    if not path.is_file():
        raise SlscanError(f"{path}: image not found")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SlscanError(f"{path}: not a readable image")
    if image.ndim == 3:  # OpenCV reads BGR(A); cvtColor is ~30x faster than a flipped copy
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB if image.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return image


_READER: tuple[int, ThreadPoolExecutor] | None = None


def _reader() -> ThreadPoolExecutor:
    """This process's one background reading thread (a forked worker starts its own).

    One long-lived thread rather than one per call: a new thread's first images are
    about twice as slow to decode while its memory arena warms up."""
    global _READER
    if _READER is None or _READER[0] != os.getpid():
        _READER = (os.getpid(), ThreadPoolExecutor(max_workers=1, thread_name_prefix="slscan-read"))
    return _READER[1]


class Prefetched(Mapping):
    """Values ``read(key)`` for ``keys``, read one after another, in order, by a background thread.

    Made for decoding a view while its PNGs are still being read: OpenCV decodes a PNG
    without holding Python's lock, so the caller works on the images already read while
    the next ones load. ``prefetched[key]`` waits for that key's read and re-raises its
    error (``read`` names the file). Use it as a context manager: leaving the block cancels
    the reads not yet started and waits for the one under way.
    """

    def __init__(self, read: Callable[[Hashable], Any], keys: Sequence[Hashable]) -> None:
        pool = _reader()
        self._futures: dict[Hashable, Future] = {k: pool.submit(read, k) for k in dict.fromkeys(keys)}

    def __getitem__(self, key: Hashable) -> Any:
        return self._futures[key].result()

    def __contains__(self, key: object) -> bool:  # without waiting for the read
        return key in self._futures

    def __iter__(self) -> Iterator[Hashable]:
        return iter(self._futures)

    def __len__(self) -> int:
        return len(self._futures)

    def close(self) -> None:
        for future in self._futures.values():
            future.cancel()
        wait(self._futures.values())

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
