"""The one-value checks behind every scene key: each names its key and rejects what it must."""

import math

import pytest
from polarstripe.sim.scene_checks import (
    SceneError,
    check_pose,
    finite,
    parse_size,
    positive,
    resolution,
    unit_interval,
    vec3,
)


def test_numbers():
    assert finite("k", "2.5") == 2.5 and positive("k", 0, allow_zero=True) == 0.0
    assert unit_interval("k", 1) == 1.0 and vec3("k", [1, 2, 3]) == (1.0, 2.0, 3.0)
    for check, value in ((finite, True), (finite, math.nan), (finite, "x"), (finite, math.inf),
                         (positive, 0.0), (positive, -1e-300), (unit_interval, 1.0000001), (vec3, [1, 2]),
                         (vec3, [1, 2, math.nan])):
        with pytest.raises(SceneError, match="the.key"):
            check("the.key", value)


def test_sizes():
    assert parse_size(" 640X480 ") == (640, 480) and resolution("r", [3, 2]) == (3, 2)
    for text in ("640", "0x480", "640x-1", "axb", "64.0x48"):
        with pytest.raises(SceneError, match="WxH"):
            parse_size(text)
    for value in ([3], [3, 0], [3.0, 2], [True, 2]):
        with pytest.raises(SceneError, match="cam.res"):
            resolution("cam.res", value)


def test_poses():
    assert check_pose("camera", (0, 0, 0), (0, 0, 1), (0, 1, 0), 60) == ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0),
                                                                         (0.0, 1.0, 0.0), 60.0)
    for args, text in ((((0, 0, 0), (0, 0, 0), (0, 1, 0), 60), "look_at must differ"),
                       (((0, 0, 0), (0, 0, 1), (0, 0, 2), 60), "up must not be parallel"),
                       (((0, 0, 0), (0, 0, 1), (0, 1, 0), 179), "fov_deg")):
        with pytest.raises(SceneError, match=text):
            check_pose("camera", *args)
