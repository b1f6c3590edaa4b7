"""File helpers shared by every stage: atomic output folders and files, PNG and JSON I/O.

Nothing half-written is left where a later stage would trust it: outputs are written to
a temporary name beside the target and renamed into place only when complete.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
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
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-", dir=parent))
    except OSError as exc:
        raise SlscanError(f"{target}: cannot write here ({exc.strerror})") from None
    try:
        yield tmp
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


@contextlib.contextmanager
def atomic_output_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary file name beside ``path``; rename it to ``path`` on success."""
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{target.name}.partial-", suffix=target.suffix, dir=target.parent)
        os.close(fd)
    except OSError as exc:
        raise SlscanError(f"{target}: cannot write here ({exc.strerror})") from None
    tmp = Path(name)
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _make_public(tmp, 0o666)
    os.replace(tmp, target)


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_output_file(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n")


def read_json(path: str | os.PathLike, what: str = "JSON file") -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise SlscanError(f"{path}: {what} not found") from None
    except json.JSONDecodeError as exc:
        raise SlscanError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an RGB or grey ``image`` (uint8 or uint16) as a lossless PNG."""
    if image.dtype not in (np.uint8, np.uint16):
        raise SlscanError(f"{path}: PNG needs uint8 or uint16 pixels, got {image.dtype}")
    image = np.ascontiguousarray(image)
    if image.ndim == 3:
        bgr = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA if image.shape[2] == 4 else cv2.COLOR_RGB2BGR)
    else:
        bgr = image
    ok = cv2.imwrite(str(path), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise SlscanError(f"{path}: could not write PNG")


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
