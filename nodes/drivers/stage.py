"""The rotation stage role: the polarizer's analyzer angle, whatever moves it.

:class:`RotationStage` owns what every backend shares: software limits, the fault latch, waiting for the stage
to settle with a timeout, the context manager and an idempotent :meth:`~RotationStage.close`. A backend
implements :meth:`_start_move`, :meth:`_read_angle`, :meth:`_is_settled`, :meth:`_reset` and :meth:`_home`,
and declares its ``Options`` (nodes/drivers/backend.py); the software limits are the node's, passed to every
backend (``min_deg``, ``max_deg``).

The contract that matters to the polarizer node: a stage never reports a wrong angle. While the position is
not known to be true (a fault is latched, the data are stale, a move is in flight on a device that cannot
report it) :attr:`~RotationStage.angle` is ``None`` and :attr:`~RotationStage.settled` is ``False``.
"""

from __future__ import annotations

import math
import threading
import time
from abc import ABC, abstractmethod

from polarstripe.nodes.drivers.backend import Backend
from polarstripe.nodes.drivers.errors import DriverTimeout, DriverValueError, StageFault


class RotationStage(Backend, ABC):
    """A rotation stage: ``move_to(angle_deg)``, then ``wait_settled``; faults are latched as text.

    :param min_deg, max_deg: software limits [deg]; a target outside raises :class:`DriverValueError`.
    :param name: how the stage is named in error texts (port, channel and node id).
    """

    def __init__(self, *, min_deg: float = -math.inf, max_deg: float = math.inf, name: str = "stage"):
        if not min_deg < max_deg:
            raise DriverValueError(
                f"{name}: software limits min_deg={min_deg} must be below max_deg={max_deg}"
            )
        self.min_deg, self.max_deg, self.name = float(min_deg), float(max_deg), name
        self._faults: list[str] = []
        self._fault_lock = threading.Lock()
        self._target_deg: float | None = None
        self._closed = False

    # -- the public interface -----------------------------------------------------------------------------
    def move_to(self, angle_deg: float) -> None:
        """Start a move to ``angle_deg`` [deg] and return once the device accepted it.

        :raises DriverValueError: the angle is not finite or is outside ``[min_deg, max_deg]``.
        :raises StageFault: a fault is latched (``reset_fault()`` first) or the command failed.
        """
        angle = float(angle_deg)
        if not math.isfinite(angle) or not self.min_deg <= angle <= self.max_deg:
            raise DriverValueError(
                f"{self.name}: target angle_deg={angle_deg!r} outside the limits "
                f"[{self.min_deg}, {self.max_deg}]"
            )
        self._check_open()
        self._raise_if_faulted()
        self._target_deg = angle
        self._start_move(angle)

    @property
    def angle(self) -> float | None:
        """The measured angle [deg], or ``None`` while it is not known to be true (fault, stale, moving
        blind)."""
        if self._closed or self.fault is not None:
            return None
        return self._read_angle()

    @property
    def target(self) -> float | None:
        """The last commanded angle [deg], or ``None`` before the first move."""
        return self._target_deg

    @property
    def settled(self) -> bool:
        """True when the stage stands still at its target and no fault is latched."""
        return not self._closed and self.fault is None and self._is_settled()

    @property
    def fault(self) -> str | None:
        """The latched fault text (several causes joined by "; "), or ``None``."""
        with self._fault_lock:
            return "; ".join(self._faults) if self._faults else None

    def wait_settled(self, timeout: float = 10.0, poll_s: float = 0.005) -> float:
        """Wait until the stage is settled; return the settled angle [deg].

        A stage that does not settle in time latches a fault (it never hangs and never claims an angle).

        :raises StageFault: a fault appeared while waiting.
        :raises DriverTimeout: not settled within ``timeout`` seconds (the fault is latched too).
        """
        deadline = time.monotonic() + timeout
        while True:
            self._raise_if_faulted()
            if self._is_settled():
                angle = self._read_angle()
                if angle is not None and self.fault is None:
                    return angle
            if time.monotonic() >= deadline:
                break
            time.sleep(poll_s)
        text = (
            f"target {self._target_deg}° not reached within {timeout:g} s "
            f"(last reading {self._read_angle()}°)"
        )
        self._latch_fault(text)
        raise DriverTimeout(f"{self.name}: {text}")

    def reset_fault(self) -> None:
        """Clear the latched fault with the device's own reset sequence.

        :raises StageFault: the device is still faulted (the cause persists); the fault stays latched.
        """
        self._check_open()
        self._reset()
        with self._fault_lock:
            self._faults.clear()

    def home(self, timeout: float = 30.0) -> None:
        """Run the device's homing (the ELL14's ``ho``; a CiA 402 drive's homing method, by default 37: the
        current position becomes 0°); on return the angle is 0° and settled.

        :raises StageFault, DriverTimeout: as for a move.
        """
        self._check_open()
        self._raise_if_faulted()
        self._home(timeout)
        self._target_deg = 0.0

    def close(self) -> None:
        """Release the device; idempotent."""
        if self._closed:
            return
        self._closed = True
        self._close()

    # -- for backends -------------------------------------------------------------------------------------
    def _latch_fault(self, text: str) -> None:
        with self._fault_lock:
            if text not in self._faults:
                self._faults.append(text)

    def _raise_if_faulted(self) -> None:
        fault = self.fault
        if fault is not None:
            raise StageFault(f"{self.name}: {fault}")

    def _check_open(self) -> None:
        if self._closed:
            raise StageFault(f"{self.name}: closed")

    @abstractmethod
    def _start_move(self, angle_deg: float) -> None: ...

    @abstractmethod
    def _read_angle(self) -> float | None: ...

    @abstractmethod
    def _is_settled(self) -> bool: ...

    @abstractmethod
    def _reset(self) -> None: ...

    @abstractmethod
    def _home(self, timeout: float) -> None: ...

    def _close(self) -> None:  # noqa: B027 - optional hook
        pass
