"""How many threads the model uses (the ``threads`` of ``polarstripe render`` and the simulator node).

Default: the cores this process may run on (its CPU affinity). :func:`set_threads` changes it for the
process; every parallel part splits work whose pieces are computed independently, so a frame is
bit-identical whatever the count (``tests/sim/test_threads.py``):

* the higher orders' FFTs (:func:`fft_workers`: scipy's pocketfft splits its batches of 1-D transforms);
* the per-pixel compiled kernels (:func:`in_bands`: bands of pixels, rows or a ray's intervals, each in a
  thread of a shared pool; the kernels release the GIL);
* OpenCV's blurs and resizes (``cv2.setNumThreads``).

numpy's BLAS is held to one thread where the model calls it (:func:`blas_one_thread`): its products there
are small, and an idle OpenBLAS thread spins, burning the CPU the frame workers need.

Whole frames in parallel (:func:`each_frame`, :func:`submit_frame`) scale better: a scan's frames are
independent and the model's kernels, numpy's and OpenCV's passes release the GIL, so ``threads`` frames
render at once on a pool of their own, each with one model thread (:func:`threads` is 1 inside a frame
worker; a frame is the same either way): :func:`polarstripe.sim.render.render_each`, the simulator node's
scan and ``polarstripe bench fidelity --threads N``.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor

import cv2
import numpy as np
from threadpoolctl import ThreadpoolController

_state = {"threads": None, "pool": None, "frames": None, "blas": None}
_lock = threading.Lock()
_local = threading.local()         # .threads: 1 inside a frame worker


def available() -> int:
    """The cores this process may run on (its CPU affinity; ``os.cpu_count()`` where there is none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def threads() -> int:
    """The model's thread count (default :func:`available`; 1 inside a frame worker)."""
    own = getattr(_local, "threads", None)
    if own is not None:
        return own
    if _state["threads"] is None:
        set_threads(None)
    return _state["threads"]


def set_threads(count: int | None) -> int:
    """Use ``count`` threads (None or 0: :func:`available`); returns the count in effect.

    Raises
    ------
    ValueError
        ``count`` negative or not an integer.
    """
    if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 0):
        raise ValueError(f"threads must be a non-negative integer (0: the CPU affinity), got {count!r}")
    n = available() if not count else int(count)
    with _lock:
        if _state["threads"] != n:
            _state["threads"] = n
            cv2.setNumThreads(n if n > 1 else 0)   # 0: OpenCV runs its loops in the calling thread
            for name in ("pool", "frames"):
                old, _state[name] = _state[name], None
                if old is not None:
                    old.shutdown(wait=False)
    return n


def blas_one_thread():
    """A context in which numpy's BLAS runs in the calling thread (threadpoolctl; the limit is the
    process's, so a frame worker's exit may lift it early for another: only the speed depends on it)."""
    with _lock:
        if _state["blas"] is None:
            _state["blas"] = ThreadpoolController()
        controller = _state["blas"]
    return controller.limit(limits=1, user_api="blas")


def fft_workers() -> int:
    """Workers for scipy.fft."""
    return threads()


def _forget_pool() -> None:
    """In a forked child: the parent's pool threads do not exist there; the next band makes a new pool. The
    lock is new too (a parent thread may have held it at the fork)."""
    global _lock
    _lock = threading.Lock()
    _state["pool"] = _state["frames"] = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _pool() -> ThreadPoolExecutor:
    with _lock:
        if _state["pool"] is None:
            _state["pool"] = ThreadPoolExecutor(_state["threads"], thread_name_prefix="model")
        return _state["pool"]


def in_bands(count: int, run, min_size: int = 4096, starts: np.ndarray | None = None) -> None:
    """Call ``run(first, end)`` over bands of ``range(count)`` (pixels, image rows, intervals), in parallel
    with more than one thread (bands of at least ``min_size``); ``run`` must compute each item on its own and
    write only its own items. ``starts`` (sorted item indices): bands begin only there (the intervals of
    one ray stay in one band)."""
    n = min(threads(), max(1, count // max(min_size, 1)))
    if n <= 1:
        run(0, count)
        return
    edges = [count * k // n for k in range(n + 1)]
    if starts is not None:                      # move each inner edge to the next allowed start
        at = np.searchsorted(starts, edges[1:-1])
        edges = sorted({0, count, *(int(starts[i]) if i < starts.size else count for i in at)})
    futures = [_pool().submit(run, a, b) for a, b in zip(edges[1:-1], edges[2:], strict=True)]
    run(edges[0], edges[1])
    for f in futures:
        f.result()


def _one_thread(fn, args):
    _local.threads = 1
    try:
        return fn(*args)
    finally:
        _local.threads = None


def submit_frame(fn, *args) -> Future:
    """``fn(*args)`` on the frame pool (:func:`threads` workers, first in first out), with one model thread
    inside; its Future."""
    n = threads()
    with _lock:
        if _state["frames"] is None:
            _state["frames"] = ThreadPoolExecutor(n, thread_name_prefix="frame")
        pool = _state["frames"]
    return pool.submit(_one_thread, fn, args)


def each_frame(fn, items) -> list:
    """``[fn(x) for x in items]`` with the frames in parallel (:func:`submit_frame`); in this thread, with
    its own thread count, when there is one thread, one item, or this is a frame worker already. ``fn``
    must not change what another frame reads (the model's caches are safe: sim/geometry_cache.py)."""
    items = list(items)
    if threads() <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    futures = [submit_frame(fn, x) for x in items]
    return [f.result() for f in futures]
