"""The calibrator node through the harness (services answered by the test): the order of what it asks for,
and a board never seen is one ERROR line, exit status 1 and the previous file untouched."""

from __future__ import annotations

import numpy as np
from polarstripe.imaging.structured_light import calibration_code
from polarstripe.msgs import Ack, Frame
from polarstripe.nodes.rig_calibrator import SCAN_ID_BASE, RigCalibrator
from polarstripe.runtime.testing import NodeHarness


def test_a_board_never_seen_fails_cleanly_and_leaves_the_previous_file(tmp_path):
    out = tmp_path / "rig.yaml"
    out.write_text("previous\n")
    h = NodeHarness(RigCalibrator, name="calibrator", namespace="/rig",
                    params={"out": str(out), "projector": "16x8", "poses": 3, "board": "4x3"})
    shown, triggers, moves, mounts = [], [], [], []

    def trigger(req):
        triggers.append((req.scan_id, req.step, req.pattern))
        level = 1000 if req.pattern == "flood" else 100  # a lit, featureless wall
        h.queue("camera/frame", Frame(image=np.full((24, 32), level, np.uint16), exposure_s=0.01,
                                      pattern=req.pattern, scan_id=req.scan_id, step=req.step))
        return Ack(ok=True)

    h.on_call("emitter/show", lambda req: shown.append(str(req.spec())) or Ack(ok=True))
    h.on_call("camera/trigger", trigger)
    h.on_call("camera/analyzer", lambda req: mounts.append(req.inserted) or Ack(ok=True))
    h.on_call("simulator/target", lambda req: moves.append(1) or Ack(ok=True, detail="pose"))
    h.node.run()
    assert h.node.exit_code == 1
    errors = [text for level, text in h.logs if level == "ERROR"]
    assert len(errors) == 1 and "0 usable poses of 3" in errors[0] and "not seen" in errors[0], errors
    assert out.read_text() == "previous\n"
    tags = ["flood", "off", *(str(g) for g in calibration_code(16, 8))]
    assert mounts == [False] and len(moves) == 3
    assert shown == tags * 3 + ["off"]
    assert triggers == [(SCAN_ID_BASE + k, i, t) for k in range(3) for i, t in enumerate(tags)]
