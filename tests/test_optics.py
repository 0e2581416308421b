"""Thin-lens optics: formulas checked against hand computation."""

import math

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.optics import (
    Optics,
    blur_circle_mm,
    focus_height_mm,
    gaussian_psf,
    image_distance_mm,
    recommend_sweep,
)


def test_thin_lens_law():
    f, u = 35.0, 80.0
    v = image_distance_mm(f, u)
    assert 1 / f == pytest.approx(1 / u + 1 / v, rel=1e-12)
    with pytest.raises(InputError, match="object_distance_mm must be > focal_length_mm"):
        image_distance_mm(50.0, 40.0)


@pytest.mark.parametrize("sigma", [0.0, 0.4, 1.0, 3.3, 7.0])
def test_psf_integrates_to_one(sigma):
    k = gaussian_psf(sigma)
    assert k.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.all(k >= 0)
    r = k.shape[0] // 2
    if sigma > 0.8:  # second moment along x matches sigma (the sampled kernel is exact-ish)
        x = np.arange(-r, r + 1)
        var = float((k.sum(axis=0) * x**2).sum())
        assert math.sqrt(var) == pytest.approx(sigma, rel=2e-3)


def test_psf_rejects_negative_sigma():
    with pytest.raises(InputError, match="sigma_px must be >= 0; got -1"):
        gaussian_psf(-1.0)


def test_blur_sigma_matches_thin_lens_by_hand():
    o = Optics(focal_length_mm=40.0, magnification=0.5, aperture_mm=20.0,
               pixel_pitch_mm=0.005, k=0.4, sigma0_px=0.0)
    # by hand: v = f(1+m) = 60, d_f = f(1+1/m) = 120; a point 0.3 mm above the focused
    # plane is at u = 119.7
    v, u = 60.0, 119.7
    c = abs(20.0 * v * (1 / 40.0 - 1 / u - 1 / v))
    assert o.sensor_distance_mm == pytest.approx(v)
    assert o.working_distance_mm == pytest.approx(120.0)
    assert float(o.blur_circle_mm(1.3, 1.0)) == pytest.approx(c, rel=1e-12)
    assert float(o.blur_sigma_px(1.3, 1.0)) == pytest.approx(0.4 * c / 0.005, rel=1e-12)
    # in focus: no blur; sigma0 adds in quadrature
    assert float(o.blur_sigma_px(2.0, 2.0)) == pytest.approx(0.0, abs=1e-12)
    o2 = Optics(focal_length_mm=40.0, magnification=0.5, aperture_mm=20.0,
                pixel_pitch_mm=0.005, k=0.4, sigma0_px=0.5)
    s = 0.4 * c / 0.005
    assert float(o2.blur_sigma_px(1.3, 1.0)) == pytest.approx(math.hypot(0.5, s), rel=1e-12)
    # the standalone formula agrees and is symmetric in sign of C
    assert float(blur_circle_mm(u, focal_length_mm=40, aperture_mm=20, sensor_distance_mm=v)) \
        == pytest.approx(c)


def test_default_is_shallow_15um():
    o = Optics()
    assert o.pixel_size_mm == pytest.approx(0.015)
    growth = float(o.blur_sigma_px(0.1, 0.0) - o.blur_sigma_px(0.05, 0.0))
    assert 0.5 <= growth <= 1.0
    assert 0.03 <= o.depth_of_field_mm() <= 0.1


def test_focus_height_formula():
    n = np.arange(5)
    h = focus_height_mm(n, d_mm=102.0, d_f_mm=100.0, step_mm=0.25)
    np.testing.assert_allclose(h, [2.0, 1.75, 1.5, 1.25, 1.0])


def test_magnification_telecentric_vs_ordinary():
    tele = Optics(telecentric=True)
    ordi = Optics(telecentric=False)
    assert np.all(tele.magnification_at([0.0, 1.0, 2.0], 1.0) == tele.magnification)
    m = ordi.magnification_at([0.0, 1.0, 2.0], 1.0)
    # v / u with u = d_f + z - h
    np.testing.assert_allclose(m, 100.0 / np.array([101.0, 100.0, 99.0]))
    assert float(ordi.scale_at(1.0, 1.0)) == pytest.approx(1.0)


def test_depth_of_field_by_hand():
    o = Optics(sigma0_px=0.0)
    c = 0.015
    e = c / (o.aperture_mm * o.sensor_distance_mm)
    dof = 1 / (1 / 100.0 - e) - 1 / (1 / 100.0 + e)
    assert o.depth_of_field_mm() == pytest.approx(dof)
    # at the DOF limits the blur circle is exactly coc
    assert float(o.blur_circle_mm(0.0, 1 / (1 / 100.0 - e) - 100.0)) == pytest.approx(c)


def test_recommend_sweep_covers_range():
    o = Optics()
    plan = recommend_sweep(o, (0.0, 1.6))
    g = o.blur_rate_px_per_mm()
    assert plan.focus_sigma_mm == pytest.approx(1 / (math.sqrt(2) * 2 * math.pi * 0.2 * g))
    assert plan.step_mm == pytest.approx(plan.focus_sigma_mm)
    assert plan.z_mm[0] < -2.5 * plan.step_mm and plan.z_mm[-1] > 1.6 + 2.5 * plan.step_mm
    np.testing.assert_allclose(np.diff(plan.z_mm), plan.step_mm)
    assert len(plan.z_mm) == plan.n_frames
    # a slower lens needs larger steps
    slow = recommend_sweep(Optics(aperture_mm=10.0), (0.0, 1.6))
    assert slow.step_mm > 4 * plan.step_mm


def test_optics_validation_and_roundtrip():
    with pytest.raises(InputError, match="aperture_mm must be > 0; got -2"):
        Optics(aperture_mm=-2)
    with pytest.raises(InputError, match="telecentric must be True or False"):
        Optics(telecentric="yes")
    with pytest.raises(InputError, match="height_range_mm must be finite with lo <= hi"):
        recommend_sweep(Optics(), (1.0, 0.0))
    with pytest.raises(InputError, match="inside the focal length"):
        Optics().blur_sigma_px(60.0, 0.0)
    o = Optics(telecentric=False, aperture_mm=30.0)
    assert Optics.from_dict(o.to_dict()) == o
    assert Optics.for_pixel_size(0.01).pixel_size_mm == pytest.approx(0.01)
