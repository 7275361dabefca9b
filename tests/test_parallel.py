"""drivetrack.parallel: the per-frame loops of the core run on the installed pool, in order, and
nested maps from pool threads run serially (a one-worker pool would otherwise wait on itself)."""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

from drivetrack import parallel


def test_pool_map_uses_the_installed_pool_in_item_order():
    caller = threading.get_ident()
    seen = []

    def work(item):
        seen.append(threading.get_ident())
        return item * item

    assert parallel.pool_map(work, range(6)) == [0, 1, 4, 9, 16, 25]
    assert set(seen) == {caller}
    seen.clear()
    with ThreadPoolExecutor(2) as pool, parallel.using(pool.map):
        assert parallel.pool_map(work, range(6)) == [0, 1, 4, 9, 16, 25]
    assert caller not in seen
    seen.clear()
    assert parallel.pool_map(work, range(3)) == [0, 1, 4]     # uninstalled on leaving the block
    assert set(seen) == {caller}


def test_nested_maps_on_a_pool_thread_run_serially():
    with ThreadPoolExecutor(1) as pool, parallel.using(pool.map):
        def outer(item):
            inner = parallel.pool_map(lambda x: (x, threading.get_ident()), range(3))
            return item, {ident for _, ident in inner} == {threading.get_ident()}

        assert parallel.pool_map(outer, range(4)) == [(i, True) for i in range(4)]
