"""Gray code patterns through the rig: the Pattern message carries them, the display draws OpenCV's images,
the emitter shows them, a serial trigger box refuses them in one line."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from polarstripe.msgs import Pattern
from polarstripe.msgs.codec import pack, unpack
from polarstripe.msgs.patterns import gray_code, xor_code
from polarstripe.nodes.drivers.display import NullDisplay, render_pattern
from polarstripe.nodes.drivers.errors import DriverValueError
from polarstripe.nodes.drivers.serial_trigger import pattern_command


@pytest.mark.parametrize("size", [(16, 8), (20, 12)])
def test_display_draws_opencvs_gray_code_images(size):
    w, h = size
    ok, images = cv2.structured_light.GrayCodePattern.create(w, h).generate()
    assert ok and len(images) == len(gray_code(w, h))
    for spec, ref in zip(gray_code(w, h), images, strict=True):
        drawn = render_pattern(str(spec), w, h)
        assert np.array_equal(drawn, ref), str(spec)


def test_display_draws_the_xor_code_as_opencvs_images_xor_the_base():
    w, h = 20, 12
    ok, images = cv2.structured_light.GrayCodePattern.create(w, h).generate()
    by = {(p.axis, p.index, p.inverse): img for p, img in zip(gray_code(w, h), images, strict=True)}
    for spec in xor_code(w, h, 1):
        ref = by[(spec.axis, spec.index, spec.inverse)]
        if spec.xor >= 0:
            ref = ref ^ by[("col", spec.xor, False)]
        assert np.array_equal(render_pattern(str(spec), w, h), ref), str(spec)


def test_pattern_message_carries_a_gray_pattern_over_the_wire():
    msg = Pattern.of("gray:3:row:1:xor2", scan_id=2, step=5)
    back = unpack(pack(msg))
    assert (back.kind, back.index, back.axis, back.inverse, back.xor) == ("gray", 3, "row", True, 2)
    assert str(back.spec()) == "gray:3:row:1:xor2"
    assert str(Pattern.of("stripe:2/4").spec()) == "stripe:2/4"


def test_emitter_shows_a_gray_pattern():
    from polarstripe.nodes.emitter import Emitter
    from polarstripe.runtime.testing import NodeHarness

    h = NodeHarness(Emitter, name="emitter", namespace="/rig", params={"display_options": {
                                                                        "width": 16, "height": 8}})
    ack = h.call("emitter/show", Pattern.of("gray:0:col:0"))
    assert ack.ok, ack.detail
    assert isinstance(h.node.display, NullDisplay)
    assert str(h.node.display.current) == "gray:0:col:0"
    assert np.array_equal(h.node.display.image()[0], np.tile([0, 255, 255, 0], 4))
    assert [str(p.spec()) for p in h.published("emitter/pattern")] == ["gray:0:col:0"]


def test_serial_trigger_box_refuses_gray_in_one_line():
    with pytest.raises(DriverValueError, match="Gray code needs a projector"):
        pattern_command(Pattern.of("gray:1:col:0").spec())
    assert pattern_command(Pattern.of("stripe:1/3").spec()) == "PAT STRIPE 1 3"
