"""Thread-pool helpers (numpy, OpenCV and open3d release the GIL in their heavy work)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def ordered_map(fn: Callable[[T], R], items: Iterable[T], threads: int) -> Iterator[R]:
    """``map(fn, items)`` on a thread pool, at most ``2 * threads`` items in flight, in order;
    the first exception is raised and pending work is cancelled."""
    if threads <= 1:
        yield from map(fn, items)
        return
    pending: list[Future[R]] = []
    with ThreadPoolExecutor(max_workers=threads) as pool:
        try:
            for item in items:
                pending.append(pool.submit(fn, item))
                if len(pending) >= 2 * threads:
                    yield pending.pop(0).result()
            while pending:
                yield pending.pop(0).result()
        finally:
            for f in pending:
                f.cancel()
