"""The model's threads: a frame is bit-identical whatever the thread count (sim/threads.py)."""

import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from polarstripe.sim import geometry_cache, threads
from polarstripe.sim.render import render_components, render_each
from polarstripe.sim.scene import load_scene


@pytest.fixture
def restore_threads():
    before = threads.threads()
    yield
    threads.set_threads(before)


@pytest.mark.parametrize("pattern,fidelity,size", [("stripe:5/12", "standard", (160, 120)),
                                                   ("checker:16:3", "standard", (96, 72)),
                                                   ("flood", "preview", (640, 480))])
def test_frames_identical_for_any_thread_count(restore_threads, pattern, fidelity, size):
    scene = load_scene(None)
    scene = scene.replace(camera=scene.camera.resized(size))
    frames = []
    for n in (1, 2, 3):
        threads.set_threads(n)
        c = render_components(scene, pattern, fidelity)
        frames.append(np.stack([c.D, c.A, c.B, c.Bq, c.Bu]))
    assert np.all(frames[0][2] > 0)
    for other in frames[1:]:
        assert np.array_equal(frames[0], other)


def test_bands_cover_every_item_once_and_respect_starts(restore_threads):
    threads.set_threads(3)
    seen = np.zeros(10_000, int)
    bands = []

    def run(a, b):
        seen[a:b] += 1
        bands.append((a, b))

    starts = np.array([0, 10, 4000, 4001, 9000])
    threads.in_bands(seen.size, run, min_size=1000, starts=starts)
    assert np.all(seen == 1)
    assert len(bands) > 1 and all(a in starts for a, _ in bands)


def test_bad_thread_count_is_refused(restore_threads):
    with pytest.raises(ValueError, match="threads must be"):
        threads.set_threads(-1)
    assert threads.set_threads(0) == threads.available()


_FORK_AFTER_RENDER = """
import multiprocessing, sys
import numpy as np
from polarstripe.sim import threads
from polarstripe.sim.render import render_components
from polarstripe.sim.scene import load_scene

def render_b(scene):
    return render_components(scene, "stripe:3/8", "standard").B

if __name__ == "__main__":
    threads.set_threads(2)
    scene = load_scene(None)
    scene = scene.replace(camera=scene.camera.resized((96, 72)))
    here = render_b(scene)                      # the parent's pool exists now
    with multiprocessing.get_context("fork").Pool(1) as pool:
        there = pool.apply_async(render_b, (scene,)).get(timeout=100)
    sys.exit(0 if np.array_equal(here, there) else 3)
"""


def test_a_forked_child_renders_with_its_own_pool(tmp_path):
    # Forked from a process of its own: a test worker's other threads (a numba compile, a bus) may hold
    # locks at the fork that no fork handler can release; that is fork's contract, not the model's.
    script = tmp_path / "fork_after_render.py"
    script.write_text(_FORK_AFTER_RENDER)
    try:
        done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=150)
    except subprocess.TimeoutExpired:
        pytest.fail("the forked child hung (its first band waited on the parent's pool)")
    assert done.returncode == 0, done.stderr[-2000:]


def test_a_forked_child_forgets_what_other_threads_were_making():
    import os

    key = (object(), "x")
    geometry_cache._making[key] = threading.Event()         # as if a parent thread were making it
    lock = geometry_cache._lock
    try:
        with lock:                                          # ... and held the lock at the fork
            pid = os.fork()
        if pid == 0:                                        # the child: nothing in flight, a free lock
            os._exit(0 if not geometry_cache._making and geometry_cache._lock.acquire(timeout=5) else 1)
        _, status = os.waitpid(pid, 0)
    finally:
        geometry_cache._making.pop(key, None)
    assert os.waitstatus_to_exitcode(status) == 0


def test_frames_in_parallel_are_the_frames_one_by_one(restore_threads):
    scene = load_scene(None)
    scene = scene.replace(camera=scene.camera.resized((96, 72)))
    patterns = [f"stripe:{k}/6" for k in range(4)]
    threads.set_threads(1)
    alone = [render_components(scene, p, "standard") for p in patterns]
    threads.set_threads(2)
    together = render_each(scene, patterns, "standard")
    for a, b in zip(alone, together, strict=True):
        assert np.array_equal(np.stack([a.D, a.A, a.B, a.Bq, a.Bu]), np.stack([b.D, b.A, b.B, b.Bq, b.Bu]))
    seen = threads.each_frame(lambda _: (threads.threads(), threading.current_thread().name), range(3))
    assert all(n == 1 and name.startswith("frame") for n, name in seen)    # one model thread per frame


def test_a_cached_value_two_threads_ask_for_is_made_once():
    made = []

    def make():
        made.append(1)
        time.sleep(0.2)
        return np.arange(3.0)

    scene = load_scene(None)
    scene = scene.replace(camera=scene.camera.resized((11, 7)))        # a scene no other test caches
    with ThreadPoolExecutor(2) as pool:
        a, b = pool.map(lambda _: geometry_cache.cached(scene, "x", make), range(2))
    assert len(made) == 1 and a is b and not a.flags.writeable
