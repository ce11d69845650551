"""A rotation stage with no bus at all: a motion model in the calling process, for fast node tests.

It moves at a finite speed, settles after ``settle_s`` and can be told to fault
(:meth:`SimStage.inject_fault`) or never to settle (:meth:`SimStage.inject_never_settle`). It models no
protocol: for the CAN path use :class:`~.simdrive.SimCia402Drive` with :class:`~.cia402.Cia402Stage`, for the
serial path :class:`~.simell14.SimEll14` with :class:`~.ell14.Ell14Stage`.
"""

from __future__ import annotations

import threading
import time

from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.stage import RotationStage


class SimStage(RotationStage):
    """An in-process stage: ``deg_per_s`` speed, ``settle_s`` settle time, starts at ``start_deg``."""

    class Options(BackendOptions):
        deg_per_s: float = 180.0  # rotation speed [deg/s]
        settle_s: float = 0.01  # settle time after a move [s]
        start_deg: float = 0.0  # where it starts [deg]

    def __init__(
        self,
        *,
        deg_per_s: float = 180.0,
        settle_s: float = 0.01,
        start_deg: float = 0.0,
        min_deg: float = -360.0,
        max_deg: float = 360.0,
    ):
        super().__init__(min_deg=min_deg, max_deg=max_deg, name="sim stage")
        self.deg_per_s, self.settle_s = deg_per_s, settle_s
        self._lock = threading.Lock()
        self._from, self._to, self._t0 = start_deg, start_deg, -1e9
        self._never_settle = False

    def _position(self, now: float) -> tuple[float, bool]:
        """(angle, settled) of the motion model at time ``now``."""
        with self._lock:
            span = self._to - self._from
            duration = abs(span) / self.deg_per_s
            t = now - self._t0
            if self._never_settle:
                return self._to + 0.05, False
            if t >= duration:
                return self._to, t >= duration + self.settle_s
            return self._from + span * t / duration, False

    def _start_move(self, angle_deg: float) -> None:
        now = time.monotonic()
        here, _ = self._position(now)
        with self._lock:
            self._from, self._to, self._t0 = here, angle_deg, now

    def _read_angle(self) -> float | None:
        return self._position(time.monotonic())[0]

    def _is_settled(self) -> bool:
        return self._target_deg is not None and self._position(time.monotonic())[1]

    def _reset(self) -> None:
        self._never_settle = False
        self._start_move(self._position(time.monotonic())[0])
        self._target_deg = self._to

    def _home(self, timeout: float) -> None:
        self._target_deg = 0.0
        self._start_move(0.0)
        self.wait_settled(timeout)

    def inject_fault(self, text: str = "injected fault") -> None:
        self._latch_fault(text)

    def inject_never_settle(self, on: bool = True) -> None:
        self._never_settle = on
