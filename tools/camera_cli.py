"""``polarstripe camera``: try a camera before a run.

* ``camera list``: the cameras this host sees: GenICam cameras through Aravis (a GigE Vision discovery
  broadcast on every interface, and USB3 Vision devices) and V4L2 devices; ``--address A`` asks only that
  GigE Vision address (no broadcast), for a camera behind a router or the simulator on 127.0.0.1.
* ``camera grab BACKEND:DEVICE -o frame.png``: one frame through the rig's own backend (``aravis:ADDRESS``,
  ``v4l2:/dev/video0``) with the exposure, gain, pixel format and trigger given, written as a PNG (16-bit for
  deeper pixels) or ``.npy``; it prints the frame's size, format, exposure, the camera's frame id and time.
* ``camera fake``: Aravis's GigE Vision simulator on a loopback address until Ctrl-C, to try ``camera grab``
  and ``launch/lab_rig.toml camera=aravis camera_device=127.0.0.1`` without a camera.

Every failure (nothing at the address, a pixel format or trigger the camera does not offer, a dropped frame)
is one line, ``polarstripe camera: error: …``, exit status 2.
"""

from __future__ import annotations

import argparse
import glob
import os
import signal
import threading
from pathlib import Path

import cv2
import numpy as np
from polarstripe.errors import PolarstripeError
from polarstripe.nodes.drivers.registry import backend_options, load_backend, open_backend

HELP = "list cameras, grab one frame through a backend, or run Aravis's GigE Vision simulator"


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    ls = sub.add_parser("list", help="the cameras this host sees (Aravis: GigE Vision, USB3 Vision; V4L2)",
                        description="The cameras this host sees. Without --address: Aravis's GigE Vision "
                                    "discovery (a broadcast on every network interface), USB3 Vision devices "
                                    "and /dev/video*.")
    ls.add_argument("--address", action="append", default=[], metavar="A",
                    help="ask only this GigE Vision address (no broadcast); repeatable")
    grab = sub.add_parser("grab", help="grab one frame through a backend and write it",
                          description="Grab one frame through the rig's camera backend and write it.")
    grab.add_argument("camera", metavar="BACKEND:DEVICE",
                      help="aravis:ADDRESS (GigE Vision) or aravis:ID (USB3 Vision), v4l2:/dev/videoN")
    grab.add_argument("-o", "--output", required=True, metavar="FILE",
                      help="frame.png (16-bit PNG for pixels deeper than 8 bits), .tif or .npy")
    grab.add_argument("--exposure-us", type=float, metavar="N", help="exposure [µs]")
    grab.add_argument("--gain", type=float, help="gain, in the camera's unit (Gain: dB; GainRaw: steps)")
    grab.add_argument("--pixel-format", metavar="FMT", help="aravis: Mono8, Mono10, Mono12, Mono14, Mono16")
    grab.add_argument("--trigger", metavar="T", help="aravis: software (default), off, Line0, Line1, …")
    grab.add_argument("--timeout", type=float, default=5.0, metavar="S", help="seconds to wait (default 5)")
    fake = sub.add_parser("fake", help="run Aravis's GigE Vision simulator on a loopback address",
                          description="Aravis's GigE Vision simulator (512x512 ramp, software trigger, "
                                      "Mono8/Mono16) on a loopback address until Ctrl-C.")
    fake.add_argument("--address", default="127.0.0.1", help="a 127.x.x.x address (default 127.0.0.1)")
    fake.add_argument("--serial", default="GV01", help="its serial number (default GV01)")
    fake.add_argument("--lost-ratio", type=float, default=0.0, metavar="R",
                      help="fraction of stream packets it drops (0-1, default 0)")


def main(args: argparse.Namespace) -> int:
    return {"list": list_cameras, "grab": grab_frame, "fake": run_fake}[args.action](args)


def _aravis():
    """The Aravis helpers, or PolarstripeError saying what to install."""
    load_backend("camera", "aravis")  # BackendUnavailable (one line, what to install) without Aravis
    from polarstripe.nodes.drivers import aravis_system

    return aravis_system


def _v4l2_devices() -> list[tuple[str, str]]:
    out = []
    for path in sorted(glob.glob("/dev/video*")):
        name_file = Path("/sys/class/video4linux") / os.path.basename(path) / "name"
        out.append((path, name_file.read_text().strip() if name_file.exists() else ""))
    return out


def list_cameras(args: argparse.Namespace) -> int:
    aravis = _aravis() if args.address else None
    if args.address:
        cameras = [aravis.probe(a) for a in args.address]
        v4l2 = []
    else:
        try:
            cameras = _aravis().discover()
        except PolarstripeError as exc:  # no Aravis here: V4L2 only, and say why
            print(f"(Aravis: {exc})")
            cameras = []
        v4l2 = _v4l2_devices()
    for cam in cameras:
        print(f"aravis:{cam.device:<24} {cam.vendor} {cam.model}, serial {cam.serial or '?'} "
              f"({cam.protocol})")
    for path, name in v4l2:
        print(f"v4l2:{path:<26} {name}")
    if not cameras and not v4l2:
        print("no camera found (GigE Vision discovery on every interface, USB3 Vision, /dev/video*)")
    return 0


def grab_frame(args: argparse.Namespace) -> int:
    backend, sep, device = args.camera.partition(":")
    if not sep or not device:
        raise PolarstripeError(f"camera {args.camera!r}: give BACKEND:DEVICE, e.g. aravis:192.168.1.20")
    suffix = Path(args.output).suffix.lower()
    if suffix not in (".png", ".tif", ".tiff", ".npy"):
        raise PolarstripeError(f"output {args.output!r}: write .png, .tif or .npy")
    options = {"device": device}
    if args.pixel_format is not None:
        options["pixel_format"] = args.pixel_format
    if args.trigger is not None:
        options["trigger"] = args.trigger
    backend_options("camera", backend, options)  # an option the backend does not take: one line, first
    common = {}
    if args.exposure_us is not None:
        common["exposure_s"] = args.exposure_us * 1e-6
    if args.gain is not None:
        common["gain"] = args.gain
    with open_backend("camera", backend, options) as cam:
        for key, value in common.items():  # through the role, as the grabber sets them
            setattr(cam, key, value)
        frame = cam.grab(timeout=args.timeout)
    image = frame.image
    if suffix == ".npy":
        np.save(args.output, image)
    elif not cv2.imwrite(args.output, image):
        raise PolarstripeError(f"output {args.output!r}: OpenCV could not write it")
    meta = frame.metadata
    when = f", device time {meta['device_stamp_ns']} ns" if "device_stamp_ns" in meta else ""
    ident = f", frame {meta['frame_id']}" if "frame_id" in meta else ""
    fmt = meta.get("pixel_format", image.dtype.name)
    print(f"{args.output}: {image.shape[1]}x{image.shape[0]} {fmt} ({frame.bit_depth} bits), exposure "
          f"{frame.exposure_s * 1e6:g} µs, gain {frame.gain:g}{ident}{when} from {cam.name}")
    return 0


def run_fake(args: argparse.Namespace) -> int:
    aravis = _aravis()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with aravis.FakeGvCamera(args.address, args.serial, args.lost_ratio):
        print(f"GigE Vision fake camera (Aravis Fake {args.serial}) at {args.address}; Ctrl-C ends",
              flush=True)
        stop.wait()
    return 0
