"""The drivers' error tree: :class:`DriverError` under :class:`polarstripe.errors.PolarstripeError`.

Like python-can's ``can/exceptions.py``: a small tree, the timeout class is also a :class:`TimeoutError`, bad
argument values are also :class:`ValueError`. Every message names the device, endpoint or field and the value.
"""

from __future__ import annotations

from polarstripe.errors import PolarstripeError


class DriverError(PolarstripeError):
    """A hardware driver failed: the device, port or endpoint is named in the text."""


class DriverTimeout(DriverError, TimeoutError):
    """A device did not answer, move or deliver in time."""


class DriverValueError(DriverError, ValueError):
    """A bad argument value (an angle beyond the limits, an unknown pattern, a negative exposure)."""


class BackendUnavailable(DriverError, ImportError):
    """A backend cannot be loaded: unknown name, or a module (an optional extra) that failed to import."""


class DeviceError(DriverError):
    """The device answered with an error code (ELL14 ``GSxx``, trigger box ``ERR``)."""


class DeviceLost(DriverError):
    """The device disappeared while in use (a camera unplugged, a serial port closed)."""


class FrameDropped(DriverError):
    """A frame did not arrive whole (stream packets lost, a transfer cut short): it is not delivered, the
    camera stays open, and the next grab may succeed."""


class EndOfFrames(DriverError):
    """A file camera has no more frames (and does not loop)."""


class StageFault(DriverError):
    """The rotation stage is faulted; the text is the fault. ``reset_fault()`` tries to clear it."""
