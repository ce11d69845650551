"""The pattern grammar: what the projector lights, as text and as a value, in one place.

Text forms (the tag a frame carries, the spec a user types):

- ``flood``: every pattern pixel lit; ``off``: nothing lit;
- ``stripe:K/N``: stripe K of N (0 ≤ K < N), columns floor(K·W/N) … floor((K+1)·W/N) − 1 of a W-wide pattern;
- ``checker:SIZE:SHIFT``: SIZE×SIZE squares lit where floor((col − SHIFT)/SIZE) + floor(row/SIZE) is even
  (SHIFT in pattern pixels along the columns; SHIFT = SIZE is the complement of SHIFT = 0);
- ``gray:BIT:AXIS:INV``: bit BIT (0 = finest) of the Gray code g = j XOR (j >> 1) of each pattern pixel's
  column (AXIS = ``col``) or row (``row``) index j, lit where the bit is 1 (INV = 0) or 0 (INV = 1): the
  images of OpenCV's ``cv2.structured_light.GrayCodePattern`` (:func:`gray_code` lists them in the order its
  ``generate()`` returns them; the projector calibration, docs/depth.md "Calibration").

Room for more kinds is one entry in :data:`KINDS`, one branch in :func:`parse` and ``__str__``.
Which patterns a scan of an imaging method shows is ``Method.patterns`` (:mod:`polarstripe.msgs.methods`).
See docs/architecture.md, "Messages".
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from polarstripe.errors import PolarstripeError

KINDS = ("flood", "stripe", "checker", "off", "gray")

_STRIPE = re.compile(r"stripe:(\d+)/(\d+)")
_CHECKER = re.compile(r"checker:(\d+):(\d+)")
_GRAY = re.compile(r"gray:(\d+):(col|row):([01])")


class PatternError(PolarstripeError, ValueError):
    """A pattern spec or value that describes no pattern; the text names it and says what is allowed."""


@dataclass(frozen=True)
class PatternSpec:
    """A checked pattern: ``kind``; stripe ``index`` of ``count``; checker ``size`` and ``shift`` [px]; Gray
    code bit ``index`` of ``axis`` (``col``/``row``), ``inverse``."""

    kind: str
    index: int = 0
    count: int = 0
    size: int = 0
    shift: int = 0
    axis: str = ""
    inverse: bool = False

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise PatternError(f"pattern kind={self.kind!r} is not one of {', '.join(KINDS)}")
        if self.kind == "stripe" and not (self.count >= 1 and 0 <= self.index < self.count):
            raise PatternError(f"stripe pattern index={self.index} count={self.count}: "
                               "need 0 <= index < count")
        if self.kind == "checker" and not (self.size >= 1 and self.shift >= 0):
            raise PatternError(f"checker pattern size={self.size} shift={self.shift}: "
                               "need size >= 1, shift >= 0")
        if self.kind == "gray" and not (0 <= self.index < 31 and self.axis in ("col", "row")):
            raise PatternError(f"gray pattern bit={self.index} axis={self.axis!r}: need 0 <= bit < 31, "
                               "axis col or row")

    def __str__(self) -> str:
        if self.kind == "stripe":
            return f"stripe:{self.index}/{self.count}"
        if self.kind == "checker":
            return f"checker:{self.size}:{self.shift}"
        if self.kind == "gray":
            return f"gray:{self.index}:{self.axis}:{int(self.inverse)}"
        return self.kind


def parse(pattern) -> PatternSpec:
    """A :class:`PatternSpec` from a spec string (``"stripe:3/30"``), a :class:`PatternSpec`, or any object
    with ``kind``, ``index``, ``count``, ``size``, ``shift`` (the ``emitter/pattern`` message).

    :raises PatternError: the text or the fields describe no pattern.
    """
    if isinstance(pattern, PatternSpec):
        return pattern
    if isinstance(pattern, str):
        spec = pattern.strip().lower()
        if spec in ("flood", "off"):
            return PatternSpec(spec)
        if m := _STRIPE.fullmatch(spec):
            return PatternSpec("stripe", index=int(m[1]), count=int(m[2]))
        if m := _CHECKER.fullmatch(spec):
            return PatternSpec("checker", size=int(m[1]), shift=int(m[2]))
        if m := _GRAY.fullmatch(spec):
            return PatternSpec("gray", index=int(m[1]), axis=m[2], inverse=m[3] == "1")
        raise PatternError(f"pattern {pattern!r} is not flood, off, stripe:K/N, checker:SIZE:SHIFT or "
                           "gray:BIT:col|row:0|1")
    kind = getattr(pattern, "kind", None)
    if kind is None:
        raise PatternError(f"pattern {pattern!r} has no kind")
    fields = {name: int(getattr(pattern, name, 0)) for name in ("index", "count", "size", "shift")}
    return PatternSpec(str(kind), **fields, axis=str(getattr(pattern, "axis", "")),
                       inverse=bool(getattr(pattern, "inverse", False)))


def stripes(count: int) -> Iterator[PatternSpec]:
    """The stripes 0 … count − 1 of a scan of ``count`` stripes, in order."""
    return (PatternSpec("stripe", index=k, count=count) for k in range(count))


def checker_pair(size: int) -> tuple[PatternSpec, PatternSpec]:
    """A checker and its complement (shift 0 and shift = size): the two frames of HF separation."""
    return PatternSpec("checker", size=size, shift=0), PatternSpec("checker", size=size, shift=size)


def stripe_columns(pattern: PatternSpec, width: int) -> tuple[int, int]:
    """Lit column edges [c0, c1) of a stripe (c1 exclusive) on a pattern ``width`` pixels wide."""
    return (pattern.index * width) // pattern.count, ((pattern.index + 1) * width) // pattern.count


def following(tag: str) -> str | None:
    """The pattern a scan shows after ``tag`` (``stripe:K/N`` → ``stripe:K+1/N``, ``checker:S:0`` →
    ``checker:S:S``), or None when ``tag`` ends its scan (or is not a scan pattern)."""
    try:
        p = parse(tag)
    except PatternError:
        return None
    if p.kind == "stripe" and p.index + 1 < p.count:
        return str(PatternSpec("stripe", index=p.index + 1, count=p.count))
    if p.kind == "checker" and p.shift == 0:
        return str(checker_pair(p.size)[1])
    return None


def gray_bits(n: int) -> int:
    """Gray code bits of ``n`` pattern columns (or rows): ⌈log2 n⌉, as OpenCV's ``GrayCodePattern``."""
    return int(math.ceil(math.log2(n))) if n > 1 else 0


