"""Receive buffers that reuse memory the process already has (glibc malloc), for a node that takes in large
messages as fast as it can write them (the recorder).

ZeroMQ receives each message into a buffer it ``malloc``s on its I/O thread and ``free``s when the message
is dropped. glibc serves a 2.6 MB buffer either with a fresh ``mmap`` or from its heap, and gives the top of
the heap back to the kernel once more than ``M_TRIM_THRESHOLD`` of it is free (by default twice the largest
buffer freed so far): so frame after frame lands in fresh pages, each page faulted in on receive (on a VM
that hands freed memory back to its host, a fault on the host too: bench/record.py's docstring). With
:func:`keep_freed_buffers`, buffers up to 32 MB come from the heap and up to ``keep_bytes`` of freed memory
stays in the process, so a node that bounds how many messages it holds at once (``subscribe(queue=…)``)
receives every frame into pages that are already mapped.

Process-wide and Linux/glibc only; elsewhere it does nothing and says so.
"""

from __future__ import annotations

import ctypes
import ctypes.util

_M_TRIM_THRESHOLD = -1  # malloc.h
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 << 20  # glibc's upper bound for M_MMAP_THRESHOLD on 64-bit (larger is refused)

try:
    _mallopt = ctypes.CDLL(ctypes.util.find_library("c") or None).mallopt
    _mallopt.argtypes, _mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to tune
    _mallopt = None


def keep_freed_buffers(keep_bytes: int) -> bool:
    """Serve buffers up to 32 MB from the heap and keep up to ``keep_bytes`` of freed heap in the process
    (``mallopt(M_MMAP_THRESHOLD)``, ``mallopt(M_TRIM_THRESHOLD)``); True if the C library took both."""
    if _mallopt is None:
        return False
    keep = max(0, min(int(keep_bytes), 2**31 - 1))
    return bool(_mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)) and bool(_mallopt(_M_TRIM_THRESHOLD, keep))
