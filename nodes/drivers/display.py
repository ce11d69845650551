"""The display / trigger role: what the projector (or laser line) lights now, and the projector image.

Pattern conventions are the rig's (:mod:`polarstripe.msgs.patterns`), for a projector ``W``
pixels wide and ``H`` high, row 0 at the top:

* ``flood`` lights every pixel, ``off`` none; * ``stripe:K/N`` lights columns ``floor(K·W/N)`` …
``floor((K+1)·W/N) − 1`` (0 ≤ K < N), ``stripe:I/N:xS`` those of each of its S sheets (msgs/patterns.py);
* ``checker:SIZE:SHIFT`` lights the pixels where ``floor((col − SHIFT)/SIZE) + floor(row/SIZE)`` is even;
* ``gray:BIT:col|row:INV`` lights the pixels whose column (row) index j has bit BIT of its Gray code
j XOR (j >> 1) at 1 (INV = 0) or 0 (INV = 1), the images of OpenCV's ``GrayCodePattern``; with ``:xorBASE``
that bit XOR bit BASE of the column's Gray code (the XOR code of the projector calibration, docs/depth.md
"Calibration").

:class:`Display` owns the shared behaviour (pattern parsing and validation, the current pattern, the context
manager, an idempotent :meth:`~Display.close`); a backend implements ``_show`` and declares its ``Options``
(nodes/drivers/backend.py). :class:`NullDisplay` (CI, the simulator) lights nothing and remembers what it was
asked to show.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections import deque

import numpy as np
from polarstripe.msgs.patterns import PatternError, PatternSpec, gray_lit, parse, sheet_columns
from polarstripe.nodes.drivers.backend import Backend, BackendOptions
from polarstripe.nodes.drivers.errors import DriverError, DriverValueError


def as_pattern(pattern) -> PatternSpec:
    """The checked pattern of a spec string (``"stripe:3/30"``), a pattern message or a
    :class:`~polarstripe.msgs.patterns.PatternSpec` (:func:`polarstripe.msgs.patterns.parse`).

    :raises DriverValueError: the spec or the fields describe no valid pattern.
    """
    try:
        return parse(pattern)
    except PatternError as exc:
        raise DriverValueError(str(exc)) from None


def render_pattern(
    pattern, width: int, height: int, *, lit: int = 255, dark: int = 0, dtype=np.uint8
) -> np.ndarray:
    """The projector image of ``pattern``: an (height, width) array, ``lit`` where lit and ``dark`` elsewhere.

    Parameters
    ----------
    pattern : a spec string, ``PatternSpec`` or pattern message (see :func:`as_pattern`).
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
        for c0, c1 in sheet_columns(p, width):     # every sheet of it
            image[:, c0:c1] = lit
    elif p.kind == "checker":
        col = np.arange(width)
        row = np.arange(height)
        even = ((np.floor_divide(col - p.shift, p.size)[None, :] + (row // p.size)[:, None]) % 2) == 0
        image[even] = lit
    elif p.kind == "gray":
        lit_where = gray_lit(p, np.arange(width)[None, :] + 0.5, np.arange(height)[:, None] + 0.5)
        image[np.broadcast_to(lit_where, image.shape)] = lit
    return image


class Display(Backend, ABC):
    """A pattern output (projector, trigger box, laser line): ``show(pattern)``, ``blank()``, ``close()``.

    :param width, height: the projector's size [pixels] (for the image and for pattern semantics).
    """

    def __init__(self, width: int = 1280, height: int = 800, name: str = "display"):
        if width < 1 or height < 1:
            raise DriverValueError(f"{name}: size {width}x{height} must be at least 1x1")
        self.width, self.height, self.name = int(width), int(height), name
        self.current: PatternSpec | None = None
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
        return self.show(PatternSpec("off"))

    def close(self) -> None:
        """Blank if possible and release the output; idempotent."""
        if self._closed:
            return
        try:
            if self.current is not None and self.current.kind != "off":
                self._show(PatternSpec("off"))
        except DriverError:
            pass
        finally:
            self._closed = True
            self._close()

    @abstractmethod
    def _show(self, pattern: PatternSpec) -> float: ...

    def _close(self) -> None:  # noqa: B027 - optional hook
        pass


class NullDisplay(Display):
    """Lights nothing; keeps the last ``history`` patterns shown (CI, the simulator, dry runs)."""

    class Options(BackendOptions):
        width: int = 1280  # the projector's size [px] (pattern semantics)
        height: int = 800
        history: int = 1000  # patterns remembered

    def __init__(self, width: int = 1280, height: int = 800, history: int = 1000):
        super().__init__(width, height, name="null display")
        self.shown: deque[PatternSpec] = deque(maxlen=history)

    def _show(self, pattern: PatternSpec) -> float:
        self.shown.append(pattern)
        return time.monotonic()

    def image(self) -> np.ndarray:
        """The projector image the current pattern would give (all dark before the first show)."""
        return render_pattern(self.current or "off", self.width, self.height)
