"""A rotation stage on a CANopen CiA 402 drive in profile position mode, through ``canopen`` on python-can.

Setup (SDO): check the device type (0x1000, profile 402) and the supported drive modes (0x6502: profile
position, and homing for :meth:`home`), then write the configuration: the producer heartbeat time (0x1017),
the mode of operation (0x6060 = 1, profile position), the profile velocity (0x6081) and the drive's own
software position limit (0x607D) from this stage's limits; then NMT start and walk the state machine to
OPERATION ENABLED. Runtime (PDO): RPDO1 carries controlword + target position, TPDO1 statusword + position
actual value + mode display. A move writes the target, raises controlword bit 4 (new set-point, bit 5 change
immediately), waits for the set-point acknowledge (statusword bit 12), lowers bit 4; "settled" is target
reached (bit 10) after that acknowledge, with the position inside the tolerance.

Faults become text in :attr:`fault`, never a wrong angle: an EMCY, the FAULT state, internal limit active (bit
11), a lost heartbeat (consumer heartbeat timeout), a drive that left NMT OPERATIONAL or rebooted (boot-up, or
another master's NMT reset), stale TPDOs, CAN error frames (bus-off, no ACK, TX timeout, bus error), a receive
error and a failed send (see :mod:`.cia402_watch`). :meth:`reset_fault` runs the drive's recovery: NMT start
if needed, the configuration again (a rebooted drive is back on its power-on values), controlword bit 7 rising
edge (transition 15), then shutdown → switch on → enable operation (2, 3, 4), holding the current position.
:meth:`home` writes the homing method it means (0x6098, ``homing_method``; 37, "home on the current position",
by default, falling back to its older number 35) and the home offset 0x607C = 0 where the drive has one.
"""

from __future__ import annotations

import logging
import math
import time

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoError
from polarstripe.nodes.drivers import cia402_states as cia
from polarstripe.nodes.drivers.backend import BackendOptions
from polarstripe.nodes.drivers.cia402_states import EDS_PATH, State
from polarstripe.nodes.drivers.cia402_watch import BusWatch, Cia402Watch
from polarstripe.nodes.drivers.errors import DriverError, DriverTimeout, StageFault
from polarstripe.nodes.drivers.stage import RotationStage

MODE_PROFILE_POSITION, MODE_HOMING = 1, 6
#: 0x6502 (supported drive modes) bit of each mode the stage uses
MODE_BITS = {MODE_PROFILE_POSITION: 1 << 0, MODE_HOMING: 1 << 5}
#: homing methods that mean the same ("home on the current position": 35 is the older number of 37)
SAME_HOMING_METHOD = {35: 37, 37: 35}

log = logging.getLogger(__name__)


