"""``polarstripe bench compositor``: per-frame cost of the running max/min reductions.

Measured in one run, for 1280×1024 uint16 frames (the target is ≤ 2 ms per frame): the compositor's
``RunningComposite.add`` (max + min, and with the argmax stripe index), beside the physical limit (a memcpy of
the frame into a preallocated array) and the best peers (a bare ``np.maximum`` into a preallocated array,
OpenCV's ``cv2.max``/``cv2.min``), and the naive stack-then-reduce whose memory grows with the stripes.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from polarstripe.imaging.composite import RunningComposite


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--width", type=int, default=1280, help="frame width in pixels (default 1280)")
    parser.add_argument("--height", type=int, default=1024, help="frame height in pixels (default 1024)")
    parser.add_argument("--frames", type=int, default=60, help="frames per scan (default 60: 30 stripes × 2 "
                        "analyzer angles)")
    parser.add_argument("--repeats", type=int, default=5, help="scans timed; the median is reported")


def _time_per_frame(fn, frames, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(frames)
        times.append((time.perf_counter() - t0) / len(frames))
    return float(np.median(times))


def run(width: int, height: int, n_frames: int, repeats: int) -> dict:
    rng = np.random.default_rng(0)
    distinct = [rng.integers(0, 4096, (height, width), dtype=np.uint16) for _ in range(8)]
    frames = [distinct[k % len(distinct)] for k in range(n_frames)]
    shape = (height, width)
    buf = np.empty(shape, np.uint16)
    buf2 = np.empty(shape, np.uint16)

    def memcpy(fs):
        for f in fs:
            np.copyto(buf, f)

    def np_max_only(fs):
        np.copyto(buf, fs[0])
        for f in fs[1:]:
            np.maximum(buf, f, out=buf)

    def np_max_min(fs):
        np.copyto(buf, fs[0])
        np.copyto(buf2, fs[0])
        for f in fs[1:]:
            np.maximum(buf, f, out=buf)
            np.minimum(buf2, f, out=buf2)

    comps = {flag: RunningComposite(shape, np.uint16, saturation=4095, track_argmax=flag) for flag in (0, 1)}

    def composite(fs, track_argmax=False):
        comp = comps[int(track_argmax)]  # one compositor reused scan after scan, as the node does
        comp.reset()
        for k, f in enumerate(fs):
            comp.add(f, angle_deg=0.0 if k % 2 == 0 else 90.0)
        comp.result(0.0)

    rows = {
        "memcpy (physical limit)": _time_per_frame(memcpy, frames, repeats),
        "np.maximum in place (peer)": _time_per_frame(np_max_only, frames, repeats),
        "np.maximum + np.minimum in place (peer)": _time_per_frame(np_max_min, frames, repeats),
    }
    try:
        import cv2

        def cv_max_min(fs):
            np.copyto(buf, fs[0])
            np.copyto(buf2, fs[0])
            for f in fs[1:]:
                cv2.max(buf, f, dst=buf)
                cv2.min(buf2, f, dst=buf2)

        rows["cv2.max + cv2.min in place (peer)"] = _time_per_frame(cv_max_min, frames, repeats)
    except ImportError:  # pragma: no cover - opencv is a dependency
        pass
    rows["RunningComposite.add (max + min)"] = _time_per_frame(composite, frames, repeats)
    rows["RunningComposite.add + argmax"] = _time_per_frame(lambda fs: composite(fs, True), frames, repeats)
    rows["naive: np.stack then max/min (memory grows)"] = _time_per_frame(
        lambda fs: (np.stack(fs).max(axis=0), np.stack(fs).min(axis=0)), frames, max(1, repeats // 2))
    limit = rows["memcpy (physical limit)"]
    peers = [v for k, v in rows.items() if "(peer)" in k and "+" in k]
    best_peer = min(peers)
    ours = rows["RunningComposite.add (max + min)"]
    return {
        "frame": {"width": width, "height": height, "dtype": "uint16", "frames_per_scan": n_frames},
        "ms_per_frame": {k: v * 1e3 for k, v in rows.items()},
        "target_ms": 2.0,
        "meets_target": ours * 1e3 <= 2.0,
        "ratio_to_memcpy": ours / limit,
        "ratio_to_best_peer": ours / best_peer,
    }


def main(args: argparse.Namespace) -> int:
    res = run(args.width, args.height, args.frames, args.repeats)
    if args.json:
        print(json.dumps(res))
        return 0
    f = res["frame"]
    print(f"compositor: {f['width']}x{f['height']} {f['dtype']}, {f['frames_per_scan']} frames per scan, "
          f"median of {args.repeats} scans")
    print(f"{'method':<46} {'ms/frame':>9} {'× memcpy':>9}")
    limit = res["ms_per_frame"]["memcpy (physical limit)"]
    for name, ms in res["ms_per_frame"].items():
        print(f"{name:<46} {ms:9.3f} {ms / limit:9.2f}")
    print(f"target ≤ {res['target_ms']} ms/frame: {'met' if res['meets_target'] else 'NOT met'}; "
          f"running max+min is {res['ratio_to_memcpy']:.2f}× memcpy and {res['ratio_to_best_peer']:.2f}× the "
          f"best peer")
    return 0
