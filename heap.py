"""Freed memory kept in the process (glibc malloc), for code that allocates and frees the same large buffers
over and over: the model's few-MB arrays frame after frame (docs/physics.md §10.6), the recorder's receive
buffers message after message (docs/architecture.md, "Throughput").

glibc serves a block above its mmap threshold with a fresh mapping, and gives the free top of its heap back to
the kernel beyond its trim threshold (by default twice the largest block freed so far). Either way the next
buffer's pages are faulted in again: 3000–4600 minor faults and 13–17 ms of system time per 640×480 model
frame, one fault per page of every received frame. :func:`keep_freed` serves blocks up to 32 MB (the largest
mmap threshold glibc takes on 64-bit) from the heap and keeps up to ``keep_bytes`` of freed heap.

Process-wide and Linux/glibc only; elsewhere it does nothing and returns False. :func:`shared_zeros`: a
read-only array of zeros kept per shape, for the fields a frame leaves at zero (no frame allocates and
clears its own).
"""

from __future__ import annotations

import ctypes

import numpy as np

_M_TRIM_THRESHOLD = -1  # malloc.h
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 << 20
KEEP_BYTES = 256 << 20

try:
    # the process's own symbols (libc's among them): ctypes.util.find_library would run /sbin/ldconfig in a
    # child process at every node's import, one that a stop signal can leave behind (runtime/pgroups.py)
    _mallopt = ctypes.CDLL(None).mallopt
    _mallopt.argtypes, _mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to tune
    _mallopt = None


def keep_freed(keep_bytes: int = KEEP_BYTES) -> bool:
    """Serve buffers up to 32 MB from the heap and keep up to ``keep_bytes`` of freed heap in the process
    (``mallopt(M_MMAP_THRESHOLD)``, ``mallopt(M_TRIM_THRESHOLD)``); True if the C library took both."""
    if _mallopt is None:
        return False
    keep = max(0, min(int(keep_bytes), 2**31 - 1))
    return bool(_mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)) and bool(_mallopt(_M_TRIM_THRESHOLD, keep))


_ZEROS: dict = {}


def shared_zeros(shape) -> np.ndarray:
    """A read-only float64 array of zeros of ``shape``, the same array for every caller (the last 8 shapes
    are kept); writing into it raises."""
    key = tuple(int(n) for n in np.atleast_1d(shape))
    z = _ZEROS.get(key)
    if z is None:
        z = np.zeros(key)
        z.flags.writeable = False
        if len(_ZEROS) >= 8:
            _ZEROS.clear()
        _ZEROS[key] = z
    return z
