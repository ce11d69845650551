"""Gray code patterns: the images OpenCV's GrayCodePattern generates, in its order."""

import cv2
import numpy as np
import pytest
from polarstripe.msgs.patterns import PatternError, gray_bits, gray_code, gray_lit, parse, xor_code


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


def test_an_xor_pattern_is_its_gray_bit_xor_the_columns_base_bit():
    rows, cols = np.mgrid[0:64, 0:256] + 0.5
    j, i = cols.astype(int), rows.astype(int)
    g_col, g_row = j ^ (j >> 1), i ^ (i >> 1)
    for text, bit in (("gray:6:col:0:xor3", ((g_col >> 6) ^ (g_col >> 3)) & 1),
                      ("gray:2:row:1:xor3", 1 - (((g_row >> 2) ^ (g_col >> 3)) & 1))):
        spec = parse(text)
        assert str(spec) == text and spec.xor == 3
        np.testing.assert_array_equal(gray_lit(spec, cols, rows), bit == 1, err_msg=text)


@pytest.mark.parametrize("text", ["gray:3:col:0:xor3", "gray:1:col:0:xor31", "gray:1:col:0:xor"])
def test_a_bad_xor_base_is_one_error(text):
    with pytest.raises(PatternError, match="xor|is not flood"):
        parse(text)


@pytest.mark.parametrize("width, base", [(256, 3), (1024, 5), (300, 2)])
def test_the_xor_codes_column_patterns_change_no_faster_than_half_the_base_run(width, base):
    """Every pattern of the XOR code keeps its lit state over runs of at least 2^base columns (Gupta et al.:
    the runs of the base's stripes, 2^(base+1), split at most once), and it is its inverse's complement."""
    code = xor_code(width, 16, base)
    assert [(p.axis, p.index, p.inverse) for p in code] == [(p.axis, p.index, p.inverse)
                                                            for p in gray_code(width, 16)]
    cols = np.arange(width) + 0.5
    for p, q in zip(code[::2], code[1::2], strict=True):
        assert q.inverse and not p.inverse and q.xor == p.xor
        for row in (0.5, 5.5):
            lit = gray_lit(p, cols, np.full(width, row))
            assert not np.any(lit & gray_lit(q, cols, np.full(width, row)))
            starts = np.flatnonzero(np.diff(lit.astype(int))) + 1
            runs = np.diff(starts)                       # the runs between two changes (not the ends)
            shortest = 2 ** min(base, p.index) if p.axis == "col" else 2 ** base
            assert runs.size == 0 or runs.min() >= shortest
