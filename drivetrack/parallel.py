"""Where the core's independent loops run: in the caller's thread, or the segment's thread pool.

``annotate``'s ``threads`` option gives the segment a thread pool; the depth maps and the object
jobs are mapped over it explicitly. Loops deeper in the core (the per-frame box membership of the
plan and of the label-time vote, the per-clip label consistency) reach it through :func:`pool_map`, which uses the pool the
caller installed with :func:`using` and runs serially otherwise, so every function keeps one
signature and gives the same result, in the same order, either way. Work already running on a
pool thread maps serially (the installed pool belongs to the installing thread's context), so
nested maps never wait on their own pool.
"""
from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterable, Iterator, TypeVar

__all__ = ["pool_map", "using"]

T = TypeVar("T")
R = TypeVar("R")

_MAP: ContextVar[Callable | None] = ContextVar("drivetrack_pool_map", default=None)


def pool_map(function: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[function(item) for item in items]``, on the installed pool when there is one (results
    in item order). ``function`` must be safe to run in threads (no shared writes)."""
    mapper = _MAP.get()
    items = list(items)
    if mapper is None or len(items) < 2:
        return [function(item) for item in items]
    return list(mapper(function, items))


@contextmanager
def using(map_fn: Callable | None) -> Iterator[None]:
    """Install ``map_fn(function, items)`` (e.g. a ThreadPoolExecutor's ``map``; None: serial)
    for :func:`pool_map` calls made in this context."""
    token = _MAP.set(map_fn)
    try:
        yield
    finally:
        _MAP.reset(token)
