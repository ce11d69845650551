"""What every backend has: its own typed ``Options``, and one way to be made from them.

python-can's ``Bus(interface=..., **kwargs)`` hands every argument it does not know to the backend; here a
node keeps the backend's name and a table of its options (``camera = "v4l2"``, ``camera_options = {device =
"/dev/video2", width = 1280}``) and hands the table on. The backend declares what it takes::

    class AcmeCamera(Camera):
        class Options(BackendOptions):
            serial: str                  # required: a launch without it is refused
            binning: int = 1             # defaults are the constructor's

``Options`` is checked with the node params' machinery (runtime/params.py: types coerced, unknown keys
refused with one line) when the launch file is read, before anything starts; :meth:`Backend.from_options`
then makes the backend: by default ``cls(**options, **common)``, where ``common`` are the settings the node
owns for every backend of the role (a stage's software limits). A backend that needs the node itself (the
simulator's camera calls a service) overrides ``from_options`` and uses the :class:`BackendContext`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from polarstripe.runtime.params import ParamSet


class BackendOptions(ParamSet):
    """A backend's own settings (none unless the backend declares them); see the module docstring."""


@dataclass(frozen=True)
class BackendContext:
    """What the node opening a backend lends it.

    :param service: ``service(name, request_type, reply_type) -> call``: a function that calls the node's
        service ``name`` (relative to its namespace) and returns the reply, raising ``TimeoutError`` when no
        answer comes within the node's timeout.
    """

    service: Callable[[str, type, type], Callable[[Any], Any]] | None = None


class Backend(ABC):
    """The base of every role's ABC (camera, display, stage): the declared ``Options``, the factory, and the
    context manager around the role's idempotent ``close``."""

    Options: ClassVar[type[BackendOptions]] = BackendOptions

    @classmethod
    def from_options(cls, options: BackendOptions, context: BackendContext | None = None, **common):
        """Make the backend from its checked ``options`` and the node's ``common`` settings of the role."""
        return cls(**options.as_dict(), **common)

    @abstractmethod
    def close(self) -> None:
        """Release the device; idempotent."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
