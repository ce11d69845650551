"""The polarizer node: turns the analyzer with a :class:`~polarstripe.nodes.drivers.stage.RotationStage` and
says where it is.

The stage is a backend of :mod:`polarstripe.nodes.drivers`, named by ``stage`` and made from
``stage_options`` (the backend's own ``Options``: docs/nodes.md) and the node's software limits ``min_deg`` /
``max_deg``: ``cia402`` (a CANopen CiA 402 drive on python-can: ``interface``/``channel``, ``zmq`` +
``ipc://…`` in simulation, ``socketcan`` + ``can0`` on a rig), ``ell14`` (Thorlabs ELL14 on serial ``port``),
``sim`` (an in-process motion model), or an entry point's.

* subscribes ``polarizer/cmd`` (:class:`PolarizerCommand`): move to ``target_deg``;
* publishes ``polarizer/state`` (:class:`PolarizerState`) every ``1/rate_hz`` s and as soon as anything
  changes (checked every ``poll_s``). While any fault stands, ``angle_deg`` is NaN and ``settled`` False: a
  fault is published, never a wrong angle. Faults: the stage's own (EMCY, lost heartbeat, bus error frames and
  bus-off, a failed send, the drive's limit), a target not reached within ``settle_timeout_s``, a rejected
  command, a stage that cannot be opened (retried every ``connect_retry_s``);
* recovers with the drive's fault-reset sequence: automatically (at most ``auto_resets`` tries, the wait
  before each twice the one before, from ``reset_delay_s``; refilled by every new command and every settle
  at the target), then re-commands the last target; and on request (``polarizer/reset``, or a new command
  while faulted);
* serves ``polarizer/calibrate`` (:class:`CalibrateRequest` → :class:`Calibration`): turns through analyzer
  angles, has the grabber take a frame at each (``camera/trigger`` then the matching ``camera/frame``) under
  ``calibrate_pattern`` lit through ``emitter/show`` (when a node serves it; ``off`` afterwards), and
  fits Malus's law over a region (:func:`polarstripe.imaging.polarization.least_backscatter_angle`) for the
  angle of least backscatter, E_b. Calibration frames carry scan ids from :data:`CALIBRATION_SCAN_ID`
  (2**30) up, apart from the emitter's scans (the compositor ignores them). The calibration is stepped by
  the loop (:mod:`polarstripe.nodes.polarizer_calibration`): the state keeps being published and
  ``polarizer/reset`` answered while it runs, and its reply comes at the end. The last E_b
  (``least_backscatter_deg``) is kept in the run directory (``state/polarizer.json``, runtime/liveness.py):
  a respawned polarizer restores it; its calibration scan ids start 2**16 further per incarnation.
"""

from __future__ import annotations

import logging
import math
from typing import Any

from polarstripe.msgs import (
    Ack,
    CalibrateRequest,
    Calibration,
    Empty,
    Frame,
    PolarizerCommand,
    PolarizerState,
)
from polarstripe.nodes.drivers.errors import DriverError, DriverValueError
from polarstripe.nodes.drivers.registry import check_backend, open_backend
from polarstripe.nodes.polarizer_calibration import Calibrating
from polarstripe.runtime.liveness import RunState
from polarstripe.runtime.node import Node
from polarstripe.runtime.params import NodeParams

__all__ = ["Polarizer"]


