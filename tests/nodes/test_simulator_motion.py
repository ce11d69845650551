"""The simulator node moving the rig during scans (params velocity_m_s, fps; nodes/simulator_motion.py)."""

import numpy as np
import pytest
from polarstripe.msgs import RenderRequest, ScanEvent
from polarstripe.nodes.simulator import Simulator
from polarstripe.runtime.params import ParamError
from polarstripe.runtime.testing import NodeHarness


def sim(**params):
    return NodeHarness(Simulator, name="simulator", namespace="/rig",
                       params={"resolution": "48x36", "seed": 3, "render_ahead": False, **params})


def stripe_scan(h, n=3, scan_id=1):
    """A stripes scan of n frames (no analyzer): the truth published at its start and its frames."""
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="start", method="stripes", stripes=n))
    frames = [h.call("simulator/render", RenderRequest(pattern=f"stripe:{k}/{n}", analyzer=False,
                                                       scan_id=scan_id, step=k)).image for k in range(n)]
    h.deliver("emitter/scan", ScanEvent(scan_id=scan_id, event="done", method="stripes", stripes=n))
    return h.published("simulator/truth")[-1], frames


def test_zero_velocity_is_the_rig_at_rest_bit_for_bit():
    truth, frames = stripe_scan(sim())
    truth0, frames0 = stripe_scan(sim(velocity_m_s=[0.0, 0.0, 0.0], fps=7.0))
    for a, b in zip(frames, frames0, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(truth.images["S"], truth0.images["S"])


def test_a_moving_rig_passes_the_scenes_pose_mid_scan():
    # 3 frames at 0, 1/30, 2/30 s: the middle one is taken at the scene's pose (offset v·0), the others
    # 0.1 m/s × 1/30 s = 3.3 mm either side; the truth is the scene's pose whatever the speed
    truth, rest = stripe_scan(sim())
    truth_v, moving = stripe_scan(sim(velocity_m_s=[0.1, 0.0, 0.0]))
    np.testing.assert_array_equal(moving[1], rest[1])
    for k in (0, 2):
        assert not np.array_equal(moving[k], rest[k])
    np.testing.assert_array_equal(truth_v.images["S"], truth.images["S"])


def test_the_frames_poses_follow_the_scan_and_the_drives_move_time():
    # polarized stripes at 0 and 90 deg, 2 stripes a pass, 10 fps, a drive of 100 deg/s settling in 0.05 s:
    # frames at 0, 0.1, then 0.2 + 0.9 + 0.05 = 1.15 and 1.25 s; mid-scan 0.625 s
    h = sim(velocity_m_s=[0.0, 0.2, 0.0], fps=10.0, drive_speed_counts_s=100_000.0, counts_per_deg=1000.0,
            drive_settle_s=0.05)
    h.deliver("emitter/scan", ScanEvent(scan_id=7, event="start", method="polarized_stripes", stripes=2,
                                        analyzer_deg=[0.0, 90.0]))
    for step, t in enumerate((0.0, 0.1, 1.15, 1.25)):
        pose = h.node.motion.scene_at(h.node.scene, 7, step).camera.position
        np.testing.assert_allclose(pose, [0.0, 0.2 * (t - 0.625), 0.0], atol=1e-12)
    h.deliver("emitter/scan", ScanEvent(scan_id=7, event="done", method="polarized_stripes", stripes=2))
    assert h.node.motion.scene_at(h.node.scene, 7, 0) is h.node.scene  # after the scan: at rest


def test_a_scan_of_k_sheets_per_frame_is_timed_by_its_frames():
    # 7 stripes, 3 sheets a frame: ceil(7/3) = 3 frames at 0, 0.1, 0.2 s (10 fps), mid-scan 0.1 s
    h = sim(velocity_m_s=[1.0, 0.0, 0.0], fps=10.0)
    h.deliver("emitter/scan", ScanEvent(scan_id=2, event="start", method="stripes", stripes=7, sheets=3))
    for step, t in enumerate((0.0, 0.1, 0.2)):
        pose = h.node.motion.scene_at(h.node.scene, 2, step).camera.position
        np.testing.assert_allclose(pose, [t - 0.1, 0.0, 0.0], atol=1e-12)
    assert h.node.motion.scene_at(h.node.scene, 2, 3) is h.node.scene  # no fourth frame


def test_each_pose_is_rendered_anew_and_the_second_angle_at_rest_is_not():
    # polarized flood: two frames of the same pattern. At rest the second analyzer angle reuses the components
    # of the auto exposure's flood (one render in all); moving, each frame is a pose of its own (1 + 2)
    for velocity, renders in (([0.0, 0.0, 0.0], 1), ([0.0, 0.0, 0.05], 3)):
        h = sim(velocity_m_s=velocity)
        h.deliver("emitter/scan", ScanEvent(scan_id=1, event="start", method="polarized_flood",
                                            analyzer_deg=[0.0, 90.0]))
        for step in (0, 1):
            h.call("simulator/render", RenderRequest(pattern="flood", scan_id=1, step=step))
        assert h.node.stats["renders"] == renders


@pytest.mark.parametrize("params, why", [
    ({"velocity_m_s": [0.1, 0.0]}, "velocity_m_s must be a list of 3 numbers"),
    ({"fps": 0.0}, "fps must be a positive number"),
])
def test_bad_motion_params_are_refused_before_anything_starts(params, why):
    with pytest.raises(ParamError, match=why):
        sim(**params)
