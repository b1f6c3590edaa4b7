"""One executor for per-view work: local processes by default, a Dask cluster on request.

Per-view stages (decode, albedo) hand their views to :func:`map_views`. With one view or
``workers=1`` the work runs in this process; otherwise in a pool of local processes
(``spawn``-started, so no thread of this process — Rerun's, open3d's — is forked), or on
a Dask distributed cluster when a scheduler address is given (``tcp://HOST:PORT``).
Results come back in input order; logging to Rerun stays in the calling process.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

from slscan.errors import SlscanError

log = logging.getLogger(__name__)
T = TypeVar("T")


@dataclass(frozen=True)
class Executor:
    """Where per-view work runs.

    scheduler : Dask scheduler address (``tcp://HOST:PORT``), or None for local processes
    workers : local processes at most (default: the machine's cores); ignored with Dask
    """

    scheduler: str | None = None
    workers: int | None = None

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise SlscanError(f"--workers must be at least 1, got {self.workers}")
        if self.scheduler is not None and "://" not in self.scheduler:
            raise SlscanError(f"--scheduler {self.scheduler!r}: expected an address like tcp://HOST:8786")

    def map(self, fn: Callable[..., T], items: Sequence[Any]) -> Iterator[T]:
        """``fn(item)`` for every item, yielded in order as they are ready in order."""
        items = list(items)
        if self.scheduler is not None:
            yield from _map_dask(self.scheduler, fn, items)
            return
        workers = min(len(items), self.workers or os.cpu_count() or 1)
        if workers <= 1:
            for item in items:
                yield fn(item)
            return
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            yield from pool.map(fn, items)


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
        futures = client.map(fn, items, pure=False)
        for future in futures:
            yield future.result()
    finally:
        client.close()


LOCAL = Executor()


def add_executor_arguments(parser) -> None:
    """Add ``--workers N`` and ``--scheduler tcp://HOST:PORT`` to an argparse parser."""
    group = parser.add_argument_group("scale-out", "per-view stages run in parallel over views")
    group.add_argument("--workers", type=int, metavar="N", help="local worker processes (default: one per core)")
    group.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                       help="run per-view work on this Dask distributed cluster instead "
                            "(its workers must see the same files)")


def executor_from_args(args) -> Executor:
    """The :class:`Executor` asked for by :func:`add_executor_arguments`' options."""
    return Executor(scheduler=getattr(args, "scheduler", None), workers=getattr(args, "workers", None))
