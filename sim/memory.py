"""Keeping freed memory for the next frame (docs/physics.md §10.6).

A 640×480 frame allocates and frees the same few-MB arrays (2.4 MB per float64 image) frame after frame.
glibc's malloc serves blocks above its mmap threshold with fresh mappings and returns the heap's free top
beyond its trim threshold to the system, so every frame faulted the pages of those arrays in again: 3000
(`standard`) to 4600 (`preview`) minor page faults, 13–17 ms of system time a frame on the 2-core machine.
:func:`keep_freed` raises both thresholds once per process (the largest mmap threshold glibc takes, 32 MB,
and a trim threshold of 256 MB), so freed blocks are reused; elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024
TRIM_THRESHOLD = 256 * 1024 * 1024
_state = {"done": False}


def keep_freed() -> bool:
    """Raise glibc's mmap and trim thresholds (once); True where glibc took both."""
    if _state["done"]:
        return _state["ok"]
    _state["done"], _state["ok"] = True, False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _state["ok"] = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _state["ok"]
