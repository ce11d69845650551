"""Gray code patterns: the images OpenCV's GrayCodePattern generates, in its order."""

import cv2
import numpy as np
import pytest
from polarstripe.msgs.patterns import gray_bits, gray_code, gray_lit, parse


@pytest.mark.parametrize("width, height", [(20, 6), (256, 192), (300, 200), (1024, 768)])
def test_gray_code_is_opencvs_generate(width, height):
    ok, images = cv2.structured_light.GrayCodePattern.create(width, height).generate()
    specs = gray_code(width, height)
    assert ok and len(specs) == len(images) == 2 * (gray_bits(width) + gray_bits(height))
    rows, cols = np.mgrid[0:height, 0:width] + 0.5          # pattern pixel centres
    for spec, image in zip(specs, images, strict=True):
        assert parse(str(spec)) == spec
        np.testing.assert_array_equal(gray_lit(spec, cols, rows), image > 0, err_msg=str(spec))


def test_gray_bits_is_ceil_log2():
    assert [gray_bits(n) for n in (1, 2, 3, 4, 5, 1024, 1025)] == [0, 1, 2, 2, 3, 10, 11]


def test_gray_pattern_and_inverse_light_complementary_pixels():
    a, b = parse("gray:2:col:0"), parse("gray:2:col:1")
    cols = np.arange(64) + 0.5
    assert not np.any(gray_lit(a, cols, 0 * cols) & gray_lit(b, cols, 0 * cols))
    assert np.all(gray_lit(a, cols, 0 * cols) | gray_lit(b, cols, 0 * cols))
