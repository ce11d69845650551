"""The root of polarstripe's error tree.

Each domain subclasses :class:`PolarstripeError` once (``MessageError`` in msgs, ``SceneError`` in sim,
``DriverError`` in drivers, ``LaunchError`` in the launcher, ...). The command line catches this root and
prints its text as one line, so the text must name what was wrong (the key, topic, field or value).
Errors about bad argument values also subclass :class:`ValueError`, timeouts :class:`TimeoutError`.
"""


class PolarstripeError(Exception):
    """A user-facing error: its text is shown as one line, without a traceback."""
