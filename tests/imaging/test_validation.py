"""The input checks every imaging function shares: what passes, and that a refusal names the argument."""

import numpy as np
import pytest
from polarstripe.errors import PolarstripeError
from polarstripe.imaging.validation import (
    ImagingError,
    as_image,
    as_stack,
    finite_array,
    finite_param,
    roi_slices,
    same_dtype,
    same_shape,
)


def test_imaging_error_is_a_value_error_of_the_project():
    assert issubclass(ImagingError, PolarstripeError) and issubclass(ImagingError, ValueError)


def test_as_image_keeps_a_mask_and_refuses_wrong_rank_dtype_or_emptiness():
    m = np.ma.MaskedArray(np.ones((2, 3)), [[1, 0, 0], [0, 0, 0]])
    out = as_image("frame", m)
    assert isinstance(out, np.ma.MaskedArray) and out.mask[0, 0]
    with pytest.raises(ImagingError, match=r"frame: expected 2 dimensions, got shape \(3,\)"):
        as_image("frame", np.ones(3))
    with pytest.raises(ImagingError, match="frame: dtype <U1 is not a real numeric type"):
        as_image("frame", np.array([["a"]]))
    with pytest.raises(ImagingError, match=r"frame: empty array of shape \(0, 4\)"):
        as_image("frame", np.ones((0, 4)))


def test_same_shape_and_dtype_name_the_odd_one():
    assert same_shape(a=np.ones((2, 3)), b=np.zeros((2, 3))) == (2, 3)
    with pytest.raises(ImagingError, match=r"b: shape \(3, 2\) does not match a shape \(2, 3\)"):
        same_shape(a=np.ones((2, 3)), b=np.ones((3, 2)))
    assert same_dtype(a=np.ones(2, np.uint16), b=np.zeros(2, np.uint16)) == np.uint16
    with pytest.raises(ImagingError, match="b: dtype float64 does not match a dtype uint16"):
        same_dtype(a=np.ones(2, np.uint16), b=np.ones(2))


def test_as_stack_from_a_list_or_an_array():
    frames = [np.full((2, 2), k, np.uint16) for k in range(3)]
    stack = as_stack("frames", frames)
    assert stack.shape == (3, 2, 2) and stack[2, 1, 1] == 2
    assert as_stack("frames", np.zeros((1, 2, 2))).shape == (1, 2, 2)
    with pytest.raises(ImagingError, match="frames: empty stack"):
        as_stack("frames", [])
    with pytest.raises(ImagingError, match=r"frames\[1\]: shape \(2, 3\) does not match frames\[0\]"):
        as_stack("frames", [np.zeros((2, 2)), np.zeros((2, 3))])
    with pytest.raises(ImagingError, match=r"frames\[1\]: dtype float64 does not match"):
        as_stack("frames", [np.zeros((2, 2), np.uint16), np.zeros((2, 2))])
    with pytest.raises(ImagingError, match=r"expected a stack of 2-D frames \(k, h, w\), got shape \(2, 2\)"):
        as_stack("frames", np.zeros((2, 2)))


@pytest.mark.parametrize(("value", "kw", "match"), [
    ("x", {}, "'x' is not a number"),
    (float("nan"), {}, "nan is not finite"),
    (0.0, {"low": 0.0, "low_open": True}, r"0.0 is below the allowed range \(> 0.0\)"),
    (2.0, {"high": 1.0}, r"2.0 is above the allowed range \(<= 1.0\)"),
    (1.0, {"high": 1.0, "high_open": True}, r"1.0 is above the allowed range \(< 1.0\)"),
])
def test_finite_param_refusals(value, kw, match):
    with pytest.raises(ImagingError, match="p: " + match):
        finite_param("p", value, **kw)


def test_finite_param_and_array_accept_the_edges():
    assert finite_param("p", "0.5", low=0.0, high=1.0) == 0.5
    assert finite_param("p", 1.0, low=0.0, high=1.0) == 1.0  # closed ends are allowed
    np.testing.assert_array_equal(finite_array("a", [1, 2]), [1.0, 2.0])
    with pytest.raises(ImagingError, match=r"a: 2 value\(s\) are NaN or infinite"):
        finite_array("a", [np.nan, 1.0, np.inf])


def test_roi_slices_rectangles_masks_and_the_whole_frame():
    img = np.arange(12).reshape(3, 4)
    assert img[roi_slices("roi", None, img.shape)].sum() == img.sum()
    assert img[roi_slices("roi", (1, 3, 2, 4), img.shape)].tolist() == [[6, 7], [10, 11]]
    mask = img % 5 == 0
    assert img[roi_slices("roi", mask, img.shape)].tolist() == [0, 5, 10]
    with pytest.raises(ImagingError, match="roi: rectangle rows 2:4, cols 0:1 is empty or outside the 3x4"):
        roi_slices("roi", (2, 4, 0, 1), img.shape)
    with pytest.raises(ImagingError, match="roi: rectangle rows 1:1"):
        roi_slices("roi", (1, 1, 0, 4), img.shape)
    with pytest.raises(ImagingError, match="roi: mask selects no pixels"):
        roi_slices("roi", np.zeros((3, 4), bool), img.shape)
    with pytest.raises(ImagingError, match=r"roi: mask shape \(2, 2\) does not match image shape \(3, 4\)"):
        roi_slices("roi", np.ones((2, 2), bool), img.shape)
    with pytest.raises(ImagingError, match="roi: expected"):
        roi_slices("roi", (0.5, 1, 0, 1), img.shape)
