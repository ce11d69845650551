"""The display / trigger role: what the projector (or laser line) lights now, and the projector image.

Pattern conventions are the light-transport model's (``polarstripe.sim.patterns``), for a projector ``W``
pixels wide and ``H`` high, row 0 at the top:

* ``flood`` lights every pixel, ``off`` none; * ``stripe:K/N`` lights columns ``floor(K·W/N)`` …
``floor((K+1)·W/N) − 1`` (0 ≤ K < N); * ``checker:SIZE:SHIFT`` lights the pixels where ``floor((col −
SHIFT)/SIZE) + floor(row/SIZE)`` is even.

:class:`Display` owns the shared behaviour (pattern parsing and validation, the current pattern, the context
manager, an idempotent :meth:`~Display.close`); a backend implements ``_show``. :class:`NullDisplay` (CI, the
simulator) lights nothing and remembers what it was asked to show.
"""

from __future__ import annotations

import re
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass

import numpy as np
from polarstripe.nodes.drivers.errors import DriverError, DriverValueError

KINDS = ("flood", "stripe", "checker", "off")


@dataclass(frozen=True)
class DisplayPattern:
    """What to light: ``kind``; stripe ``index`` of ``count``; checker squares ``size`` px, ``shift`` px."""

    kind: str
    index: int = 0
    count: int = 0
    size: int = 0
    shift: int = 0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise DriverValueError(f"pattern kind={self.kind!r} is not one of {', '.join(KINDS)}")
        if self.kind == "stripe" and not (self.count >= 1 and 0 <= self.index < self.count):
            raise DriverValueError(
                f"stripe pattern index={self.index} count={self.count}: need 0 <= index < count"
            )
        if self.kind == "checker" and not (self.size >= 1 and self.shift >= 0):
            raise DriverValueError(
                f"checker pattern size={self.size} shift={self.shift}: need size >= 1, shift >= 0"
            )

    def __str__(self) -> str:
        if self.kind == "stripe":
            return f"stripe:{self.index}/{self.count}"
        if self.kind == "checker":
            return f"checker:{self.size}:{self.shift}"
        return self.kind


def as_pattern(pattern) -> DisplayPattern:
    """A :class:`DisplayPattern` from a spec string (``"stripe:3/30"``), a message with ``kind``,
    ``index``, ``count``, ``size``, ``shift`` (``polarstripe.msgs.Pattern``) or the model's pattern (``kind``,
    ``k``, ``n``).

    :raises DriverValueError: the spec or the fields describe no valid pattern.
    """
    if isinstance(pattern, DisplayPattern):
        return pattern
    if isinstance(pattern, str):
        spec = pattern.strip().lower()
        if spec in ("flood", "off"):
            return DisplayPattern(spec)
        if m := re.fullmatch(r"stripe:(\d+)/(\d+)", spec):
            return DisplayPattern("stripe", index=int(m[1]), count=int(m[2]))
        if m := re.fullmatch(r"checker:(\d+):(\d+)", spec):
            return DisplayPattern("checker", size=int(m[1]), shift=int(m[2]))
        raise DriverValueError(f"pattern {pattern!r} is not flood, off, stripe:K/N or checker:SIZE:SHIFT")
    kind = getattr(pattern, "kind", None)
    if kind is None:
        raise DriverValueError(f"pattern {pattern!r} has no kind")
    kind = str(kind)
    if kind == "stripe":
        return DisplayPattern(
            kind,
            index=int(getattr(pattern, "index", getattr(pattern, "k", 0))),
            count=int(getattr(pattern, "count", getattr(pattern, "n", 0))),
        )
    if kind == "checker":
        return DisplayPattern(
            kind, size=int(getattr(pattern, "size", 0)), shift=int(getattr(pattern, "shift", 0))
        )
    return DisplayPattern(kind)  # flood, off; an unknown kind is refused here


def render_pattern(
    pattern, width: int, height: int, *, lit: int = 255, dark: int = 0, dtype=np.uint8
) -> np.ndarray:
    """The projector image of ``pattern``: an (height, width) array, ``lit`` where lit and ``dark`` elsewhere.

    Parameters
    ----------
    pattern : a spec string, :class:`DisplayPattern` or pattern message (see :func:`as_pattern`).
    width, height : projector size [pixels].
    lit, dark : pixel values (``dark`` > 0 models a projector black level).

    Returns
    -------
    ndarray, shape (height, width), dtype ``dtype``.
    """
    p = as_pattern(pattern)
    if width < 1 or height < 1:
        raise DriverValueError(f"projector size {width}x{height} must be at least 1x1")
    image = np.full((height, width), dark, dtype=dtype)
    if p.kind == "flood":
        image[:] = lit
    elif p.kind == "stripe":
        image[:, (p.index * width) // p.count : ((p.index + 1) * width) // p.count] = lit
    elif p.kind == "checker":
        col = np.arange(width)
        row = np.arange(height)
        even = ((np.floor_divide(col - p.shift, p.size)[None, :] + (row // p.size)[:, None]) % 2) == 0
        image[even] = lit
    return image


class Display(ABC):
    """A pattern output (projector, trigger box, laser line): ``show(pattern)``, ``blank()``, ``close()``.

    :param width, height: the projector's size [pixels] (for the image and for pattern semantics).
    """

    def __init__(self, width: int = 1280, height: int = 800, name: str = "display"):
        if width < 1 or height < 1:
            raise DriverValueError(f"{name}: size {width}x{height} must be at least 1x1")
        self.width, self.height, self.name = int(width), int(height), name
        self.current: DisplayPattern | None = None
        self._closed = False

    def show(self, pattern) -> float:
        """Light ``pattern``; return the time (``time.monotonic()``, s) it was shown.

        :raises DriverValueError: not a valid pattern.
        :raises DriverError: the output failed (the text names the device); :class:`DriverTimeout` if it did
            not answer in time.
        """
        if self._closed:
            raise DriverError(f"{self.name}: closed")
        p = as_pattern(pattern)
        stamp = self._show(p)
        self.current = p
        return stamp

    def blank(self) -> float:
        """Light nothing (``off``)."""
        return self.show(DisplayPattern("off"))

    def close(self) -> None:
        """Blank if possible and release the output; idempotent."""
        if self._closed:
            return
        try:
            if self.current is not None and self.current.kind != "off":
                self._show(DisplayPattern("off"))
        except DriverError:
            pass
        finally:
            self._closed = True
            self._close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @abstractmethod
    def _show(self, pattern: DisplayPattern) -> float: ...

    def _close(self) -> None:  # noqa: B027 - optional hook
        pass


class NullDisplay(Display):
    """Lights nothing; keeps the last ``history`` patterns shown (CI, the simulator, dry runs)."""

    def __init__(self, width: int = 1280, height: int = 800, history: int = 1000):
        super().__init__(width, height, name="null display")
        self.shown: deque[DisplayPattern] = deque(maxlen=history)

    def _show(self, pattern: DisplayPattern) -> float:
        self.shown.append(pattern)
        return time.monotonic()

    def image(self) -> np.ndarray:
        """The projector image the current pattern would give (all dark before the first show)."""
        return render_pattern(self.current or "off", self.width, self.height)
