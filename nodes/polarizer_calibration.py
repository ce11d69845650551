"""Calibration of the analyzer for the polarizer node: ``polarizer/calibrate`` finds E_b, the analyzer angle
of least backscatter.

At each angle (:class:`CalibrateRequest` or the node's ``calibrate_angles_deg``) the stage settles, the
grabber takes a frame (``camera/trigger`` then the matching ``camera/frame``) with ``calibrate_pattern`` lit
through ``emitter/show`` when a node of the launch serves it (``off`` afterwards; a rig's projector
otherwise shows whatever it shows), and Malus's law is fitted over an object-free region
(:func:`polarstripe.imaging.polarization.least_backscatter_angle`). Calibration frames carry scan ids from
:data:`CALIBRATION_SCAN_ID` up, apart from the emitter's scans (the compositor ignores them).

The calibration is a state machine stepped by the node's loop, not a wait inside the service handler: the
handler starts it and returns a :class:`~polarstripe.runtime.node_bus.Deferred`, the ``poll`` timer moves
it on once the stage has settled (and enforces ``settle_timeout_s`` and ``frame_timeout_s``), the matching
``camera/frame`` moves it to the next angle, and the :class:`Calibration` reply goes out at the end. In
between the node keeps publishing ``polarizer/state`` and answers ``polarizer/reset``; a second
``polarizer/calibrate`` is refused while one runs, and a stop answers the running one with a failure.
:class:`Calibrating` is a mixin of :class:`~polarstripe.nodes.polarizer.Polarizer` (it uses the node's
stage, ``_move``, ``_fault_text``, ``state`` and params; ``poll`` calls :meth:`Calibrating.calibration_poll`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.polarization import least_backscatter_angle
from polarstripe.imaging.validation import roi_slices
from polarstripe.msgs import (
    CALIBRATION_SCAN_ID,
    Ack,
    CalibrateRequest,
    Calibration,
    Frame,
    FrameRequest,
    Pattern,
)
from polarstripe.runtime.bus import BusError
from polarstripe.runtime.node_bus import Deferred

_FAILURES = (PolarstripeError, BusError, TimeoutError)


@dataclass
class _Run:
    """A calibration under way: the reply to give, the next step and what it waits for until when."""

    reply: Deferred
    request: CalibrateRequest
    angles: list[float]
    roi: list[int] | None
    scan_id: int
    lit: bool = False
    step: int = 0
    waiting: str = ""  # "settle" | "frame" | "" (between steps)
    deadline: float = math.inf
    measured: list[float] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)
    bit_depth: int = 12


class Calibrating:
    """``polarizer/calibrate`` and its steps, mixed into the polarizer node."""

    _calibration: _Run | None = None

    def in_range(self, angle_deg: float) -> float:
        """The analyzer angle equivalent to ``angle_deg`` (modulo 180°) within the limits: the one in [0, 180)
        if the limits allow, else the nearest to it."""
        here = angle_deg % 180.0
        options = [angle_deg + 180.0 * k for k in range(-8, 9)]
        inside = [a for a in options if self.params.min_deg <= a <= self.params.max_deg]
        if not inside:
            raise PolarstripeError(f"node {self.name!r}: no angle equivalent to {angle_deg:g}° lies within "
                                   f"[{self.params.min_deg:g}, {self.params.max_deg:g}]")
        return min(inside, key=lambda a: abs(a - here))

    # ---- the service -------------------------------------------------------------------------------------
    def calibrate(self, request: CalibrateRequest) -> Calibration | Deferred:
        """Start a calibration; its :class:`Calibration` comes when the loop has taken every angle."""
        p = self.params
        if self.stage is None:
            return Calibration(ok=False, detail=self._connect_error)
        if self._calibration is not None:
            return Calibration(ok=False, detail=f"calibration {self._calibration.scan_id} is running")
        self._calibrations += 1
        run = self._calibration = _Run(
            Deferred(), request, list(request.angles_deg) or list(p.calibrate_angles_deg),
            list(request.roi) or list(p.calibrate_roi) or None, CALIBRATION_SCAN_ID + self._calibrations)
        self._calibration_step(self._calibration_start, run)
        return run.reply

    def _calibration_start(self, run: _Run) -> None:
        if self._trigger is None:
            timeout_s = self.params.frame_timeout_s
            self._trigger = self.client("camera/trigger", FrameRequest, Ack, timeout_s=timeout_s)
        run.lit = self._light(self.params.calibrate_pattern, run.scan_id)
        self._calibration_next(run)

    # ---- the events that step it ---------------------------------------------------------------------------
    def calibration_poll(self) -> None:
        """From :meth:`poll`: settled at the angle → trigger the frame; a fault or a deadline → failure."""
        run = self._calibration
        if run is not None and run.waiting:
            self._calibration_step(self._calibration_check, run)

    def on_calibration_frame(self, frame: Frame) -> None:
        run = self._calibration
        if run is None or run.waiting != "frame" or (frame.scan_id, frame.step) != (run.scan_id, run.step):
            return  # not the frame the calibration waits for (an emitter scan's, a late one)
        run.frames.append(np.asarray(frame.image))
        run.bit_depth = frame.bit_depth
        run.step += 1
        run.waiting, run.deadline = "", math.inf
        self._calibration_step(self._calibration_next, run)

    def calibration_stop(self) -> None:
        """The node is stopping: a running calibration is answered with a failure."""
        run = self._calibration
        if run is not None:
            self._calibration_failed(run, PolarstripeError(f"stopped ({self.stop_reason})"))

    # ---- its steps -----------------------------------------------------------------------------------------
    def _calibration_step(self, step, run: _Run) -> None:
        """Run one step; a failure ends the calibration with its reply (never an exception in the loop)."""
        try:
            step(run)
        except _FAILURES as exc:
            self._calibration_failed(run, exc)
        except Exception as exc:  # unexpected: an error reply, as a handler raising it would give
            self.log.exception("calibration failed")
            self._calibration_end(run)
            run.reply.fail(exc)

    def _calibration_next(self, run: _Run) -> None:
        """Turn to the next angle (or fit when every frame is in)."""
        if run.step == len(run.angles):
            return self._calibration_fit(run)
        self._move(self.in_range(run.angles[run.step]))
        run.waiting, run.deadline = "settle", self.now() + self.params.settle_timeout_s

    def _calibration_check(self, run: _Run) -> None:
        p = self.params
        if run.waiting == "settle":
            fault = self._fault_text()
            if fault:
                raise PolarstripeError(f"stage fault: {fault}")
            state = self.state()
            if state.settled:
                run.measured.append(state.angle_deg)
                return self._calibration_trigger(run)
            if self.now() > run.deadline:
                raise PolarstripeError(f"target {self.target_deg:g}° not reached within "
                                       f"{p.settle_timeout_s:g} s")
        elif run.waiting == "frame" and self.now() >= run.deadline:
            raise PolarstripeError(f"node {self.name!r}: no matching message on "
                                   f"{self.resolve('camera/frame')!r} within {p.frame_timeout_s} s")

    def _calibration_trigger(self, run: _Run) -> None:
        """Have the grabber take the step's frame (a short call, bounded by ``frame_timeout_s``)."""
        ask = FrameRequest(scan_id=run.scan_id, step=run.step, pattern=self.params.calibrate_pattern)
        reply = self._trigger.call(ask)
        if not reply.ok:
            raise PolarstripeError(f"camera/trigger refused step {run.step}: {reply.detail}")
        run.waiting, run.deadline = "frame", self.now() + self.params.frame_timeout_s

    def _calibration_fit(self, run: _Run) -> None:
        p = self.params
        frames = run.frames
        sat = p.saturation_dn if p.saturation_dn is not None else float((1 << run.bit_depth) - 1)
        best = least_backscatter_angle(run.measured, frames, run.roi, dark_offset=p.dark_offset_dn,
                                       saturation=sat)
        best = self.in_range(best)
        index = roi_slices("roi", run.roi, frames[0].shape)
        means = [float(np.mean(f[index])) - p.dark_offset_dn for f in frames]
        self._calibration_end(run)
        self.least_backscatter_deg = best
        if run.request.apply:
            self._move(best)
        self.log.info("least backscatter at %.2f° (from %d angles)", best, len(run.measured))
        run.reply.reply(Calibration(ok=True, angle_deg=best, detail=f"E_b at {best:.2f}°, E_w at "
                                    f"{best + 90.0:.2f}°", angles_deg=run.measured, means_dn=means))

    def _calibration_failed(self, run: _Run, exc: Exception) -> None:
        self.log.error("calibration failed: %s", exc)
        self._calibration_end(run)
        run.reply.reply(Calibration(ok=False, detail=f"calibration failed: {exc}", angles_deg=run.measured))

    def _calibration_end(self, run: _Run) -> None:
        self._calibration = None
        run.waiting = ""
        if run.lit:
            run.lit = False
            self._unlight(run.scan_id)

    # ---- lighting the scene --------------------------------------------------------------------------------
    def _show_client(self):
        """The ``emitter/show`` client, or None when calibration is not to light the scene or no node of
        the launch serves it (then the projector shows whatever it shows)."""

        service = self.params.calibrate_show_service
        if self._show is None and service:
            try:
                self._show = self.client(service, Pattern, Ack, timeout_s=self.params.frame_timeout_s)
            except BusError as exc:
                self._show = False
                self.log.info("calibration does not light the scene: %s", exc)
        return self._show or None

    def _light(self, tag: str, scan_id: int) -> bool:
        """Have the emitter show ``tag`` for the calibration frames; False if there is no emitter to ask.

        :raises PolarstripeError: the emitter refused (a scan is running, a bad pattern).
        """

        show = self._show_client()
        if show is None:
            return False
        service = self.params.calibrate_show_service
        reply = show.call(Pattern.of(tag, scan_id, 0))
        if not reply.ok:
            raise PolarstripeError(f"{service} {tag!r} refused: {reply.detail}")
        return True

    def _unlight(self, scan_id: int) -> None:
        """Blank the projector after the calibration frames (a failure is only logged)."""

        try:
            reply = self._show_client().call(Pattern.of("off", scan_id, 0))
            if not reply.ok:
                self.log.warning("%s off: %s", self.params.calibrate_show_service, reply.detail)
        except (BusError, TimeoutError) as exc:
            self.log.warning("%s off: %s", self.params.calibrate_show_service, exc)
