"""One executor for per-view work: local processes by default, a Dask cluster on request.

Per-view stages (decode, albedo) hand their views to :meth:`Executor.map`. With one view or
``workers=1`` the work runs in this process. Otherwise this process works through the
views together with ``workers - 1`` helper processes (``spawn``-started, so no thread of
this process — Rerun's, open3d's — is forked), or the views go to a Dask distributed
cluster when a scheduler address is given (``tcp://HOST:PORT``). Results come back in
input order; logging to Rerun stays in the calling process.

The helper processes are started once and kept for the rest of the run (every stage of
a recipe reuses them), so each pays its imports (NumPy, SciPy, OpenCV, Open3D: about a
second of CPU) once, not once per stage; :meth:`Executor.start` starts them early, each
importing the stage's modules, while this process reads its inputs.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import functools
import importlib
import logging
import multiprocessing
import os
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, TypeVar

from slscan.errors import SlscanError

log = logging.getLogger(__name__)
T = TypeVar("T")


@dataclass(frozen=True)
class Executor:
    """Where per-view work runs.

    scheduler : Dask scheduler address (``tcp://HOST:PORT``), or None for local processes
    workers : local processes at most, this one included (default: the machine's cores);
        ignored with Dask
    """

    scheduler: str | None = None
    workers: int | None = None

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise SlscanError(f"--workers must be at least 1, got {self.workers}")
        if self.scheduler is not None and "://" not in self.scheduler:
            raise SlscanError(f"--scheduler {self.scheduler!r}: expected an address like tcp://HOST:8786")

    def _local_workers(self) -> int:
        return self.workers or os.cpu_count() or 1

    def parallel(self, items: int) -> bool:
        """Whether :meth:`map` over ``items`` items works on more than one at a time."""
        return self.scheduler is not None or min(items, self._local_workers()) > 1

    def start(self, items: int, modules: Sequence[str] = ()) -> None:
        """Start the helper processes that :meth:`map` over ``items`` items will use now,
        each importing ``modules`` (e.g. the stage's module), so that their start-up
        overlaps this process's own work. Nothing to do for Dask or a single worker."""
        helpers = min(items, self._local_workers()) - 1
        if self.scheduler is None and helpers > 0:
            _helpers(self._local_workers() - 1, helpers, tuple(modules))

    def map(self, fn: Callable[..., T], items: Sequence[Any]) -> Iterator[T]:
        """``fn(item)`` for every item, yielded in input order as they are ready."""
        items = list(items)
        if self.scheduler is not None:
            yield from _map_dask(self.scheduler, fn, items)
            return
        helpers = min(len(items), self._local_workers()) - 1
        if helpers <= 0:
            for item in items:
                yield fn(item)
            return
        yield from _map_shared(_helpers(self._local_workers() - 1, helpers, ()), helpers, fn, items)



def map_retrying(executor: Executor | None, fn: Callable[..., T], items: Sequence[Any], *,
                 key: Callable[[Any], Any], done: Callable[[T], None] | None = None,
                 noun: str = "task") -> dict[Any, T]:
    """``{key(item): fn(item)}`` for every item on ``executor`` (None: in this process).

    A local helper process that dies (killed, out of memory) loses only the items not yet
    back: they run once more, on fresh helpers (tasks must write their files under
    temporary names, so that a half-written one is never read). A second death is the
    executor's one line ("a worker process died ..."). Dask reschedules a dead worker's
    tasks itself. ``done(result)`` is called as each result arrives (a progress bar); a
    result's key is ``key`` of its item, which the result must carry as ``result.index``.
    """
    results: dict[Any, T] = {}
    runner = executor.map if executor is not None else map
    for attempt in (1, 2):
        pending = [item for item in items if key(item) not in results]
        try:
            for result in runner(fn, pending):
                results[result.index] = result
                if done is not None:
                    done(result)
        except SlscanError as exc:
            if attempt == 2 or not isinstance(exc.__context__, BrokenProcessPool):
                raise
            log.warning("a worker process died; running its %d %s(s) again", len(items) - len(results), noun)
            continue
        break
    return results
_lock = threading.Lock()
_pool: ProcessPoolExecutor | None = None
_pool_size = 0


def _preload(modules: tuple[str, ...]) -> None:
    """A helper process's initializer: import what its stage needs, once."""
    for name in modules:
        importlib.import_module(name)


def _nothing() -> None:
    """A task that makes the pool start a process (it starts them on demand; the
    initializer imports)."""


def _helpers(count: int, spawn: int, modules: tuple[str, ...]) -> ProcessPoolExecutor:
    """The run's pool of at most ``count`` helper processes (the one already running when
    it has that size and is sound, else a new one importing ``modules``), with ``spawn``
    of them started now; the pool starts more when it is given more work."""
    global _pool, _pool_size
    with _lock:
        if _pool is not None and _pool_size != count:
            _pool.shutdown(wait=True, cancel_futures=True)
            _pool = None
        if _pool is None:
            _pool = ProcessPoolExecutor(max_workers=count, mp_context=multiprocessing.get_context("spawn"),
                                        initializer=_preload, initargs=(modules,))
            _pool_size = count
            for _ in range(spawn):  # the pool starts a process per task while none is idle
                _pool.submit(_nothing)
        elif modules:  # the running processes (or new ones) import them now, not on their first item
            for _ in range(spawn):
                _pool.submit(_preload, modules)
        return _pool


def _discard(pool: ProcessPoolExecutor) -> None:
    """Forget a pool whose process died (the next map starts a new one)."""
    global _pool
    with _lock:
        if _pool is pool:
            _pool = None
    pool.shutdown(wait=False, cancel_futures=True)


def shutdown() -> None:
    """Stop the helper processes (at exit; a later :meth:`Executor.map` starts new ones)."""
    global _pool
    with _lock:
        if _pool is not None:
            _pool.shutdown(wait=True, cancel_futures=True)
            _pool = None


atexit.register(shutdown)


def _in_dir(cwd: str, fn: Callable[..., T], item: Any) -> T:
    """``fn(item)`` in a helper process, run from the caller's working directory (the
    helpers outlive a ``chdir`` of the caller, and paths may be relative to it)."""
    if os.getcwd() != cwd:
        os.chdir(cwd)
    return fn(item)


def _map_shared(pool: ProcessPoolExecutor, helpers: int, fn: Callable[..., T], items: list[Any]) -> Iterator[T]:
    """``fn`` over ``items`` by ``helpers`` pool processes taking items from the front
    and this process taking them from the back, yielded in input order.

    A helper is handed its next item as soon as it finishes one (from the pool's
    callback, while this process works on its own), never queued more than that: a
    helper still starting up holds back one item at most.
    """
    cwd = os.getcwd()
    lock = threading.RLock()  # a callback on a finished future runs at once, in add_done_callback
    futures: dict[int, Future] = {}
    done: dict[int, T] = {}
    front, back, busy = 0, len(items), 0  # items[front:back] are not taken yet

    def feed(finished: Future | None = None) -> None:
        nonlocal front, busy
        with lock:
            busy -= finished is not None
            while front < back and busy < helpers:
                try:
                    future = pool.submit(_in_dir, cwd, fn, items[front])
                except RuntimeError:  # the pool is shutting down (at exit)
                    return
                futures[front] = future
                front += 1
                busy += 1
                future.add_done_callback(feed)

    try:
        for index in range(len(items)):
            feed()
            while True:
                with lock:
                    if index in done or (index in futures and futures[index].done()) or front >= back:
                        break
                    back -= 1
                    mine = back
                done[mine] = fn(items[mine])
            if index in done:
                result = done.pop(index)
            else:
                with lock:
                    future = futures.pop(index)
                try:
                    result = future.result()
                except BrokenProcessPool:
                    _discard(pool)
                    raise SlscanError("a worker process died (out of memory?); "
                                      "run again with fewer --workers") from None
            yield result
    finally:
        with lock:
            back = front  # hand out nothing more
            for future in futures.values():
                future.cancel()
            running = [f for f in futures.values() if not f.cancelled()]
        # a helper's item already under way finishes before the caller goes on (it may be
        # writing into a folder the caller is about to remove after an error)
        concurrent.futures.wait(running)


_MALLOC_TUNED: bool | None = None  # whether glibc took the thresholds; None: not tried yet
MMAP_THRESHOLD = 32 << 20
"""Allocations below this come from the heap on a Dask worker (glibc's own ceiling for its
dynamic threshold on 64-bit); freed heap above twice that goes back to the system."""


def _tune_malloc() -> bool:
    """Undo, once per Dask worker process, what Dask's ``MALLOC_TRIM_THRESHOLD_=65536``
    does to per-view work: setting any malloc threshold switches glibc's dynamic mmap
    threshold off, so every array above 128 KiB is mapped and unmapped afresh and its
    pages faulted in again. Measured on an albedo view: 10-20x the system time (1.3-2.3 s
    instead of 0.1 s), 2-3x the CPU. Setting the thresholds glibc itself would reach keeps
    big temporaries on the heap. Nothing happens off glibc."""
    global _MALLOC_TUNED
    if _MALLOC_TUNED is None:
        try:
            import ctypes

            libc = ctypes.CDLL("libc.so.6")
            _MALLOC_TUNED = (libc.mallopt(-3, MMAP_THRESHOLD) == 1  # M_MMAP_THRESHOLD
                             and libc.mallopt(-1, 2 * MMAP_THRESHOLD) == 1)  # M_TRIM_THRESHOLD
        except (OSError, AttributeError):
            _MALLOC_TUNED = False
        if not _MALLOC_TUNED:
            log.debug("malloc thresholds not set (not glibc?)")
    return _MALLOC_TUNED


def _on_dask_worker(cwd: str, fn: Callable[..., T], item: Any) -> T:
    """``fn(item)`` on a Dask worker, with the worker's malloc tuned for per-view work, from
    the caller's working directory when the worker has it (the same files at the same
    paths), so that paths relative to it resolve as for local helpers."""
    _tune_malloc()
    if os.getcwd() != cwd and os.path.isdir(cwd):
        os.chdir(cwd)
    return fn(item)


def _map_dask(address: str, fn: Callable[..., T], items: list[Any]) -> Iterator[T]:
    try:
        from distributed import Client
    except ImportError:
        raise SlscanError("--scheduler needs Dask: pip install 'dask[distributed]'") from None
    try:
        client = Client(address, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise SlscanError(f"--scheduler {address}: cannot reach the Dask scheduler ({exc})") from None
    try:
        log.info("running %d item(s) on the Dask cluster at %s", len(items), address)
        name = getattr(fn, "__name__", "slscan")  # the stage's task name on the dashboard
        futures = client.map(functools.partial(_on_dask_worker, os.getcwd(), fn), items, pure=False,
                             key=[f"{name}-{uuid.uuid4().hex}" for _ in items])
        for index, future in enumerate(futures):
            result = future.result()
            futures[index] = None  # the cluster forgets a result once it is here (146 views' range maps)
            future.release()
            yield result
    finally:
        client.close()


LOCAL = Executor()


def add_executor_arguments(parser) -> None:
    """Add ``--workers N`` and ``--scheduler tcp://HOST:PORT`` to an argparse parser."""
    group = parser.add_argument_group(
        "scale-out",
        "independent tasks (views; registration's pairs; fusion's and simplification's bricks) "
        "run in parallel")
    group.add_argument("--workers", type=int, metavar="N",
                       help="processes working on tasks, this one included (default: one per core); "
                            "the others start once per run and are reused by every stage")
    group.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                       help="run the tasks on this Dask distributed cluster instead "
                            "(its workers must see the same files at the same paths)")


def executor_from_args(args) -> Executor:
    """The :class:`Executor` asked for by :func:`add_executor_arguments`' options."""
    return Executor(scheduler=getattr(args, "scheduler", None), workers=getattr(args, "workers", None))
