"""JSON Schema of each message type, describing its self-contained MessagePack form (:func:`codec.pack`).

MCAP channels with ``message_encoding = "msgpack"`` carry this schema (``schema encoding = "jsonschema"``).
"""

from __future__ import annotations

from polarstripe.msgs.base import Message


def json_schema(cls: type[Message]) -> dict:
    """The JSON Schema (draft 2020-12) of the packed form of message type ``cls``.

    Arrays are objects ``{dtype, shape, data}`` where ``data`` is the raw C-order bytes (a MessagePack
    ``bin``; ``contentEncoding: base64`` when shown as JSON).
    """
    if not (isinstance(cls, type) and issubclass(cls, Message) and cls.TYPE):
        raise TypeError(f"{cls!r} is not a declared message type")
    props = {name: kind.schema() for name, kind in cls.FIELDS}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"polarstripe/{cls.TYPE}",
        "description": (cls.__doc__ or "").strip().split("\n\n")[0],
        "type": "object",
        "properties": {
            "type": {"const": cls.TYPE},
            "version": {"const": cls.VERSION},
            "stamp_ns": {"type": "integer"},
            "seq": {"type": "integer"},
            "frame_id": {"type": "string"},
            "fields": {
                "type": "object",
                "properties": props,
                "required": list(props),
                "additionalProperties": False,
            },
        },
        "required": ["type", "version", "stamp_ns", "seq", "frame_id", "fields"],
        "additionalProperties": False,
    }
