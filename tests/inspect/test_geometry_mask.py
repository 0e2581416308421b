"""polygon_mask: parts beyond the field add nothing and never overflow OpenCV's fixed point."""

import warnings

import numpy as np

from smdinspect.inspect._geometry import polygon_mask


def test_polygons_outside_the_image_or_not_finite_add_nothing():
    inside = np.array([[10.0, 10], [20, 10], [20, 20], [10, 20]])
    far = np.array([[1e7, 1e7], [1e7 + 5, 1e7], [1e7 + 5, 1e7 + 5]])  # x 256 overflows int32
    left = np.array([[-60.0, 10], [-40, 10], [-40, 20]])
    nan = np.array([[np.nan, 1.0], [3, 1], [3, 4]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "invalid value encountered in cast"
        only = polygon_mask(inside, (50, 50))
        assert np.array_equal(polygon_mask([inside, far, left, nan], (50, 50)), only)
        assert not polygon_mask([far, left, nan], (50, 50)).any()
    assert 100 <= only.sum() <= 121  # the 10 x 10 px square (OpenCV fills its boundary too)
    edge = np.array([[-5.0, -5], [5, -5], [5, 5], [-5, 5]])  # partly inside: kept
    assert polygon_mask(edge, (50, 50))[:5, :5].all()
