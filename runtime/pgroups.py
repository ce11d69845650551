"""What a node leaves in its process group when it exits: the launcher waits for it, then kills it.

A node runs in a session (and process group) of its own, and so does every process it starts without
``start_new_session``. Such a child can outlive the node: one a stop signal cut short in the middle of
``subprocess`` (Python then gives the child 0.25 s and returns without reaping it), or any helper process
a library starts. Orphaned, it belongs to init, which reaps it whenever it gets to it. The launcher makes
itself the *child subreaper* of its descendants (Linux ``prctl(PR_SET_CHILD_SUBREAPER)``), so those
orphans become its children: after the nodes it reaps what is left in each node's group, waits up to
``shutdown_timeout`` for the rest, and sends SIGKILL to what is still there, saying so. A launch leaves no
process behind (tests/launch/test_sigint.py).
"""

from __future__ import annotations

import ctypes
import os
import signal
import time
from collections.abc import Callable

_PR_SET_CHILD_SUBREAPER, _PR_GET_CHILD_SUBREAPER = 36, 37  # linux/prctl.h


def set_subreaper(on: bool) -> bool | None:
    """Make this process the subreaper of its descendants (``on``) or not; returns the previous setting,
    or None where the system has none (not Linux)."""
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    old = ctypes.c_int(0)
    if prctl(_PR_GET_CHILD_SUBREAPER, ctypes.byref(old), 0, 0, 0) != 0:
        return None
    prctl(_PR_SET_CHILD_SUBREAPER, int(on), 0, 0, 0)
    return bool(old.value)


def _reap(pgid: int) -> None:
    """Reap this process's exited children in process group ``pgid`` (the orphans it adopted)."""
    try:
        while os.waitpid(-pgid, os.WNOHANG)[0]:
            pass
    except ChildProcessError:
        pass


def _alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # a member that is no longer ours (it changed user): not ours to wait for
        return False
    return True


def reap_groups(groups: dict[int, str], timeout_s: float, say: Callable[[str], None]) -> list[str]:
    """Once the group leaders (the nodes, ``{pgid: name}``) are reaped: wait up to ``timeout_s`` for the
    rest of each group to exit, then SIGKILL what is left (one line each through ``say``) and wait up to
    1 s more. Returns the names whose group had to be killed."""
    left = dict(groups)
    killed: list[str] = []
    deadline = time.monotonic() + timeout_s
    while True:
        for pgid in list(left):
            _reap(pgid)
            if not _alive(pgid):
                del left[pgid]
        if not left:
            return killed
        if time.monotonic() > deadline:
            if killed:  # killed 1 s ago and still there: a zombie of another parent, or stuck in the kernel
                say(f"processes left in the group of {', '.join(left.values())} did not go away")
                return killed
            for pgid, name in left.items():
                say(f"{name} left processes in its group after it exited: SIGKILL")
                try:
                    os.killpg(pgid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                killed.append(name)
            deadline = time.monotonic() + 1.0
        time.sleep(0.02)


def dump_stacks(pids: list[int], settle_s: float = 0.3) -> None:
    """SIGUSR1 to each node process of ``pids``: from its first line it writes every thread's Python stack to
    its log on that signal (``faulthandler``, __main__.py), even while it is stuck in C code holding the GIL.
    Then ``settle_s`` for the writes. Only the node's own process: a child it started may not handle it."""
    for pid in pids:
        try:
            os.kill(pid, signal.SIGUSR1)
        except ProcessLookupError:
            pass
    time.sleep(settle_s)
