"""What the model's dearest step cost inside a block, for benches: the field transforms that the orders'
propagations made (:func:`polarstripe.sim.multiple.propagate`, one per source of a batch, or per basis source
of a batch in low rank) and the process CPU they took.

``with propagations() as t: …`` then reads ``t.transforms`` and ``t.cpu_s``. Nothing is counted while no block
is open. The CPU is the process's: on one model thread (:mod:`polarstripe.sim.threads`) it is the
propagations' own."""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass


@dataclass
class Tally:
    transforms: int = 0
    cpu_s: float = 0.0


_open: list[Tally] = []


@contextlib.contextmanager
def propagations():
    """A :class:`Tally` of the propagations made inside the block."""
    t = Tally()
    _open.append(t)
    try:
        yield t
    finally:
        _open.remove(t)


def start() -> float | None:
    """The process CPU now if a block is open (for :func:`add`), else None."""
    return time.process_time() if _open else None


def add(transforms: int, since: float | None) -> None:
    """Count ``transforms`` made since ``since`` (:func:`start`) in every open block."""
    if since is None:
        return
    cpu = time.process_time() - since
    for t in _open:
        t.transforms += int(transforms)
        t.cpu_s += cpu
