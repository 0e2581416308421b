"""Test scenes: known heights, textures, validation."""

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.synth import (
    Scene,
    band_limited_texture,
    cone_scene,
    half_textured_scene,
    slanted_plane_scene,
    staircase_scene,
)


def test_cone_heights():
    s = cone_scene(size_px=101, height_mm=1.2, radius_frac=0.4)
    h = s.height_mm
    assert h[50, 50] == pytest.approx(1.2)
    assert h[0, 0] == 0 and h[50, 0] == 0
    # linear in r: half-way out the cone is at half height
    r_half = 0.5 * 0.4 * 101
    assert h[50, 50 + int(r_half)] == pytest.approx(1.2 * (1 - int(r_half) / (0.4 * 101)), abs=1e-6)
    assert s.name == "cone" and s.meta["height_mm"] == 1.2


def test_staircase_terraces():
    s = staircase_scene(size_px=80, n_steps=4, step_mm=0.15)
    h = s.height_mm
    np.testing.assert_allclose(h[:, 0:20], 0.0)
    np.testing.assert_allclose(h[:, 20:40], 0.15, rtol=1e-6)
    np.testing.assert_allclose(h[:, 60:80], 0.45, rtol=1e-6)
    with pytest.raises(InputError, match="n_steps must be an integer"):
        staircase_scene(size_px=32, n_steps=20)


def test_slanted_plane_rise_and_direction():
    s = slanted_plane_scene(size_px=50, rise_mm=0.7, base_mm=0.1, azimuth_deg=90)
    h = s.height_mm
    # azimuth 90: rises towards +y, i.e. up the image (row 0 is highest)
    assert h[0, 10] == pytest.approx(0.8) and h[-1, 10] == pytest.approx(0.1)
    np.testing.assert_allclose(h[:, 0], h[:, -1])
    x = slanted_plane_scene(size_px=50, rise_mm=0.7)
    assert x.height_mm[5, -1] == pytest.approx(0.7) and x.height_mm[5, 0] == 0


def test_half_textured_right_half_is_flat():
    s = half_textured_scene(size_px=64, flat_albedo=0.4, contrast=0.2)
    a = s.albedo
    assert np.all(a[:, 32:] == np.float32(0.4))
    assert a[:, :32].std() > 0.15
    assert s.meta["textured_cols"] == [0, 32]
    c = half_textured_scene(size_px=64, color=True)
    assert c.albedo.shape == (64, 64, 3) and c.is_color


def test_texture_is_band_limited_and_seeded():
    t = band_limited_texture((128, 128), seed=4, mean=0.5, contrast=0.1, high_cyc_px=0.2)
    assert t.dtype == np.float32
    assert t.mean() == pytest.approx(0.5, abs=0.02) and t.std() == pytest.approx(0.1, rel=0.05)
    np.testing.assert_array_equal(t, band_limited_texture((128, 128), seed=4, mean=0.5,
                                                          contrast=0.1, high_cyc_px=0.2))
    assert not np.array_equal(t, band_limited_texture((128, 128), seed=5, mean=0.5,
                                                      contrast=0.1, high_cyc_px=0.2))
    spec = np.abs(np.fft.fft2(t - t.mean())) ** 2
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(128), np.fft.fftfreq(128)))
    # almost no power beyond ~1.5x the band edge (no pixel-level white noise)
    assert spec[f > 0.3].sum() < 1e-3 * spec.sum()


def test_scene_is_read_only_copy():
    h = np.zeros((8, 8))
    s = Scene(h, np.zeros((8, 8)), 0.01)
    h[0, 0] = 5
    assert s.height_mm[0, 0] == 0
    with pytest.raises(ValueError):
        s.height_mm[0, 0] = 1
    with pytest.raises(InputError, match="pixel_size_mm must be > 0"):
        Scene(h, np.zeros((8, 8)), 0.0)
    with pytest.raises(InputError, match="size_px must be an integer >= 16"):
        cone_scene(size_px=8)
