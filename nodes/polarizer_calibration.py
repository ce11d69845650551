"""Calibration of the analyzer for the polarizer node: ``polarizer/calibrate`` finds E_b, the analyzer angle
of least backscatter.

At each angle (:class:`CalibrateRequest` or the node's ``calibrate_angles_deg``) the stage settles, the
grabber takes a frame (``camera/trigger`` then the matching ``camera/frame``) with ``calibrate_pattern`` lit
through ``emitter/show`` when a node of the launch serves it (``off`` afterwards; a rig's projector
otherwise shows whatever it shows), and Malus's law is fitted over an object-free region
(:func:`polarstripe.imaging.polarization.least_backscatter_angle`). Calibration frames carry scan ids from
:data:`CALIBRATION_SCAN_ID` up, apart from the emitter's scans (the compositor ignores them).
:class:`Calibrating` is a mixin of :class:`~polarstripe.nodes.polarizer.Polarizer` (it uses the node's stage,
``_move``, ``poll``, ``state`` and params).
"""

from __future__ import annotations

import time

import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.polarization import least_backscatter_angle
from polarstripe.imaging.validation import roi_slices
from polarstripe.msgs import CALIBRATION_SCAN_ID, Ack, CalibrateRequest, Calibration, FrameRequest, Pattern
from polarstripe.runtime.bus import BusError


class Calibrating:
    """``polarizer/calibrate`` and its helpers, mixed into the polarizer node."""

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

    def _wait_settled(self, timeout_s: float) -> float:
        """Block (publishing the state) until settled at the target; the measured angle [deg]."""
        deadline = time.monotonic() + timeout_s
        while True:
            self.poll()
            fault = self._fault_text()
            if fault:
                raise PolarstripeError(f"stage fault: {fault}")
            state = self.state()
            if state.settled:
                return state.angle_deg
            if time.monotonic() > deadline:
                raise PolarstripeError(f"target {self.target_deg:g}° not reached within {timeout_s:g} s")
            time.sleep(min(self.params.poll_s, 0.01))

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

    def calibrate(self, request: CalibrateRequest) -> Calibration:

        p = self.params
        angles = list(request.angles_deg) or list(p.calibrate_angles_deg)
        roi = list(request.roi) or list(p.calibrate_roi) or None
        if self.stage is None:
            return Calibration(ok=False, detail=self._connect_error)
        self._calibrations += 1
        scan_id = CALIBRATION_SCAN_ID + self._calibrations
        measured, frames = [], []
        lit = False
        try:
            if self._trigger is None:
                self._trigger = self.client("camera/trigger", FrameRequest, Ack, timeout_s=p.frame_timeout_s)
            lit = self._light(p.calibrate_pattern, scan_id)
            for step, angle in enumerate(angles):
                self._move(self.in_range(angle))
                measured.append(self._wait_settled(p.settle_timeout_s))
                ask = FrameRequest(scan_id=scan_id, step=step, pattern=p.calibrate_pattern)
                reply = self._trigger.call(ask)
                if not reply.ok:
                    raise PolarstripeError(f"camera/trigger refused step {step}: {reply.detail}")
                frame = self.wait_for("camera/frame", lambda m, s=step: m.scan_id == scan_id and m.step == s,
                                      timeout_s=p.frame_timeout_s)
                frames.append(np.asarray(frame.image))
            sat = p.saturation_dn if p.saturation_dn is not None else float((1 << frame.bit_depth) - 1)
            best = least_backscatter_angle(measured, frames, roi, dark_offset=p.dark_offset_dn,
                                           saturation=sat)
            best = self.in_range(best)
            index = roi_slices("roi", roi, frames[0].shape)
            means = [float(np.mean(f[index])) - p.dark_offset_dn for f in frames]
        except (PolarstripeError, BusError, TimeoutError) as exc:
            self.log.error("calibration failed: %s", exc)
            return Calibration(ok=False, detail=f"calibration failed: {exc}", angles_deg=measured)
        finally:
            if lit:
                self._unlight(scan_id)
        self.least_backscatter_deg = best
        if request.apply:
            self._move(best)
        self.log.info("least backscatter at %.2f° (from %d angles)", best, len(measured))
        return Calibration(ok=True, angle_deg=best, detail=f"E_b at {best:.2f}°, E_w at {best + 90.0:.2f}°",
                           angles_deg=measured, means_dn=means)