class Cia402Stage(Cia402Watch, RotationStage):
    """A polarizer rotation stage on a CiA 402 drive (see the module docstring).

    :param channel, interface: the python-can bus (``zmq`` for the simulator, ``socketcan`` on ``can0``), or
        pass an open ``bus``.
    :param node_id: the drive's CANopen node id.
    :param counts_per_deg: encoder counts per degree of the polarizer (gear included).
    :param min_deg, max_deg: software limits [deg], also written to the drive (0x607D).
    :param speed_deg_s: profile velocity [deg/s] written to 0x6081, or None to keep the drive's.
    :param heartbeat_ms: the drive's producer heartbeat time; the consumer timeout is ``heartbeat_timeout_s``.
    :param tolerance_deg: how far from the target a settled stage may be.
    :param homing_method: the CiA 402 homing method :meth:`home` writes to 0x6098.
    """

    class Options(BackendOptions):
        interface: str = "zmq"  # python-can interface: socketcan on a rig, zmq in simulation
        channel: str = "polarstripe"  # python-can channel: can0, or the simulator's ipc://... segment
        node_id: int = 5  # the drive's CANopen node id
        counts_per_deg: float = 1000.0  # encoder counts per analyzer degree, gear included
        speed_deg_s: float | None = 180.0  # profile velocity [deg/s]; None: the drive's
        heartbeat_ms: int = 100  # the drive's producer heartbeat [ms]
        heartbeat_timeout_s: float = 0.5  # a heartbeat older than this is a lost drive [s]
        pdo_timeout_s: float = 0.5  # TPDO1 older than this is stale [s]
        sdo_timeout_s: float = 0.3  # SDO reply timeout [s]
        tolerance_deg: float = 0.01  # how far from the target a settled stage may be [deg]
        connect_timeout_s: float = 3.0
        homing_method: int = 37  # the CiA 402 homing method written to 0x6098

    def __init__(
        self,
        channel: str = "polarstripe",
        node_id: int = 5,
        *,
        interface: str = "zmq",
        bus: can.BusABC | None = None,
        eds: str = EDS_PATH,
        counts_per_deg: float = 1000.0,
        min_deg: float = -360.0,
        max_deg: float = 360.0,
        speed_deg_s: float | None = 180.0,
        heartbeat_ms: int = 100,
        heartbeat_timeout_s: float = 0.5,
        pdo_timeout_s: float = 0.5,
        sdo_timeout_s: float = 0.3,
        tolerance_deg: float = 0.01,
        connect_timeout_s: float = 3.0,
        homing_method: int = 37,
        **bus_kwargs,
    ):
        super().__init__(min_deg=min_deg, max_deg=max_deg, name=f"CiA 402 node {node_id} on {channel}")
        if not counts_per_deg > 0:
            raise ValueError(f"{self.name}: counts_per_deg={counts_per_deg} must be positive")
        self.counts_per_deg, self.tolerance_deg = float(counts_per_deg), float(tolerance_deg)
        self.heartbeat_timeout_s, self.pdo_timeout_s = heartbeat_timeout_s, pdo_timeout_s
        self.heartbeat_ms, self.speed_deg_s, self.homing_method = heartbeat_ms, speed_deg_s, homing_method
        # the watchdog's period: a tenth of the shorter timeout, at most 50 ms (detection within 10 %)
        self._watch_s = min(0.05, heartbeat_timeout_s / 10.0, pdo_timeout_s / 10.0)
        self._init_watch()
        self.supported_modes = 0
        self._own_bus = bus is None
        if bus is None:
            try:
                bus = can.Bus(interface=interface, channel=channel, **bus_kwargs)
            except (can.CanError, OSError, ImportError) as exc:
                raise DriverError(f"{self.name}: cannot open CAN interface {interface!r}: {exc}") from exc
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.05  # the receive poll; a short one makes close() quick
        try:
            self.network.connect()
            self.network.notifier.add_listener(BusWatch(self))
            self.node = canopen.RemoteNode(node_id, eds)
            self.network.add_node(self.node)
            self.node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
            self._start_watch()
            self._check_drive()
            self._configure()
            self.node.tpdo.read(from_od=True)
            self.node.rpdo.read(from_od=True)
            self.node.tpdo[1].subscribe()
            self.node.tpdo[1].add_callback(self._on_tpdo)
            self._enable(connect_timeout_s)
            if self._needs_config:  # the drive rebooted while we connected: its configuration is gone
                self._configure()
                self._enable(connect_timeout_s)
            # a drive found in FAULT was just reset by the enable walk (transition 15): say what it was
            with self._fault_lock:
                self.startup_faults, self._faults = list(self._faults), []
        except BaseException:
            self._close()
            raise

    # -- setup --------------------------------------------------------------------------------------------
    def _check_drive(self) -> None:
        """Device type 402 and profile position among the supported drive modes (0x6502)."""
        sdo = self.node.sdo
        try:
            try:
                device_type = sdo[0x1000].raw
            except SdoError:
                if self._nmt_state != 4:
                    raise
                # a drive in NMT STOPPED serves no SDO: PRE-OPERATIONAL does
                self._send(lambda: self.node.nmt.send_command(0x80), "NMT enter PRE-OPERATIONAL")
                device_type = sdo[0x1000].raw
            self.supported_modes = sdo[0x6502].raw
        except (SdoError, can.CanError) as exc:
            raise DriverError(f"{self.name}: drive check over SDO failed: {exc}") from exc
        if device_type & 0xFFFF != 402:
            raise DriverError(f"{self.name}: device type 0x{device_type:08X} is not a CiA 402 drive")
        if not self.supported_modes & MODE_BITS[MODE_PROFILE_POSITION]:
            raise DriverError(
                f"{self.name}: the drive does not support profile position mode "
                f"(0x6502 = 0x{self.supported_modes:08X})"
            )

    def _configure(self) -> None:
        """Write the configuration (again after a drive reset: it is back on its power-on values)."""
        sdo = self.node.sdo
        try:
            sdo[0x1017].raw = self.heartbeat_ms
            sdo[0x6060].raw = MODE_PROFILE_POSITION  # 0x6502 was checked
            if self.speed_deg_s is not None:
                sdo[0x6081].raw = int(round(self.speed_deg_s * self.counts_per_deg))
            lo = max(-(2**31), math.floor(self.min_deg * self.counts_per_deg))
            hi = min(2**31 - 1, math.ceil(self.max_deg * self.counts_per_deg))
            sdo[0x607D][1].raw, sdo[0x607D][2].raw = lo, hi
        except (SdoError, can.CanError) as exc:
            raise DriverError(f"{self.name}: drive setup over SDO failed: {exc}") from exc
        self._needs_config = False

    def _enable(self, timeout: float) -> None:
        """NMT start, then walk the state machine to OPERATION ENABLED holding the current position."""
        self._nmt_start()
        deadline = time.monotonic() + timeout
        while self._pos is None:
            if time.monotonic() > deadline:
                raise DriverTimeout(
                    f"{self.name}: no TPDO1 from the drive within {timeout:g} s after NMT start"
                )
            time.sleep(0.005)
        self._target_counts = self._pos
        while True:
            state = self.drive_state
            if state is State.OPERATION_ENABLED:
                return
            number = cia.PATH_TO_OPERATION_ENABLED.get(state)
            if time.monotonic() > deadline:
                raise DriverTimeout(f"{self.name}: drive stuck in {state.value} while enabling")
            if number == 15:
                self._controlword(cia.CW_DISABLE_VOLTAGE)
                self._wait_pdo()
            if number is not None:
                self._controlword(cia.TRANSITIONS[number][2])
            self._wait_pdo(until=lambda s=state: self.drive_state is not s, timeout=0.2)

    # -- sending ------------------------------------------------------------------------------------------
    def _send(self, action, what: str) -> None:
        try:
            action()
        except (can.CanError, OSError) as exc:
            self._latch_fault(f"send failed ({what}): {exc}")
            raise StageFault(f"{self.name}: send failed ({what}): {exc}") from exc

    def _controlword(self, cw: int) -> None:
        rpdo = self.node.rpdo[1]

        def send():
            rpdo["Controlword"].raw = cw
            rpdo["Target position"].raw = self._target_counts or 0
            rpdo.transmit()

        self._send(send, f"controlword 0x{cw:04X}")

    def _wait_pdo(self, until=None, timeout: float | None = None) -> bool:
        """Wait for the next TPDO1 (or until ``until()`` holds); True if it came in time."""
        timeout = self.pdo_timeout_s if timeout is None else timeout
        deadline, start = time.monotonic() + timeout, self._pdo_at
        while time.monotonic() < deadline:
            if until() if until else self._pdo_at > start:
                return True
            time.sleep(0.002)
        return False

    # -- RotationStage ------------------------------------------------------------------------------------
    @property
    def drive_state(self) -> State | None:
        """The drive's CiA 402 state from the last statusword, or None before the first TPDO."""
        sw = self._sw
        return None if sw is None else cia.decode_statusword(sw)

    def _start_move(self, angle_deg: float) -> None:
        counts = int(round(angle_deg * self.counts_per_deg))
        with self._lock:
            self._target_counts = counts
            self._acked.clear()
            self._awaiting_ack = True
        self._controlword(cia.CW_ENABLE_OPERATION)
        self._controlword(cia.CW_ENABLE_OPERATION | cia.CW_NEW_SETPOINT | cia.CW_CHANGE_SET_IMMEDIATELY)
        acked = self._acked.wait(self.pdo_timeout_s)
        self._awaiting_ack = False
        self._controlword(cia.CW_ENABLE_OPERATION)
        if not acked:
            text = f"set-point {angle_deg}° not acknowledged within {self.pdo_timeout_s:g} s"
            self._latch_fault(text)
            raise StageFault(f"{self.name}: {text}")

    def _read_angle(self) -> float | None:
        with self._lock:
            fresh = time.monotonic() - self._pdo_at <= self.pdo_timeout_s
            return self._pos / self.counts_per_deg if fresh and self._pos is not None else None

    def _is_settled(self) -> bool:
        with self._lock:
            sw, pos, target = self._sw, self._pos, self._target_counts
            if sw is None or pos is None or target is None or self._awaiting_ack:
                return False
            return (
                bool(sw & cia.SW_TARGET_REACHED)
                and cia.decode_statusword(sw) is State.OPERATION_ENABLED
                and abs(pos - target) <= self.tolerance_deg * self.counts_per_deg
            )

    def _reset(self) -> None:
        if self.network.bus is not None and self.network.bus.state is can.BusState.ERROR:
            raise StageFault(f"{self.name}: cannot reset, the CAN bus is still off (no restart seen)")
        if self._nmt_state != 5:
            self._nmt_start()  # a drive serves SDO in OPERATIONAL and PRE-OPERATIONAL, not in STOPPED
        try:
            self._configure()  # always: a drive that rebooted unseen runs on its power-on values too
        except DriverError as exc:
            text = exc.args[0].removeprefix(f"{self.name}: ")
            raise StageFault(f"{self.name}: cannot reset, {text}") from exc
        if self._listening_clock() - self._hb_at > self.heartbeat_timeout_s:
            # give a recovering drive one heartbeat period to show up
            self._wait_pdo(
                until=lambda: self._listening_clock() - self._hb_at <= self.heartbeat_timeout_s,
                timeout=2 * self.heartbeat_timeout_s,
            )
        if self._listening_clock() - self._hb_at > self.heartbeat_timeout_s:
            raise StageFault(f"{self.name}: cannot reset, the drive's heartbeat is still missing")
        if not self._wait_pdo():
            # the drive may have left OPERATIONAL without our seeing it yet (a reset by another master whose
            # heartbeat is still on its way): NMT start again (a no-op for an OPERATIONAL node, CiA 301)
            self._nmt_start()
            if not self._wait_pdo(timeout=max(2.0, self.pdo_timeout_s)):
                raise StageFault(f"{self.name}: cannot reset, no TPDO1 from the drive")
        self.node.emcy.reset()
        with self._lock:
            self._target_counts = self._pos
        try:
            self._enable(timeout=2.0)
        except DriverTimeout as exc:
            raise StageFault(f"{self.name}: fault reset failed: {exc}") from exc
        # the fault is cleared only when a fresh statusword says so
        self._wait_pdo()
        state = self.drive_state
        if state is not State.OPERATION_ENABLED:
            raise StageFault(f"{self.name}: fault reset failed, drive in {state.value if state else None}")
        # a new set-point at the present position drops whatever set-point the drive still holds (limited
        # ones)
        with self._fault_lock:
            self._faults.clear()
        self._target_deg = self._pos / self.counts_per_deg
        self._start_move(self._target_deg)
        if not self._wait_pdo(until=lambda: not (self._sw or 0) & cia.SW_INTERNAL_LIMIT):
            raise StageFault(
                f"{self.name}: fault reset failed, the drive still reports internal limit active"
            )

    def _home(self, timeout: float) -> None:
        if not self.supported_modes & MODE_BITS[MODE_HOMING]:
            raise StageFault(
                f"{self.name}: the drive does not support homing mode (0x6502 = 0x{self.supported_modes:08X})"
            )
        sdo = self.node.sdo
        try:
            self._write_homing_method()
            if 0x607C in self.node.object_dictionary:
                sdo[0x607C].raw = 0  # the home position is 0° of this stage
            sdo[0x6060].raw = MODE_HOMING
            self._controlword(cia.CW_ENABLE_OPERATION)
            with self._lock:
                self._target_counts = 0
                self._awaiting_ack = True  # until homing attained
            self._controlword(cia.CW_ENABLE_OPERATION | cia.CW_NEW_SETPOINT)
            ended = self._wait_pdo(
                until=lambda: (
                    (sw := self._sw or 0) & cia.SW_FOLLOWING_ERROR
                    or (sw & cia.SW_SETPOINT_ACK and sw & cia.SW_TARGET_REACHED)
                ),
                timeout=timeout,
            )
            failed = bool((self._sw or 0) & cia.SW_FOLLOWING_ERROR)
            self._awaiting_ack = False
            self._controlword(cia.CW_ENABLE_OPERATION)
            sdo[0x6060].raw = MODE_PROFILE_POSITION
        except (SdoError, can.CanError) as exc:
            self._latch_fault(f"homing failed: {exc}")
            raise StageFault(f"{self.name}: homing failed: {exc}") from exc
        if failed:
            text = f"homing error (statusword bit 13), homing method {self.homing_method}"
            self._latch_fault(text)
            raise StageFault(f"{self.name}: {text}")
        if not ended:
            self._latch_fault(f"homing not attained within {timeout:g} s")
            raise DriverTimeout(f"{self.name}: homing not attained within {timeout:g} s")

    def _write_homing_method(self) -> None:
        """0x6098 = ``homing_method``; a drive that refuses 37 or 35 gets the other number of that method."""
        try:
            self.node.sdo[0x6098].raw = self.homing_method
        except SdoAbortedError:
            other = SAME_HOMING_METHOD.get(self.homing_method)
            if other is None:
                raise
            self.node.sdo[0x6098].raw = other

    def _close(self) -> None:
        """Disable the drive if it can hear us, then let go of the bus. Never raises: a bus that failed
        earlier makes canopen's ``Network.disconnect`` re-raise the receive thread's exception, which is
        logged here (the fault was already latched when it happened)."""
        self._stop.set()
        try:
            if getattr(self, "node", None) is not None and self._pos is not None and self.fault is None:
                self._controlword(cia.CW_SHUTDOWN)  # leave the drive disabled (transition 8)
        except StageFault:
            pass
        try:
            if self._own_bus:
                self.network.disconnect()
            elif self.network.notifier is not None:
                self.network.notifier.stop(1.0)
        except Exception as exc:  # noqa: BLE001 - teardown must not raise
            log.warning("%s: closing the CAN network: %s: %s", self.name, type(exc).__name__, exc)
            if self._own_bus and self.network.bus is not None:
                try:
                    self.network.bus.shutdown()
                except Exception as exc2:  # noqa: BLE001
                    log.warning("%s: closing the CAN bus: %s: %s", self.name, type(exc2).__name__, exc2)
                self.network.bus = None
