"""A big fleet's passes over its rows spread over threads, one contiguous range of rows each.

numpy releases the GIL inside its loops over arrays, so the same operations applied to two halves of the rows in
two threads run on two cores at once (measured on a 2-core host: 45 ms in one thread, 17-21 ms in two, for the
offsets and weights of eq. (3) over 10^6 pairs). Every row is computed by the same operations in either case, so
the results are the same bits whatever the number of threads. Work of fewer than 2 * `min_work` array elements
stays in the calling thread: handing work to a thread, and its data to another core's cache, costs more than it
saves below ~10^5 elements per pass on a 2-core virtual machine (a 10,000-agent fleet stepped 8 % slower split in
two, a 100,000-agent one 1.3 times faster).
"""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

Result = TypeVar("Result")

# Array elements per range below which a pass is not split.
DEFAULT_MIN_WORK = 100_000

_pools: dict[int, ThreadPoolExecutor] = {}
_pools_lock = threading.Lock()
if hasattr(os, "register_at_fork"):  # a forked child has none of its parent's threads: it makes its own pools
    os.register_at_fork(after_in_child=_pools.clear)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports it, else the CPU count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def _pool(workers: int) -> ThreadPoolExecutor:
    """The process's shared pool of `workers` threads (made on first use)."""
    with _pools_lock:
        pool = _pools.get(workers)
        if pool is None:
            pool = _pools[workers] = ThreadPoolExecutor(workers, thread_name_prefix="bob-rows")
        return pool


class RowThreads:
    """Splits [0, n) into contiguous ranges and runs a function of (lo, hi) on each, one range per thread.

    threads: ranges at most (1: everything in the calling thread; None: the cores available).
    min_work: array elements per range at least (the rows' share of the work a caller states).
    """

    def __init__(self, threads: int | None = None, min_work: int = DEFAULT_MIN_WORK) -> None:
        threads = available_cores() if threads is None else threads
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be a whole number >= 1, not {threads!r}")
        if min_work < 1:
            raise ValueError(f"min_work must be >= 1, not {min_work!r}")
        self.threads = threads
        self.min_work = min_work

    def ranges(self, n: int, work: int | None = None) -> list[tuple[int, int]]:
        """Contiguous (lo, hi) ranges covering [0, n) in order: as many as the threads, and as `work` (array
        elements the n rows' passes touch; default n) allows at min_work each."""
        k = min(self.threads, (n if work is None else work) // self.min_work, n)
        if k <= 1:  # (every small fleet's step, several times: no list to build)
            return [(0, n)]
        edges = [n * i // k for i in range(k + 1)]
        return list(itertools.pairwise(edges))

    def map(self, work: Callable[[int, int], Result], ranges: Sequence[tuple[int, int]]) -> list[Result]:
        """[work(lo, hi) for each range], the first in the calling thread and the others in the pool's threads
        at the same time; an exception in any is raised here (after all have finished)."""
        if len(ranges) <= 1:
            return [work(lo, hi) for lo, hi in ranges]
        pool = _pool(self.threads - 1)
        futures = [pool.submit(work, lo, hi) for lo, hi in ranges[1:]]
        try:
            first = work(*ranges[0])
        finally:
            wait(futures)  # never leave a thread working on arrays the caller is about to change
        return [first, *(future.result() for future in futures)]

    def map_rows(self, work: Callable[[int, int], Result], n: int, elements: int | None = None) -> list[Result]:
        """`map` over `ranges(n, elements)`."""
        return self.map(work, self.ranges(n, elements))

    def flatnonzero(self, mask: NDArray[np.bool_]) -> NDArray[np.intp]:
        """np.flatnonzero(mask) of a 1-D mask, in parts."""
        ranges = self.ranges(mask.size)
        if len(ranges) == 1:
            return np.flatnonzero(mask)
        return np.concatenate(self.map(lambda lo, hi: np.flatnonzero(mask[lo:hi]) + lo, ranges))


ONE_THREAD = RowThreads(1)  # everything in the calling thread (the default of the parts that take `threads`)
