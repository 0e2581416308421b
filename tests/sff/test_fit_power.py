"""The power fit's curve shape chosen from the sweep (FocusConfig.fit_power="auto"):
a narrow-band texture's focus curve is close to a Gaussian, and the operator's power law
terraces its heights at a coarse step."""

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import GatherNoise, render_gather, slanted_plane, texture

STEP = 0.12


def _plane(tmp_path, kind):
    tex = texture(kind, 192, seed=10101, freq_cyc_px=0.2, contrast=0.25)
    radiance, height = slanted_plane(size_px=192, low_mm=0.0, high_mm=1.0, texture=tex,
                                     seed=10101)
    z = np.arange(-0.2, 1.2 + 1e-9, STEP) + 0.013  # 2.5 depths of field per step
    w = StackWriter(tmp_path / kind, pixel_size_mm=0.01)
    for frame, zn in zip(render_gather(radiance, height, z, blur_px_per_mm=2.5 * 0.3536 / STEP,
                                       sigma0_px=0.5, psf="gauss",
                                       noise=GatherNoise(read_noise=0.002), seed=10101), z):
        w.add_frame(frame, float(zn))
    w.write_manifest()
    return FocalStack.open(tmp_path / kind), height, z


def _terrace_ptp(s, height, z):
    r = s.reliable
    frac = np.interp(height[r], z, np.arange(len(z))) % 1.0
    err = (s.height_mm - height)[r] / STEP
    means = [np.mean(err[(frac >= a) & (frac < a + 0.2)]) for a in np.arange(0, 1, 0.2)]
    return float(max(means) - min(means))


def test_auto_shape_removes_the_terraces_of_a_narrow_band_texture(tmp_path):
    stack, height, z = _plane(tmp_path, "band")
    fixed = reconstruct(stack, FocusConfig(fit_power=None))
    auto = reconstruct(stack, FocusConfig())
    # measured: 0.068 -> 0.009 step peak-to-peak; p 4.3 chosen (the operator's is 2)
    assert _terrace_ptp(fixed, height, z) > 0.05
    assert _terrace_ptp(auto, height, z) < 0.03
    assert auto.meta["curve_power"]["power"] > 3
    assert np.array_equal(auto.reliable, fixed.reliable)  # the confidence is the same


def test_auto_shape_keeps_the_power_law_for_a_broadband_texture(tmp_path):
    stack, height, z = _plane(tmp_path, "grain")
    auto = reconstruct(stack, FocusConfig())
    assert 1.5 <= auto.meta["curve_power"]["power"] <= 3.0
    assert _terrace_ptp(auto, height, z) < 0.03


def test_fit_power_values():
    assert FocusConfig(fit_power=3.0).fit_power == 3.0
    for bad in ("gauss", 0.0, 100.0, True):
        with pytest.raises(InputError, match="fit_power"):
            FocusConfig(fit_power=bad)
