import numpy as np
import pytest
from polarstripe.imaging.composite import RunningComposite, StripeMosaic, delineate_stripe, max_composite
from polarstripe.imaging.validation import ImagingError


def _stripe_frames(h=20, w=40, width=4, background=10, peak=200):
    frames = []
    for k in range(w // width):
        f = np.full((h, w), background, np.uint16)
        f[:, k * width:(k + 1) * width] = peak + k
        frames.append(f)
    return frames


def test_running_max_min_equal_plain_reductions():
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 4096, (16, 24), dtype=np.uint16) for _ in range(9)]
    comp = RunningComposite((16, 24), np.uint16, track_argmax=True)
    for f in frames:
        comp.add(f, angle_deg=30.0)
    out = comp.result(30.0 + 180.0)  # angles are modulo 180
    stack = np.stack(frames)
    np.testing.assert_array_equal(out.maximum.data, stack.max(axis=0))
    np.testing.assert_array_equal(out.minimum.data, stack.min(axis=0))
    np.testing.assert_array_equal(out.argmax, stack.argmax(axis=0))
    assert out.n_frames == 9


def test_saturated_pixels_are_masked():
    frames = _stripe_frames()
    frames[3][5, 13] = 4095
    ci = max_composite(frames, saturation=4095)
    assert ci.mask[5, 13] and ci.mask.sum() == 1


def test_memory_does_not_grow_with_frames():
    comp = RunningComposite((8, 8), np.uint16)
    for f in _stripe_frames(8, 8, 2):
        comp.add(f, None)
    held = [comp._max[None], comp._min[None]]
    for f in _stripe_frames(8, 8, 1):
        comp.add(f, None)
    assert comp._max[None] is held[0] and comp._min[None] is held[1]


def test_angles_kept_apart():
    comp = RunningComposite((2, 2), np.float64)
    comp.add(np.ones((2, 2)), 0.0)
    comp.add(np.full((2, 2), 5.0), 90.0)
    assert comp.result(0.0).maximum.max() == 1.0 and comp.result(90.0).maximum.max() == 5.0
    with pytest.raises(ImagingError, match="no frames were added at 45"):
        comp.result(45.0)


def test_frame_shape_and_dtype_mismatch():
    comp = RunningComposite((4, 4), np.uint16)
    with pytest.raises(ImagingError, match="frame: shape"):
        comp.add(np.zeros((4, 5), np.uint16))
    with pytest.raises(ImagingError, match="frame: dtype float64"):
        comp.add(np.zeros((4, 4)))
    with pytest.raises(ImagingError, match="empty stack"):
        max_composite([])


def test_delineation_finds_the_stripe_under_noise_and_backscatter():
    rng = np.random.default_rng(5)
    h, w = 30, 60
    frame = 100.0 + 2.0 * np.arange(w)[None, :] * np.ones((h, 1))  # smooth backscatter ramp
    frame[:, 21:27] += 300.0
    frame += rng.normal(0, 3, frame.shape)
    mask = delineate_stripe(frame)
    # the Sobel edge lands on the stripe border, so allow one pixel either side
    assert not mask[:, :20].any() and not mask[:, 28:].any()
    assert mask[:, 22:26].all()


def test_delineation_rejects_flat_frame():
    frame = np.random.default_rng(0).normal(100, 1, (10, 30))
    assert not delineate_stripe(frame, min_gradient=50.0).any()


def test_mosaic_rebuilds_the_scene():
    h, w, width = 12, 36, 6
    scene = np.linspace(50, 400, w)[None, :] * np.ones((h, 1))
    mosaic = StripeMosaic((h, w))
    for k in range(w // width):
        f = np.full((h, w), 5.0)
        f[:, k * width:(k + 1) * width] = scene[:, k * width:(k + 1) * width]
        mosaic.add(f)
    out = mosaic.result()
    # interior pixels of every stripe are recovered exactly
    for k in range(w // width):
        cols = slice(k * width + 1, (k + 1) * width - 1)
        assert not out.mask[:, cols].any()
        np.testing.assert_allclose(out[:, cols], scene[:, cols])


def test_reset_starts_a_new_scan_in_the_same_buffers():
    comp = RunningComposite((4, 4), np.uint16)
    comp.add(np.full((4, 4), 900, np.uint16), 0.0)
    held = comp._max[0.0]
    comp.reset()
    assert comp.angles == []
    comp.add(np.full((4, 4), 7, np.uint16), 0.0)
    comp.add(np.full((4, 4), 3, np.uint16), 0.0)
    out = comp.result(0.0)
    assert comp._max[0.0] is held
    assert out.maximum.max() == 7 and out.minimum.min() == 3 and out.n_frames == 2
