"""The imaging methods of the rig, in one table: each knows its pattern family and whether it is polarized.

The ``emitter/start_scan`` request, the ``emitter/scan`` event and the compositor's results name a method by
its value (``"polarized_stripes"``). See docs/architecture.md, "Messages".
"""

from __future__ import annotations

import enum

from polarstripe.msgs.patterns import PatternError, PatternSpec, checker_pair, parse, stripes


class Method(enum.StrEnum):
    """An imaging method; ``Method("stripes")`` parses its name (``ValueError`` for an unknown one)."""

    FLOOD = "flood"
    POLARIZED_FLOOD = "polarized_flood"
    STRIPES = "stripes"
    POLARIZED_STRIPES = "polarized_stripes"
    HF_SEPARATION = "hf_separation"

    @property
    def family(self) -> str:
        """The pattern kind its frames show: ``flood``, ``stripe`` or ``checker``."""
        return _FAMILY[self]

    @property
    def polarized(self) -> bool:
        """True when it takes every pattern at two analyzer angles (E_b and E_w)."""
        return self in (Method.POLARIZED_FLOOD, Method.POLARIZED_STRIPES)

    @property
    def striped(self) -> bool:
        """True when its frames are stripes: a scan of it delineates the stripes, so it yields a depth map
        (docs/depth.md) and the medium fit reads it (docs/planning.md §6)."""
        return self.family == "stripe"

    def patterns(self, n_stripes: int, checker_size: int, sheets: int = 1) -> tuple[PatternSpec, ...]:
        """The patterns of one pass at one analyzer angle, in order (a stripe scan: ⌈n_stripes/sheets⌉
        frames of ``sheets`` sheets each, msgs/patterns.py)."""
        if self.family == "flood":
            return (PatternSpec("flood"),)
        if self.family == "stripe":
            return tuple(stripes(n_stripes, sheets))
        return checker_pair(checker_size)

    def accepts(self, tag: str) -> bool:
        """True when a frame tagged ``tag`` can belong to a scan of this method (its family's kind)."""
        try:
            return parse(tag).kind == self.family
        except PatternError:
            return False

    @classmethod
    def lookup(cls, name: str) -> Method | None:
        """The method called ``name``, None for any other text (a name read off the wire)."""
        return cls._value2member_map_.get(name)

    @classmethod
    def parse(cls, name: str) -> Method:
        """The method called ``name``; ``ValueError`` naming the choices otherwise."""
        try:
            return cls(name)
        except ValueError:
            raise ValueError(f"method {name!r} is not one of {', '.join(m.value for m in cls)}") from None


_FAMILY = {Method.FLOOD: "flood", Method.POLARIZED_FLOOD: "flood", Method.STRIPES: "stripe",
           Method.POLARIZED_STRIPES: "stripe", Method.HF_SEPARATION: "checker"}

#: every method's name, in the order the sim demo runs them
METHOD_NAMES: tuple[str, ...] = tuple(m.value for m in Method)
