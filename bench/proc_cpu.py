"""CPU time and minor page faults of a process, of some of this process's threads, or of the calling thread
(from /proc and getrusage; the benches' per-process CPU columns)."""

from __future__ import annotations

import os
import resource
from pathlib import Path


def process_cpu(pid: int | None = None, prefix: str = "") -> tuple[float, int]:
    """(user + system CPU seconds, minor page faults) so far of process ``pid`` (all threads), or of this
    process's threads whose name starts with ``prefix`` (``ZMQbg``: the sender's I/O thread); from /proc
    (Linux; (nan, 0) elsewhere)."""
    tick = os.sysconf("SC_CLK_TCK")
    stats = (
        [f"/proc/{pid}/stat"]
        if pid is not None
        else [f"/proc/self/task/{t}/stat" for t in os.listdir("/proc/self/task")]
        if os.path.isdir("/proc/self/task")
        else []
    )
    cpu, faults, seen = 0.0, 0, False
    for path in stats:
        try:
            text = Path(path).read_text()
        except OSError:  # a thread that just ended
            continue
        name, f = text[text.index("(") + 1 : text.rindex(")")], text[text.rindex(")") + 2 :].split()
        if name.startswith(prefix):
            cpu, faults, seen = cpu + (int(f[11]) + int(f[12])) / tick, faults + int(f[7]), True
    return (cpu, faults) if seen else (float("nan"), 0)


def thread_cpu(since: dict | None = None) -> dict:
    """CPU seconds and minor page faults of the calling thread so far, or since the reading ``since``."""
    r = resource.getrusage(getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF))
    now = {"cpu_s": r.ru_utime + r.ru_stime, "faults": r.ru_minflt}
    return now if since is None else {k: now[k] - since[k] for k in now}
