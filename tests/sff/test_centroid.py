"""Centroid correction: a window on a slope measures the height under its focus energy's
centroid; the core moves it back (gather renderer, test seeds)."""

import numpy as np
import pytest

from smdinspect.sff import FocusConfig, centroid_correction, focus_measure, focus_measure_moments, reconstruct
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import TEST_SEEDS, GatherNoise, cone, render_gather, texture


def test_moments_match_a_brute_force_sum():
    rng = np.random.default_rng(3)
    g = (rng.random((40, 50)) * 200).astype(np.float32)
    for op in ("sml", "gder", "lapm"):
        f, mx, my = focus_measure_moments(g, operator=op, window_px=7)
        assert np.allclose(f, focus_measure(g, operator=op, window_px=7), rtol=1e-5)
        r = focus_measure(g, operator=op, window_px=1)
        y, x = 20, 25
        block = r[y - 3:y + 4, x - 3:x + 4]
        off = np.arange(-3, 4)
        assert mx[y, x] == pytest.approx((block * off[None, :]).sum(), rel=1e-4)
        assert my[y, x] == pytest.approx((block * off[:, None]).sum(), rel=1e-4)
    f, mx, my = focus_measure_moments(g, operator="glva", window_px=7)  # not a sum: no moments
    assert mx is None and my is None and f.shape == g.shape


def test_correction_on_a_known_plane():
    h = np.tile(np.arange(32, dtype=np.float32) * 0.01, (32, 1))  # 0.01 mm per column
    ok = np.ones(h.shape, bool)
    dx = np.full(h.shape, 2.0, np.float32)  # energy 2 px to the right: measured 0.02 too high
    out = centroid_correction(h + 0.02, ok, (dx, np.zeros_like(dx)), window_px=9, max_mm=0.05)
    assert np.allclose(out[8:-8, 8:-8], h[8:-8, 8:-8], atol=1e-5)
    coarse = centroid_correction(h + 0.02, ok, (dx, np.zeros_like(dx)), window_px=9, max_mm=0.05,
                                 width_steps=np.full(h.shape, 0.3, np.float32))
    assert np.array_equal(coarse, h + 0.02)  # curves narrower than the step: left alone


def test_cone_error_drops_with_the_correction(tmp_path):
    seed, n, step = TEST_SEEDS[0] + 7, 128, 0.05
    tex = texture("band", n, seed=seed, freq_cyc_px=0.15, contrast=0.2)
    radiance, height = cone(size_px=n, low_mm=0.1, high_mm=0.7, texture=tex, seed=seed)
    z = np.arange(-0.1, 0.9 + 1e-9, step) + 0.013
    w = StackWriter(tmp_path / "c", pixel_size_mm=0.01)
    for frame, zn in zip(render_gather(radiance, height, z, blur_px_per_mm=0.3536 / step,
                                       noise=GatherNoise.off(), seed=seed), z):
        w.add_frame(frame, float(zn))
    w.write_manifest()
    stack = FocalStack.open(tmp_path / "c")
    rmse = {}
    for on in (False, True):
        s = reconstruct(stack, FocusConfig(centroid_correction=on))
        e = (s.height_mm - height)[s.reliable] / step
        assert s.reliable.mean() > 0.95
        rmse[on] = float(np.sqrt(np.mean(e ** 2)))
    assert rmse[True] < 0.07 and rmse[True] < 0.7 * rmse[False], rmse
