"""The pattern grammar: what the projector lights, as text and as a value, in one place.

Text forms (the tag a frame carries, the spec a user types):

- ``flood``: every pattern pixel lit; ``off``: nothing lit;
- ``stripe:K/N``: stripe K of N (0 ≤ K < N), columns floor(K·W/N) … floor((K+1)·W/N) − 1 of a W-wide pattern;
- ``stripe:I/N:xK``: K light sheets at once, evenly spaced: the stripes I, I + F, I + 2F, … (those < N) of N,
  F = ⌈N/K⌉ (0 ≤ I < F, 1 ≤ K ≤ N). A scan of N stripe positions is then F frames, I = 0 … F − 1, and every
  position is lit in exactly one frame (position n in frame n mod F); the sheets of one frame are F stripes
  (F·W/N columns) apart, so when K does not divide N some frames light fewer than K sheets. ``:x1`` is
  ``stripe:K/N`` (the tag is written without it);
- ``checker:SIZE:SHIFT``: SIZE×SIZE squares lit where floor((col − SHIFT)/SIZE) + floor(row/SIZE) is even
  (SHIFT in pattern pixels along the columns; SHIFT = SIZE is the complement of SHIFT = 0);
- ``gray:BIT:AXIS:INV``: bit BIT (0 = finest) of the Gray code g = j XOR (j >> 1) of each pattern pixel's
  column (AXIS = ``col``) or row (``row``) index j, lit where the bit is 1 (INV = 0) or 0 (INV = 1): the
  images of OpenCV's ``cv2.structured_light.GrayCodePattern`` (:func:`gray_code` lists them in the order its
  ``generate()`` returns them);
- ``gray:BIT:AXIS:INV:xorBASE``: that bit XOR bit BASE of the Gray code of the column index, the XOR codes
  of Gupta et al. (CVPR 2011) that keep every pattern fine enough for the light scattered in the medium to
  be alike under a pattern and its inverse (:func:`xor_code`; the projector calibration, docs/depth.md
  "Calibration").

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

_STRIPE = re.compile(r"stripe:(\d+)/(\d+)(?::x(\d+))?")
_CHECKER = re.compile(r"checker:(\d+):(\d+)")
_GRAY = re.compile(r"gray:(\d+):(col|row):([01])(?::xor(\d+))?")


class PatternError(PolarstripeError, ValueError):
    """A pattern spec or value that describes no pattern; the text names it and says what is allowed."""


@dataclass(frozen=True)
class PatternSpec:
    """A checked pattern: ``kind``; stripe ``index`` of ``count`` with ``sheets`` sheets at once (frame
    ``index`` of the scan's ⌈count/sheets⌉); checker ``size`` and ``shift`` [px]; Gray code bit ``index`` of
    ``axis`` (``col``/``row``), ``inverse``, XOR the column code's bit ``xor`` (−1: none)."""

    kind: str
    index: int = 0
    count: int = 0
    size: int = 0
    shift: int = 0
    axis: str = ""
    inverse: bool = False
    xor: int = -1
    sheets: int = 1

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise PatternError(f"pattern kind={self.kind!r} is not one of {', '.join(KINDS)}")
        if self.sheets != 1 and not (self.kind == "stripe" and 1 <= self.sheets <= max(self.count, 1)):
            raise PatternError(f"{self.kind} pattern sheets={self.sheets}: only a stripe pattern has sheets, "
                               "1 <= sheets <= count")
        if self.kind == "stripe" and not (self.count >= 1 and 0 <= self.index < frames_of(self.count,
                                                                                        self.sheets)):
            raise PatternError(f"stripe pattern index={self.index} count={self.count} sheets={self.sheets}: "
                               "need 0 <= index < ceil(count/sheets)")
        if self.kind == "checker" and not (self.size >= 1 and self.shift >= 0):
            raise PatternError(f"checker pattern size={self.size} shift={self.shift}: "
                               "need size >= 1, shift >= 0")
        if self.kind == "gray" and not (0 <= self.index < 31 and self.axis in ("col", "row")):
            raise PatternError(f"gray pattern bit={self.index} axis={self.axis!r}: need 0 <= bit < 31, "
                               "axis col or row")
        if self.xor != -1 and not (self.kind == "gray" and 0 <= self.xor < 31 and
                                   (self.axis, self.index) != ("col", self.xor)):
            raise PatternError(f"{self.kind} pattern xor={self.xor}: only a gray pattern takes an XOR base, "
                               "a column bit 0..30 other than its own")

    def __str__(self) -> str:
        if self.kind == "stripe":
            return f"stripe:{self.index}/{self.count}" + (f":x{self.sheets}" if self.sheets > 1 else "")
        if self.kind == "checker":
            return f"checker:{self.size}:{self.shift}"
        if self.kind == "gray":
            xor = f":xor{self.xor}" if self.xor >= 0 else ""
            return f"gray:{self.index}:{self.axis}:{int(self.inverse)}{xor}"
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
            return PatternSpec("stripe", index=int(m[1]), count=int(m[2]), sheets=int(m[3] or 1))
        if m := _CHECKER.fullmatch(spec):
            return PatternSpec("checker", size=int(m[1]), shift=int(m[2]))
        if m := _GRAY.fullmatch(spec):
            return PatternSpec("gray", index=int(m[1]), axis=m[2], inverse=m[3] == "1",
                               xor=-1 if m[4] is None else int(m[4]))
        raise PatternError(f"pattern {pattern!r} is not flood, off, stripe:K/N[:xSHEETS], checker:SIZE:SHIFT "
                           "or "
                           "gray:BIT:col|row:0|1[:xorBASE]")
    kind = getattr(pattern, "kind", None)
    if kind is None:
        raise PatternError(f"pattern {pattern!r} has no kind")
    fields = {name: int(getattr(pattern, name, 0)) for name in ("index", "count", "size", "shift")}
    return PatternSpec(str(kind), **fields, axis=str(getattr(pattern, "axis", "")),
                       inverse=bool(getattr(pattern, "inverse", False)), xor=int(getattr(pattern, "xor", -1)),
                       sheets=int(getattr(pattern, "sheets", 1)))


def frames_of(count: int, sheets: int = 1) -> int:
    """Frames of a scan of ``count`` stripe positions lit ``sheets`` at a time: ⌈count/sheets⌉."""
    return -(-int(count) // max(int(sheets), 1))


def stripes(count: int, sheets: int = 1) -> Iterator[PatternSpec]:
    """The frames of a scan of ``count`` stripes with ``sheets`` sheets each (0 … ⌈count/sheets⌉ − 1), in
    order."""
    return (PatternSpec("stripe", index=k, count=count, sheets=sheets)
            for k in range(frames_of(count, sheets)))


def sheet_positions(pattern: PatternSpec) -> tuple[int, ...]:
    """The stripe positions a stripe pattern lights: index + j·F (j = 0 … sheets − 1, those < count),
    F = ⌈count/sheets⌉."""
    step = frames_of(pattern.count, pattern.sheets)
    return tuple(range(pattern.index, pattern.count, step))[:pattern.sheets]


def sheet_columns(pattern: PatternSpec, width: int) -> list[tuple[int, int]]:
    """Lit column intervals [c0, c1) of a flood (one) or stripe pattern (one per sheet, left to right) on a
    pattern ``width`` pixels wide."""
    if pattern.kind == "flood":
        return [(0, int(width))]
    return [((k * width) // pattern.count, ((k + 1) * width) // pattern.count)
            for k in sheet_positions(pattern)]


def single_sheets(pattern: PatternSpec) -> list[PatternSpec]:
    """The one-sheet stripe patterns whose light adds up to ``pattern`` (itself when it has one sheet)."""
    if pattern.kind != "stripe" or pattern.sheets == 1:
        return [pattern]
    return [PatternSpec("stripe", index=k, count=pattern.count) for k in sheet_positions(pattern)]


def checker_pair(size: int) -> tuple[PatternSpec, PatternSpec]:
    """A checker and its complement (shift 0 and shift = size): the two frames of HF separation."""
    return PatternSpec("checker", size=size, shift=0), PatternSpec("checker", size=size, shift=size)


def stripe_columns(pattern: PatternSpec, width: int) -> tuple[int, int]:
    """Lit column edges [c0, c1) of a one-sheet stripe (c1 exclusive) on a pattern ``width`` pixels wide
    (:func:`sheet_columns` for several sheets; a several-sheet pattern here is a :class:`PatternError`)."""
    if pattern.sheets != 1:
        raise PatternError(f"{pattern} has {pattern.sheets} sheets: one column interval per sheet "
                           "(sheet_columns)")
    return (pattern.index * width) // pattern.count, ((pattern.index + 1) * width) // pattern.count


def following(tag: str) -> str | None:
    """The pattern a scan shows after ``tag`` (``stripe:K/N`` → ``stripe:K+1/N``, ``stripe:I/N:xS`` →
    ``stripe:I+1/N:xS``, ``checker:S:0`` → ``checker:S:S``), or None when ``tag`` ends its scan (or is not a
    scan pattern)."""
    try:
        p = parse(tag)
    except PatternError:
        return None
    if p.kind == "stripe" and p.index + 1 < frames_of(p.count, p.sheets):
        return str(PatternSpec("stripe", index=p.index + 1, count=p.count, sheets=p.sheets))
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


def xor_code(width: int, height: int, base: int) -> list[PatternSpec]:
    """The XOR code of a ``width``×``height`` projector with base bit ``base`` (Gupta, Agrawal,
    Veeraraghavan & Narasimhan, CVPR 2011): the order of :func:`gray_code`, every column bit coarser than
    ``base`` and every row bit XOR the column code's bit ``base``; the finer column bits and the base itself
    as they are. Each pattern then changes at least every 2^(base+1) columns, and along every row (where a
    camera ray crosses the projector's columns: a horizontal baseline) alike, so light scattered in the medium
    over many columns is alike under a pattern and its inverse; the decoder XORs the base back
    (imaging/structured_light.py)."""
    if not 0 <= base < gray_bits(width):
        raise PatternError(f"XOR base bit {base}: a {width}-column projector has column bits 0.."
                           f"{gray_bits(width) - 1}")
    out = []
    for axis, n in (("col", width), ("row", height)):
        for bit in range(gray_bits(n) - 1, -1, -1):
            xor = base if axis == "row" or bit > base else -1
            out += [PatternSpec("gray", index=bit, axis=axis, xor=xor),
                    PatternSpec("gray", index=bit, axis=axis, inverse=True, xor=xor)]
    return out


def _gray_bit(x, bit: int) -> np.ndarray:
    """Bit ``bit`` of the Gray code j XOR (j >> 1) of j = ⌊x⌋ (NaN: −1)."""
    with np.errstate(invalid="ignore"):
        j = np.floor(np.nan_to_num(np.asarray(x, float), nan=-1.0)).astype(np.int64)
    return ((j ^ (j >> 1)) >> bit) & 1


def gray_lit(pattern: PatternSpec, col, row) -> np.ndarray:
    """Where a ``gray`` pattern is lit at continuous pattern coordinates (col, row) (pixel j covers [j, j+1)):
    bit ``index`` of g = j XOR (j >> 1), j = ⌊col⌋ (or ⌊row⌋), XOR (with ``xor`` ≥ 0) bit ``xor`` of the
    column's g, is 1 (0 for the inverse)."""
    bit = _gray_bit(col if pattern.axis == "col" else row, pattern.index)
    if pattern.xor >= 0:
        bit = bit ^ _gray_bit(col, pattern.xor)
    return (bit == 1) != pattern.inverse
