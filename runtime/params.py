"""Typed parameters: a frozen dataclass per node (:class:`NodeParams`) or per hardware backend (its
``Options``, nodes/drivers/backend.py), filled from defaults, the launch file and the command line.

::

    class Params(NodeParams):
        rate_hz: float = 10.0
        text: str = "hello"

        def validate(self):
            if self.rate_hz <= 0:
                raise ValueError("must be > 0")   # reported as: node 'talker': param 'rate_hz' ...

Values may arrive as strings (``--param rate_hz=5``, ``${arg}`` substitution in a launch file); they are
coerced to the declared type. Supported types: bool, int, float, str, ``Literal[...]`` of str, ``X | None``,
``list[X]`` of those scalars, and ``dict[str, Any]`` (a TOML table, or JSON text on the command line: a
backend's options, checked by the backend's own ``Options``). A field without a default must be given.
"""

from __future__ import annotations

import dataclasses
import json
import os
import types
import typing
from typing import Any, Literal

from polarstripe.errors import PolarstripeError


class ParamError(PolarstripeError, ValueError):
    """A parameter that is unknown or has a bad value; the text names the node, the key and the value."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class ParamSet:
    """Typed settings; subclasses are made frozen keyword-only dataclasses automatically, and a list or dict
    default is copied for each instance."""

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        for key, value in list(vars(cls).items()):
            if key in cls.__dict__.get("__annotations__", {}) and isinstance(value, list | dict):
                setattr(cls, key, dataclasses.field(default_factory=lambda v=value: type(v)(v)))
        dataclasses.dataclass(frozen=True, kw_only=True)(cls)

    def validate(self) -> None:  # noqa: B027 - optional hook
        """Override to check values together; raise ``ValueError`` naming the problem."""

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class NodeParams(ParamSet):
    """Parameters every node has."""

    heartbeat_s: float = 0.25  # heartbeat period [s]; a peer is lost after 4 missed (runtime/liveness.py)
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"
    max_message_bytes: int = 128 * 2**20  # larger received messages are dropped as bad [bytes]
    pub_hwm: int = 100  # messages queued per subscriber before the publisher drops (seen as gaps)

    def validate(self) -> None:
        if self.heartbeat_s < 0:
            raise ValueError(f"heartbeat_s must be >= 0, got {self.heartbeat_s}")
        if self.pub_hwm < 1:
            raise ValueError(f"pub_hwm must be >= 1, got {self.pub_hwm}")
        if self.max_message_bytes <= 0:
            raise ValueError(f"max_message_bytes must be > 0, got {self.max_message_bytes}")


_TRUE, _FALSE = {"true", "yes", "on", "1"}, {"false", "no", "off", "0"}


def _coerce(tp: Any, value: Any) -> Any:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType) and type(None) in args:
        if value is None or (isinstance(value, str) and value.lower() in ("none", "null", "")):
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(inner[0], value)
    if origin is Literal:
        if value in args:
            return value
        raise ValueError(f"expected one of {', '.join(map(str, args))}")
    if origin is list:
        if isinstance(value, str):
            try:
                value = (
                    json.loads(value) if value.strip().startswith("[") else [v for v in value.split(",") if v]
                )
            except json.JSONDecodeError as exc:
                raise ValueError(f"not a list ({exc})") from None
        if not isinstance(value, list | tuple):
            raise ValueError("expected a list")
        return [_coerce(args[0], v) for v in value]
    if origin is dict or tp is dict:
        if isinstance(value, str):
            try:
                value = json.loads(value) if value.strip() else {}
            except json.JSONDecodeError as exc:
                raise ValueError(f"not a table ({exc})") from None
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            raise ValueError("expected a table {name: value}")
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in _TRUE | _FALSE:
            return value.lower() in _TRUE
        raise ValueError("expected a bool (true/false)")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, str):
            return int(value.strip())
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ValueError("expected an int")
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            return float(value.strip())
        raise ValueError("expected a float")
    if tp is str:
        if isinstance(value, str):
            return value
        if isinstance(value, int | float | bool):
            return str(value)
        raise ValueError("expected a string")
    raise ValueError(f"unsupported parameter type {tp!r}")


def build_params(cls: type[ParamSet], values: dict[str, Any], *, node: str = "?", what: str = "",
                 noun: str = "param") -> ParamSet:
    """Make ``cls`` from ``values`` (strings are coerced), then run ``validate``. Error texts start with
    ``what`` (default: ``node 'NAME'``) and call a key a ``noun``.

    Raises :class:`ParamError` for an unknown or missing key, a value of the wrong type, or a failed
    validation.
    """
    what = what or f"node {node!r}"
    hints = typing.get_type_hints(cls)
    fields = dataclasses.fields(cls)
    names = {f.name for f in fields}
    kwargs = {}
    for key, value in values.items():
        if key not in names:
            raise ParamError(f"{what}: unknown {noun} {key!r} (known: {', '.join(sorted(names)) or 'none'})")
        try:
            kwargs[key] = _coerce(hints[key], value)
        except ValueError as exc:
            raise ParamError(f"{what}: {noun} {key!r}: bad value {value!r}: {exc}") from None
    missing = [f.name for f in fields if f.name not in kwargs and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ParamError(f"{what}: missing {noun} {', '.join(map(repr, missing))}")
    params = cls(**kwargs)
    try:
        params.validate()
    except ValueError as exc:
        raise ParamError(f"{what}: {noun}s: {exc}") from None
    return params


DEFAULT_MAX_PIXELS = 16_000_000  # e.g. 4096x3904; $POLARSTRIPE_MAX_PIXELS overrides


def max_pixels() -> int:
    """The largest frame (width × height) a node accepts: ``$POLARSTRIPE_MAX_PIXELS`` or 16 Mpx. Beyond it a
    frame is refused as a param error, before anything allocates (a 4000×6000 uint16 stream grows a
    compositor by GBs; 100000×100000 cannot be allocated at all)."""
    value = os.environ.get("POLARSTRIPE_MAX_PIXELS", "")
    try:
        return int(value) if value else DEFAULT_MAX_PIXELS
    except ValueError:
        raise ParamError(f"$POLARSTRIPE_MAX_PIXELS: expected a number of pixels, got {value!r}") from None


def check_frame_size(width: int, height: int, *, what: str = "frame size") -> None:
    """Raise ``ValueError`` (one line) when ``width``×``height`` is not positive or exceeds
    :func:`max_pixels`."""
    if width < 1 or height < 1:
        raise ValueError(f"{what} {width}x{height}: width and height must be >= 1")
    limit = max_pixels()
    if width * height > limit:
        raise ValueError(f"{what} {width}x{height} is {width * height / 1e6:.3g} Mpx, beyond the limit of "
                         f"{limit / 1e6:.3g} Mpx (set $POLARSTRIPE_MAX_PIXELS to allow more)")


def parse_assignments(items: list[str], *, what: str = "param") -> dict[str, str]:
    """``["k=v", …]`` → ``{"k": "v"}``; raises :class:`ParamError` for an item without ``=``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ParamError(f"{what} {item!r}: expected KEY=VALUE")
        out[key.strip()] = value
    return out
