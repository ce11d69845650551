"""``polarstripe bench fidelity --threads N``: how the model scales with threads (sim/threads.py), two ways,
each against one thread in the same run:

* **a frame** — one stripe frame with N model threads (the banded kernels, the FFTs, OpenCV);
* **a scan's frames** — 2N stripe frames (stripe 10/30 onwards) one after another on one thread, against
  the same frames N at a time (:func:`polarstripe.sim.render.render_each`, one model thread each): what a
  scan, the simulator node and the planner do.

Wall seconds (best of ``repeat``) and process CPU seconds; the frames are the same for any count.
"""

from __future__ import annotations

import time

import numpy as np
from polarstripe.sim.render import render_components, render_each
from polarstripe.sim.threads import set_threads

FRAME = "stripe:14/30"


def _best(fn, repeat: int) -> tuple[float, float]:
    """(best wall seconds, process CPU seconds of that run)."""
    best = (np.inf, np.inf)
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        best = min(best, (time.perf_counter() - w, time.process_time() - c))
    return best


def scaling(scene, threads: int, repeat: int, levels=("preview", "standard")) -> dict:
    """Per level: ``frame`` and ``frames`` (see the module docstring), each with ``wall_s_1``,
    ``wall_s_N``, ``cpu_s_1``, ``cpu_s_N`` and ``speedup`` (wall at one thread ÷ wall at N)."""
    out = {}
    patterns = [f"stripe:{k}/30" for k in range(10, 10 + 2 * threads)]
    for level in levels:
        frame, frames = {}, {"count": len(patterns)}
        for n in (1, threads):
            set_threads(n)
            render_components(scene, FRAME, level)                                  # warm
            frame[f"wall_s_{n}"], frame[f"cpu_s_{n}"] = _best(
                lambda lv=level: render_components(scene, FRAME, lv), repeat)
            frames[f"wall_s_{n}"], frames[f"cpu_s_{n}"] = _best(
                lambda lv=level: render_each(scene, patterns, lv), repeat)
        for row in (frame, frames):
            row["speedup"] = row["wall_s_1"] / row[f"wall_s_{threads}"]
        out[level] = {"frame": frame, "frames": frames}
    set_threads(1)
    return out


def describe(th: dict) -> str:
    """The table's lines for :func:`scaling`'s result (``th``: count, available, levels)."""
    k = f"_{th['count']}"
    lines = [f"threads: {th['count']} (this process may use {th['available']} cores); wall clock, one thread "
             f"vs {th['count']} (process CPU in brackets):"]
    for lv, r in th["levels"].items():
        a, b = r["frame"], r["frames"]
        lines.append(f"  {lv}: one stripe frame {a['wall_s_1']:.3f} vs {a['wall_s' + k]:.3f} s = "
                     f"{a['speedup']:.2f}x ({a['cpu_s_1']:.3f} vs {a['cpu_s' + k]:.3f} s); {b['count']} "
                     f"frames {b['wall_s_1']:.3f} vs {b['wall_s' + k]:.3f} s = {b['speedup']:.2f}x "
                     f"({b['cpu_s_1']:.3f} vs {b['cpu_s' + k]:.3f} s)")
    return "\n".join(lines)
