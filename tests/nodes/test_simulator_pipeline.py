"""The simulator's frames on worker threads (nodes/simulator_pipeline.py): the same frames whether they are
made ahead on two threads or one by one on one, answered in request order, and the loop answers other
services while a frame is being made."""

import numpy as np
import pytest
from polarstripe.msgs import RenderRequest, SimFault
from polarstripe.nodes.simulator import Simulator
from polarstripe.runtime.testing import NodeHarness
from polarstripe.sim import threads


@pytest.fixture(autouse=True)
def restore_threads():
    before = threads.threads()
    yield
    threads.set_threads(before)


def sim(**params):
    return NodeHarness(Simulator, name="simulator", namespace="/rig",
                       params={"resolution": "48x36", "seed": 3, "fidelity": "standard", **params})


def scan(h):
    """Two passes of four stripes (analyzer, then none; step 6 breaks the second pass's prediction), a dark
    frame and a mosaic frame: the images."""
    out = []
    for step in range(8):
        tag = f"stripe:{step % 4}/4"
        req = RenderRequest(pattern=tag, analyzer=step < 4 or step == 6, scan_id=2, step=step)
        f = h.call("simulator/render", req)
        assert (f.step, f.pattern, f.polarizer_deg is None) == (step, tag, not req.analyzer)
        out.append(f.image)
    out.append(h.call("simulator/render", RenderRequest(pattern="off", scan_id=2, step=8)).image)
    out.append(h.call("simulator/render_mosaic", RenderRequest(pattern="stripe:1/4", scan_id=3)).image)
    return out


@pytest.mark.parametrize("batch", [1, 3])
def test_frames_made_ahead_on_two_threads_are_the_frames_made_one_by_one(batch):
    """Made ahead one by one (``render_batch`` 1) or in batches rendered together (3: stripes 1-3 at step
    0, sim/scan_render.py), the frames are those of one thread without ahead, to the bit."""
    one = sim(threads=1, render_ahead=False)
    alone = scan(one)
    two = sim(threads=2, render_batch=batch)
    ahead = scan(two)
    assert two.node.threads == 2 and one.node.threads == 1
    assert len({a.tobytes() for a in alone}) == len(alone)          # every frame differs (pattern, noise)
    for a, b in zip(alone, ahead, strict=True):
        assert np.array_equal(a, b)
    # flood + 4 stripes once each, and the mosaic's stripe again: a source made for the analyzer's frames
    # keeps no (S1, S2)
    assert two.node.stats["renders"] == one.node.stats["renders"] == 6
    assert one.node.stats["made_ahead"] == 0 and two.node.stats["made_ahead"] == 4  # steps 1-3, 5
    assert two.node.sources.together == (3 if batch == 3 else 0) and one.node.sources.together == 0


def test_batches_share_a_model_scene_and_keep_the_order():
    from polarstripe.nodes.simulator_pipeline import FrameJob, batches
    from polarstripe.sim.scene import load_scene
    scene = load_scene(None)
    small = scene.replace(camera=scene.camera.resized((32, 24)))

    def job(k, pose=0, model=scene):
        return FrameJob(f"stripe:{k}/9", (pose,), model, 0.0, None, scene.camera, None, (0, 1, k, k), False)

    jobs = [job(0), job(1), job(2), job(3), job(4, pose=1), job(5, pose=1), job(6, model=None), job(7),
            job(8, model=small)]
    cut = [[j.seed[2] for j in b] for b in batches(jobs, 3)]
    assert cut == [[0, 1, 2], [3], [4, 5], [6], [7], [8]]
    assert [[j.seed[2] for j in b] for b in batches(jobs[:4], 1)] == [[0], [1], [2], [3]]


def test_the_loop_answers_other_services_while_a_frame_is_made_and_frames_come_in_order():
    h = sim(fidelity="preview", faults=["frame_delay 0.4"])
    first = h.request("simulator/render", RenderRequest(pattern="stripe:0/4", step=0))
    ack = h.call("simulator/fault", SimFault(command="camera_lost off"))
    assert ack.ok and not first.done                                  # answered while the frame waits
    second = h.call("simulator/render", RenderRequest(pattern="flood", step=1))
    assert first.done and first.result().step == 0 and second.step == 1
    h.call("simulator/fault", SimFault(command="frame_delay 0"))
    assert h.call("simulator/render", RenderRequest(pattern="flood", step=2)).step == 2


@pytest.mark.parametrize("port", [False, True])
def test_a_frame_source_holds_the_linear_stokes_of_the_backscatter_and_the_object_light(port):
    """The mosaic's (S1, S2) = (Bq + Sq, Bu + Su) of a frame source: without a port (Sq, Su the shared
    zeros; Bq, Bu kept as they are) and behind a camera port of glass (its faces polarize the object
    light)."""
    from polarstripe.nodes.simulator_pipeline import frame_source
    from polarstripe.sim.render import render_components, resolve_fidelity
    from polarstripe.sim.scene import load_scene
    from polarstripe.sim.scene_port import Port
    scene = load_scene(None)
    cam = scene.camera.replace(resolution=(48, 36))
    if port:
        cam = cam.replace(port=Port(distance_m=0.02, thickness_m=0.01, n_glass=1.5, n_water=1.333))
    scene, fid = scene.replace(camera=cam), resolve_fidelity("preview")
    source, comp = frame_source(scene, "stripe:1/4", fid), render_components(scene, "stripe:1/4", fid)
    assert np.any(comp.Sq) == port
    assert np.array_equal(source.s1, comp.Bq + comp.Sq) and np.array_equal(source.s2, comp.Bu + comp.Su)