class Polarizer(Calibrating, Node):
    """The analyzer's rotation stage as a node (see the module docstring)."""

    class Params(NodeParams):
        stage: str = "sim"  # stage backend: cia402 | ell14 | sim, or an entry point's
        stage_options: dict[str, Any] = {}  # the backend's own options (its Options)
        min_deg: float = -360.0  # software limits [deg], passed to the stage
        max_deg: float = 360.0
        start_deg: float | None = None  # move here once connected
        rate_hz: float = 10.0  # steady publishing rate of polarizer/state
        poll_s: float = 0.02  # how often a change is looked for while a move or a fault is in progress
        idle_poll_s: float = 0.1  # ... and while settled without a fault (at most 1/rate_hz)
        settle_timeout_s: float = 5.0
        auto_resets: int = 5
        reset_delay_s: float = 0.2  # wait before the first automatic fault reset (then 2x, 4x, ...)
        connect_retry_s: float = 1.0
        calibrate_angles_deg: list[float] = [0.0, 30.0, 60.0, 90.0, 120.0, 150.0]
        calibrate_roi: list[int] = []  # object-free region (row0, row1, col0, col1); empty: whole frame
        calibrate_pattern: str = "flood"
        calibrate_show_service: str = "emitter/show"  # lights calibrate_pattern first, if served; "": don't
        frame_timeout_s: float = 5.0
        dark_offset_dn: float = 0.0
        saturation_dn: float | None = None  # None: 2**bit_depth - 1 of the frames

        def validate(self):
            super().validate()
            check_backend("stage", self.stage, self.stage_options)
            if not self.min_deg < self.max_deg:
                raise ValueError(f"min_deg={self.min_deg} must be below max_deg={self.max_deg}")
            for key in ("rate_hz", "poll_s", "idle_poll_s", "settle_timeout_s", "connect_retry_s",
                        "frame_timeout_s"):
                if not getattr(self, key) > 0:
                    raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
            if self.auto_resets < 0 or self.reset_delay_s < 0:
                raise ValueError("auto_resets and reset_delay_s must be >= 0")
            if self.calibrate_roi and len(self.calibrate_roi) != 4:
                raise ValueError(f"calibrate_roi must be [row0, row1, col0, col1], got {self.calibrate_roi}")

    PUBLISHES = {"polarizer/state": PolarizerState}
    SUBSCRIBES = {"polarizer/cmd": PolarizerCommand, "camera/frame": Frame}
    SERVES = {"polarizer/calibrate": (CalibrateRequest, Calibration), "polarizer/reset": (Empty, Ack)}

    @property
    def least_backscatter_deg(self) -> float | None:
        """E_b of the last calibration [deg], kept in the run directory (runtime/liveness.py)."""
        return self.run_state.get("least_backscatter_deg")

    @least_backscatter_deg.setter
    def least_backscatter_deg(self, value: float | None) -> None:
        self.run_state.save(least_backscatter_deg=value)

    # ---- wiring ----------------------------------------------------------------------------------------
    def setup(self):
        self.stage = None
        self.target_deg: float | None = None  # the last commanded target
        self.run_state = RunState.of(self.graph, self.name)  # the calibration outlives a respawn
        if self.least_backscatter_deg is not None:
            self.log.info("calibration restored: E_b at %.2f deg (run state)", self.least_backscatter_deg)
        self._connect_error = "not connected yet"
        self._next_connect = -math.inf
        self._node_fault = ""  # faults the node finds itself (settle timeout, rejected command)
        self._node_fault_resettable = False
        self._move_started: float | None = None
        self._resets_left = self.params.auto_resets
        self._next_reset: float | None = None
        self._last_key = None
        self._last_pub = -math.inf
        # calibration scan ids go on across incarnations too: offset by 2**16 per incarnation
        self._calibrations = self.incarnation << 16
        self._trigger = None
        self._show = None  # emitter/show client; False once known not to be served
        for key in ("moves", "faults", "auto_resets", "resets_failed", "connects_failed"):
            self.counters[key] = 0
        self.state_pub = self.publisher("polarizer/state")
        self.subscribe("polarizer/cmd", self.on_command, mode="all")
        self.subscribe("camera/frame", self.on_calibration_frame, mode="latest")  # calibration frames
        self.serve("polarizer/calibrate", self.calibrate)
        self.serve("polarizer/reset", self.on_reset)
        self._poll_fast = True
        self.every(self.params.poll_s, self.poll, name="poll")
        self._connect()
        self.poll()

    def teardown(self):
        self.calibration_stop()  # a calibration under way gets its (failed) reply
        if self.stage is not None:
            self.stage.close()  # never raises (a failed bus is logged by the driver)
            self.stage = None

    def _open_stage(self):
        p = self.params
        return open_backend("stage", p.stage, p.stage_options, min_deg=p.min_deg, max_deg=p.max_deg)

    def _connect(self) -> None:
        self._next_connect = self.now() + self.params.connect_retry_s
        sdo_log = logging.getLogger("canopen.sdo.client")  # one error line per failed try is ours, not its
        level = sdo_log.level
        sdo_log.setLevel(logging.CRITICAL)
        try:
            self.stage = self._open_stage()
        except Exception as exc:  # any backend or bus failure: a published fault, retried
            self.counters["connects_failed"] += 1
            text = f"{self.params.stage} stage not connected: {type(exc).__name__}: {exc}"
            if text != self._connect_error:
                self.log.error("%s (retrying every %g s)", text, self.params.connect_retry_s)
            self._connect_error = text
            return
        finally:
            sdo_log.setLevel(level)
        self._connect_error = ""
        self.log.info("connected: %s", self.stage.name)
        start = self.target_deg if self.target_deg is not None else self.params.start_deg
        if start is not None:
            self._move(start)

    # ---- commands ------------------------------------------------------------------------------------------
    def on_command(self, msg: PolarizerCommand) -> None:
        self._resets_left = self.params.auto_resets
        if self.stage is not None and self._fault_text():
            self._reset("command while faulted")
        self._move(msg.target_deg)

    def on_reset(self, request: Empty) -> Ack:
        self._resets_left = self.params.auto_resets
        if self.stage is None:
            return Ack(ok=False, detail=self._connect_error)
        ok = self._reset("requested")
        if ok and self.target_deg is not None:
            self._move(self.target_deg)
        self.poll()
        return Ack(ok=ok and not self._fault_text(), detail=self._fault_text() or "fault cleared")

    def _move(self, angle_deg: float) -> None:

        self.target_deg = float(angle_deg)
        self._node_fault, self._node_fault_resettable = "", False
        self._set_poll(fast=True)  # until settled (or a failed move's fault is published)
        if self.stage is None:
            return  # moved there once connected
        try:
            self.stage.move_to(angle_deg)
        except DriverValueError as exc:
            self._set_node_fault(f"command rejected: {exc}", resettable=False)
            return
        except DriverError as exc:  # the stage latched it (send failure, fault)
            self.log.warning("move to %g° failed: %s", angle_deg, exc)
            return
        self.counters["moves"] += 1
        self._move_started = self.now()

    def _set_node_fault(self, text: str, *, resettable: bool) -> None:
        self._node_fault, self._node_fault_resettable = text, resettable
        self.log.error("%s", text)

    # ---- faults and recovery -------------------------------------------------------------------------
    def _fault_text(self) -> str:
        if self.stage is None:
            return self._connect_error
        parts = [t for t in (self.stage.fault, self._node_fault) if t]
        return "; ".join(parts)

    def _reset(self, why: str) -> bool:
        """The drive's fault-reset sequence; True if the stage came back without a fault."""

        try:
            self.stage.reset_fault()
        except DriverError as exc:
            self.counters["resets_failed"] += 1
            self.log.warning("fault reset (%s) failed: %s", why, exc)
            return False
        if self._node_fault_resettable:
            self._node_fault, self._node_fault_resettable = "", False
        self._move_started = None
        self.log.info("fault reset (%s) done", why)
        return True

    def _recover(self, now: float) -> None:
        """Automatic recovery: a bounded number of fault resets, each followed by the last command again."""
        if self._next_reset is None:
            self._next_reset = now + self.params.reset_delay_s
            self._reset_wait = self.params.reset_delay_s
            return
        if now < self._next_reset or self._resets_left <= 0:
            return
        if self._node_fault and not self._node_fault_resettable:
            return  # a rejected command waits for a good one
        self._resets_left -= 1
        self.counters["auto_resets"] += 1
        self._reset_wait *= 2.0  # a drive that needs longer (a restarting bus, a busy host) gets it
        self._next_reset = now + self._reset_wait
        if self._reset(f"automatic, {self._resets_left} left") and self.target_deg is not None:
            self._move(self.target_deg)
        if self._resets_left == 0 and self._fault_text():
            self.log.error("giving up automatic fault resets; send a command or call polarizer/reset")

    # ---- the state -----------------------------------------------------------------------------------------
    def poll(self) -> None:
        now = self.now()
        if self.stage is None and now >= self._next_connect:
            self._connect()
        stage = self.stage
        if stage is not None and self._move_started is not None and not self._node_fault and not stage.fault:
            if stage.settled:
                self._move_started = None
                self._resets_left = self.params.auto_resets
            elif now - self._move_started > self.params.settle_timeout_s:
                self._move_started = None
                reading = stage.angle
                self._set_node_fault(
                    f"target {self.target_deg:g}° not reached within {self.params.settle_timeout_s:g} s "
                    f"(last reading {'none' if reading is None else f'{reading:.3f}°'})", resettable=True)
        fault = self._fault_text()
        if fault and stage is not None:
            self._recover(now)
            fault = self._fault_text()
        elif not fault:
            self._next_reset = None
        state = self.state()
        key = (None if math.isnan(state.angle_deg) else round(state.angle_deg, 3), state.target_deg,
               state.settled, state.fault)
        if key != self._last_key or now - self._last_pub >= 1.0 / self.params.rate_hz - 1e-6:
            if state.fault and (self._last_key is None or state.fault != self._last_key[3]):
                self.counters["faults"] += 1
            self.state_pub.publish(state)
            self._last_key, self._last_pub = key, now
        self._set_poll(fast=bool(self._move_started is not None or fault))
        self.calibration_poll()  # a calibration under way moves on (or fails) with what was seen here

    def _set_poll(self, *, fast: bool) -> None:
        """Poll every ``poll_s`` while a move or a fault is in progress, else every ``idle_poll_s`` (capped
        at the steady period 1/rate_hz): a settled stage costs a tenth of the wake-ups."""
        if fast == self._poll_fast:
            return
        self._poll_fast = fast
        p = self.params
        self.cancel("poll")
        self.every(p.poll_s if fast else min(p.idle_poll_s, 1.0 / p.rate_hz), self.poll, name="poll")

    def state(self) -> PolarizerState:
        """The state as it stands: NaN angle and not settled whenever a fault stands."""
        fault = self._fault_text()
        stage = self.stage
        angle = None if fault or stage is None else stage.angle
        target = self.target_deg if self.target_deg is not None else (stage.target if stage else None)
        settled = bool(not fault and stage is not None and stage.settled and angle is not None
                       and (self.target_deg is None
                            or (stage.target is not None and abs(stage.target - self.target_deg) < 1e-9)))
        nan = float("nan")
        return PolarizerState(angle_deg=nan if angle is None else float(angle),
                              target_deg=nan if target is None else float(target), settled=settled,
                              fault=fault)


NODE = Polarizer
