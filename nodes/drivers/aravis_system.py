"""Aravis (GenICam: GigE Vision and USB3 Vision cameras) through GObject introspection: the library, the
cameras it can see, and its GigE Vision simulator.

Aravis 0.8 comes from the distribution (Debian/Ubuntu ``gir1.2-aravis-0.8``), its Python binding from
PyGObject (``pip install 'polarstripe[aravis]'``; docs/hardware.md "GenICam cameras"). Importing this module
without them is one :class:`ImportError` naming what to install, which the backend registry turns into
:class:`~polarstripe.nodes.drivers.errors.BackendUnavailable`.

* :func:`discover` lists every camera Aravis finds: a GigE Vision discovery broadcast on every network
  interface, and the USB3 Vision devices on the USB bus.
* :func:`probe` asks one address and nothing else (no broadcast): a camera on a routed network, or the
  simulator on 127.0.0.1.
* :class:`FakeGvCamera` runs Aravis's GigE Vision simulator (``ArvGvFakeCamera``) in this process on a
  loopback address: a real GVCP/GVSP peer on UDP port 3956 with a 512x512 diagonal ramp, software trigger,
  ``ExposureTimeAbs`` and ``GainRaw`` (not the SFNC ``ExposureTime``/``Gain``: the fallbacks get used), Mono8
  and Mono16 (no Mono12), and a ratio of stream packets it drops on purpose. It never resends a packet, so a
  dropped packet is an incomplete frame.
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass

from polarstripe.nodes.drivers.errors import DriverError, DriverValueError

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis, GLib
except ImportError as _exc:
    raise ImportError(f"{_exc} (PyGObject: pip install 'polarstripe[aravis]'; docs/hardware.md)") from None
except ValueError as _exc:  # PyGObject is there, Aravis's typelib is not
    raise ImportError(f"Aravis 0.8 is not installed for GObject introspection ({_exc}): "
                      "apt-get install gir1.2-aravis-0.8 (docs/hardware.md)") from None

GVCP_PORT = 3956  # GigE Vision control protocol (UDP)


@dataclass(frozen=True)
class CameraInfo:
    """One camera as Aravis names it: ``device`` is what the backend's ``device`` option takes (an address
    for GigE Vision, the device id for USB3 Vision)."""

    device: str
    vendor: str
    model: str
    serial: str
    protocol: str  # GigEVision | USB3Vision


def error_text(exc: BaseException) -> str:
    """Aravis's GError as one line (its message, without GLib's domain prefix)."""
    return getattr(exc, "message", None) or str(exc)


def discover() -> list[CameraInfo]:
    """Every camera Aravis finds: GigE Vision discovery broadcast on every interface, USB3 Vision devices."""
    Aravis.update_device_list()
    out = []
    for i in range(Aravis.get_n_devices()):
        protocol = Aravis.get_device_protocol(i) or ""
        device = Aravis.get_device_address(i) if protocol == "GigEVision" else Aravis.get_device_id(i)
        out.append(CameraInfo(device or Aravis.get_device_id(i), Aravis.get_device_vendor(i) or "",
                              Aravis.get_device_model(i) or "", Aravis.get_device_serial_nbr(i) or "",
                              protocol))
    return out


def open_device(device: str):
    """The ``ArvDevice`` at ``device`` (an address: asked directly, no broadcast; an id: found by Aravis's
    discovery).

    :raises DriverError: nothing answers."""
    try:
        return Aravis.open_device(device)
    except GLib.Error as exc:
        raise DriverError(f"Aravis camera {device}: {error_text(exc)} (camera on, address right, "
                          "same subnet? 'polarstripe camera list')") from None


def probe(address: str) -> CameraInfo:
    """The camera at ``address`` (one GigE Vision camera asked directly; no broadcast).

    :raises DriverError: nothing answers there."""
    dev = open_device(address)
    read = lambda *names: next((dev.get_string_feature_value(n) for n in names  # noqa: E731
                                if dev.is_feature_available(n)), "")
    return CameraInfo(address, read("DeviceVendorName"), read("DeviceModelName"),
                      read("DeviceSerialNumber", "DeviceID"), "GigEVision")


def check_port_free(address: str) -> None:
    """Raise :class:`DriverError` when UDP ``address``:3956 is taken (the simulator would start deaf: Aravis
    does not report a failed bind)."""
    probe_socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe_socket.bind((address, GVCP_PORT))
    except OSError as exc:
        why = "in use (another fake camera?)" if exc.errno == errno.EADDRINUSE else exc.strerror or str(exc)
        raise DriverError(f"GigE Vision fake camera: cannot listen on {address}:{GVCP_PORT}: {why}") from None
    finally:
        probe_socket.close()


class FakeGvCamera:
    """Aravis's GigE Vision simulator on ``address`` (a loopback address of this host), serial ``serial``.

    ``lost_ratio`` is the fraction of stream packets (leader, payload, trailer) it drops, settable while it
    runs. Use as a context manager; :meth:`close` stops it.
    """

    def __init__(self, address: str = "127.0.0.1", serial: str = "GV01", lost_ratio: float = 0.0):
        if not address.startswith("127."):
            raise DriverError(f"GigE Vision fake camera: {address!r} is no loopback address (127.x.x.x)")
        check_port_free(address)
        self.address, self.serial = address, serial
        self._fake = Aravis.GvFakeCamera.new(address, serial)
        if not self._fake.is_running():
            raise DriverError(f"GigE Vision fake camera: Aravis could not start it on {address}")
        self.lost_ratio = lost_ratio

    @property
    def lost_ratio(self) -> float:
        """Fraction of stream packets dropped, 0 to 1."""
        return self._fake.get_property("gvsp-lost-ratio") if self._fake is not None else 0.0

    @lost_ratio.setter
    def lost_ratio(self, value: float) -> None:
        if not 0.0 <= value <= 1.0:
            raise DriverValueError(f"GigE Vision fake camera: lost ratio {value} must be between 0 and 1")
        self._fake.set_property("gvsp-lost-ratio", float(value))

    def close(self) -> None:
        """Stop the simulator (its thread and sockets); idempotent."""
        self._fake = None  # the last reference: Aravis's finalize stops the thread and closes the sockets

    def __enter__(self) -> FakeGvCamera:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
