"""Projector–camera calibration over the rig's nodes (launch/calibrate.toml; the method is docs/depth.md
"Calibration", the pure steps :mod:`polarstripe.imaging.calibration`).

The calibrator node, per board pose k of ``poses``:

1. puts the board at pose k: calls ``target_service`` (the simulator's ``simulator/target``, Empty → Ack)
   or, on a real rig (``target_service = ""``), logs "pose k: place the board" and waits ``pose_wait_s``;
2. for each of ``flood``, ``off`` and the XOR code of the ``projector`` size (imaging/structured_light.py
   ``calibration_code``): ``emitter/show`` (the pattern), ``camera/trigger`` (a FrameRequest tagged with that
   pattern, scan id ``CALIBRATION_SCAN_ID + 1000 + k``, step i) and the matching frame on ``camera/frame``,
   exactly as a scan's frames travel (docs/architecture.md "How a frame travels");
3. decodes the pose (``decode_pose``; a pose the board or its decoding fails is skipped with its reason)
   and rewrites the live coverage view ``<out>_coverage.png``.

Then ``calibrate`` fits both devices and the stereo pose (with ``port``, both behind flat ports of that data
sheet, :func:`~polarstripe.imaging.port_calibration.fit_ports` then fits the refractive rig, the lens taken
as undistorted unless ``lens_distortion`` gives it; ``glass_tank`` is one tank wall before both devices)
and ``save`` writes ``out`` atomically (a failed run leaves the previous file whole). The analyzer is taken
out of the path first (``camera/analyzer``). Exit status 0 with a file written, 1 otherwise (the ERROR line
says why). Like the sequencer, it is a script: it blocks in its own ``run`` and serves nothing.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.calibration import (
    MIN_POSES,
    Board,
    CalibrationError,
    PoseError,
    calibrate,
    coverage_image,
    decode_pose,
    failed_poses,
    save,
)
from polarstripe.imaging.port_calibration import fit_ports, names_a_wall, parse_distortion, parse_port_spec
from polarstripe.imaging.structured_light import calibration_code
from polarstripe.msgs import Ack, Empty, Frame, FrameRequest, Heartbeat, Pattern
from polarstripe.msgs.rig import CALIBRATION_SCAN_ID, AnalyzerMount
from polarstripe.runtime.bus import BusError, BusTimeout
from polarstripe.runtime.node import Node, NodeStopping
from polarstripe.runtime.params import NodeParams
from polarstripe.sim.scene import SceneError, parse_size
from polarstripe.sim.scene_target import parse_board

SCAN_ID_BASE = CALIBRATION_SCAN_ID + 1000  # frames of pose k carry scan id SCAN_ID_BASE + k


def coverage_path(out: str) -> str:
    """``rig_coverage.png`` beside ``rig.yaml``."""
    return os.path.splitext(out)[0] + "_coverage.png"


def write_coverage(path: str, poses, proj_size) -> None:
    """The coverage view (imaging.calibration.coverage_image), replaced atomically: watch it fill in."""
    base, ext = os.path.splitext(path)
    tmp = f"{base}.tmp{os.getpid()}{ext}"
    if not cv2.imwrite(tmp, coverage_image(poses, proj_size)):
        raise PolarstripeError(f"cannot write {path!r}")
    os.replace(tmp, path)

class RigCalibrationError(CalibrationError):
    """A step of the calibration over the nodes failed; the text names the service, topic or pose."""


class RigCalibrator(Node):
    """Calibrates the rig over its nodes (see the module docstring)."""

    class Params(NodeParams):
        out: str = "rig.yaml"  # the calibration file (OpenCV FileStorage; .yaml, .xml or .json)
        projector: str = "1024x768"  # the emitter's display size WxH (its display_options width, height)
        board: str = "8x6"  # inner corners COLSxROWS
        square_m: float = 0.015
        poses: int = 8
        distortion: str = "radial"  # none | radial | full (the camera's lens model)
        port: str = ""  # flat ports: glass_tank (one tank wall before both) or T,N_AIR,N_GLASS,N_WATER (each)
        lens_distortion: str = ""  # behind ports: the camera lens's K1,K2[,P1,P2[,K3]], calibrated in air
        target_service: str = "simulator/target"  # moves the board; "" = a person does (pose_wait_s)
        pose_wait_s: float = 10.0
        startup_timeout_s: float = 30.0
        frame_timeout_s: float = 30.0

        def validate(self):
            super().validate()
            parse_size(self.projector, "projector")
            parse_board(self.board, "board")
            if self.poses < MIN_POSES:
                raise ValueError(f"poses={self.poses}: a calibration needs at least {MIN_POSES}")
            if self.distortion not in ("none", "radial", "full"):
                raise ValueError(f"distortion must be none, radial or full, got {self.distortion!r}")
            if not self.square_m > 0:
                raise ValueError(f"square_m must be > 0, got {self.square_m}")
            try:
                parse_port_spec(self.port)
                parse_distortion(self.lens_distortion)
            except CalibrationError as exc:
                raise ValueError(str(exc)) from None

    SUBSCRIBES = {"camera/frame": Frame, "heartbeat": Heartbeat}

    def setup(self):
        self.subscribe("camera/frame", mode="all")
        self.subscribe("heartbeat", mode="all")

    def run(self) -> None:
        ok = False
        try:
            ok = self.calibrate()
        except (RigCalibrationError, CalibrationError, SceneError) as exc:
            self.log.error("%s", exc)
        except NodeStopping:
            pass
        if not self.stopping:
            self.stop("calibration written" if ok else "calibration failed", exit_code=0 if ok else 1)
        for _ in self.events():  # ends with Stop
            pass

    # ---- steps ---------------------------------------------------------------------------------------------
    def call(self, service: str, req_type, request, *, timeout_s: float = 5.0) -> Ack:
        """Call ``service`` (reply Ack), retried while it is not up yet or its node is respawned
        (``startup_timeout_s``, runtime/client.py); a refusal is an error naming the service."""
        client = self.client(service, req_type, Ack, timeout_s=timeout_s)
        try:
            reply = client.call(request, retry_s=self.params.startup_timeout_s)
        except BusError as exc:
            raise RigCalibrationError(f"{service}: {exc}") from None
        if not reply.ok:
            raise RigCalibrationError(f"{service}: {reply.detail}")
        return reply

    def grab(self, tag: str, scan_id: int, step: int) -> np.ndarray:
        """Show ``tag``, trigger the camera, return the matching frame's image."""
        self.call("emitter/show", Pattern, Pattern.of(tag, scan_id=scan_id, step=step))
        self.call("camera/trigger", FrameRequest, FrameRequest(scan_id=scan_id, step=step, pattern=tag),
                  timeout_s=self.params.frame_timeout_s)
        try:
            frame = self.wait_for("camera/frame", lambda f: f.scan_id == scan_id and f.step == step,
                                  self.params.frame_timeout_s)
        except BusTimeout as exc:
            pose = scan_id - SCAN_ID_BASE
            raise RigCalibrationError(f"camera/frame of {tag} (pose {pose}): {exc}") from None
        return np.asarray(frame.image)

    def calibrate(self) -> bool:
        p = self.params
        out_dir = os.path.dirname(os.path.abspath(p.out))
        if not os.path.isdir(out_dir):
            raise RigCalibrationError(f"param 'out' {p.out!r}: folder {out_dir!r} does not exist")
        cols, rows = parse_board(p.board, "board")
        board = Board(cols, rows, float(p.square_m))
        proj = parse_size(p.projector, "projector")
        tags = ["flood", "off", *(str(g) for g in calibration_code(*proj))]
        self.call("camera/analyzer", AnalyzerMount, AnalyzerMount(inserted=False))
        results, failures, cam_size = [], [], None
        for k in range(p.poses):
            if p.target_service:
                self.log.info("pose %d: %s", k, self.call(p.target_service, Empty, Empty()).detail)
            else:
                self.log.warning("pose %d of %d: place the board; frames in %g s", k, p.poses, p.pose_wait_s)
                deadline = self.now() + p.pose_wait_s
                while self.now() < deadline and not self.stopping:
                    self.take("heartbeat", deadline - self.now())  # keeps the loop's inbox drained
                if self.stopping:
                    return False
            images = [self.grab(tag, SCAN_ID_BASE + k, i) for i, tag in enumerate(tags)]
            cam_size = (images[0].shape[1], images[0].shape[0])
            try:
                results.append(decode_pose(images[0], images[1], images[2:], board, proj, pose=k))
            except PoseError as exc:
                failures.append(exc)
                self.log.warning("skipped %s", exc)
                continue
            write_coverage(coverage_path(p.out), results, proj)  # the live view: the poses so far
            self.log.info("pose %d: %d pixels decoded around the corners (%d poses usable)", k,
                          results[-1].decoded, len(results))
        self.call("emitter/show", Pattern, Pattern.of("off"))
        if len(results) < MIN_POSES:
            raise RigCalibrationError(f"{len(results)} usable poses of {p.poses}: a calibration needs at "
                                      f"least {MIN_POSES}"
                                      + (f"; {failed_poses(failures)}" if failures else ""))
        pinhole = calibrate(results, board, cam_size, proj, distortion=p.distortion)
        spec = parse_port_spec(p.port)
        wall = names_a_wall(p.port)
        cal = pinhole if spec is None else fit_ports(pinhole, board, spec, spec, one_wall=wall,
                                                     lens_distortion=parse_distortion(p.lens_distortion))
        extra = {"rms_cam": cal.rms_cam, "rms_proj": cal.rms_proj, "rms_stereo": cal.rms_stereo,
                 "poses": len(pinhole.poses), "board": f"{p.board} inner corners, {p.square_m} m squares",
                 "source": f"polarstripe launch launch/calibrate.toml (node {self.name})"}
        if spec is not None:
            extra.update(model="refractive (flat ports)", corners_dropped=cal.dropped,
                         pinhole_rms_cam=pinhole.rms_cam, pinhole_rms_proj=pinhole.rms_proj, **cal.sigma)
        save(p.out, {**cal.geometry(), "dist_proj": np.zeros(5) if spec else pinhole.dist_proj}, extra)
        write_coverage(coverage_path(p.out), pinhole.poses, cal.proj_size)
        self.log.info("%s: %d poses, %s, RMS camera %.3f px, projector %.3f px, stereo %.3f px; coverage %s",
                      p.out, len(pinhole.poses), "pinhole" if spec is None else "refractive (flat ports)",
                      cal.rms_cam, cal.rms_proj, cal.rms_stereo, coverage_path(p.out))
        return True


NODE = RigCalibrator