def gray_code(width: int, height: int) -> list[PatternSpec]:
    """The Gray code patterns of a ``width``×``height`` projector in the order of OpenCV's
    ``GrayCodePattern.create(width, height).generate()``: per column bit from the coarsest (⌈log2 W⌉ − 1) to
    0 the pattern and its inverse, then the rows alike."""
    out = []
    for axis, n in (("col", width), ("row", height)):
        for bit in range(gray_bits(n) - 1, -1, -1):
            out += [PatternSpec("gray", index=bit, axis=axis), PatternSpec("gray", index=bit, axis=axis,
                                                                           inverse=True)]
    return out


def gray_lit(pattern: PatternSpec, col, row) -> np.ndarray:
    """Where a ``gray`` pattern is lit at continuous pattern coordinates (col, row) (pixel j covers [j, j+1)):
    bit ``index`` of g = j XOR (j >> 1), j = ⌊col⌋ (or ⌊row⌋), is 1 (0 for the inverse)."""
    x = np.asarray(col if pattern.axis == "col" else row, float)
    with np.errstate(invalid="ignore"):
        j = np.floor(np.nan_to_num(x, nan=-1.0)).astype(np.int64)
    bit = ((j ^ (j >> 1)) >> pattern.index) & 1
    return (bit == 1) != pattern.inverse
