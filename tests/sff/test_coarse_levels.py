"""Coarse focus levels: the energy-centroid check that keeps a coarse window from giving
a textureless pixel its textured neighbour's height, and the optional second level."""

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.sff._reconstruct import _coarse_factors, _energy_offset_px
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import GatherNoise, half_textured, render_gather, texture


def test_energy_offset_points_at_the_texture():
    e = np.zeros((64, 96), np.float32)
    e[:, :48] = 1.0  # texture on the left half only
    dx, dy = _energy_offset_px(e, 21)
    # deep inside the texture the centroid is the pixel; at the boundary a quarter
    # window to the left; d px into the textureless side w/4 + d/2
    assert abs(dx[32, 20]) < 1e-3 and abs(dy[32, 20]) < 1e-3
    # at column 48 the window holds textured columns 38..47: offsets -10..-1, mean -5.5
    assert dx[32, 48] == pytest.approx(-5.5, abs=0.01)
    assert dx[32, 55] < -21 / 4
    assert dx[32, 80] == 21  # no energy in the window: marked as far as the window


def test_coarse_factors_and_validation():
    assert _coarse_factors(FocusConfig(), (300, 400)) == [4]
    assert _coarse_factors(FocusConfig(coarse_levels=2), (300, 400)) == [4, 16]
    assert _coarse_factors(FocusConfig(coarse_levels=2), (100, 400)) == [4]  # 16 too coarse
    assert _coarse_factors(FocusConfig(coarse_factor=0, coarse_levels=2), (300, 400)) == []
    with pytest.raises(InputError, match="coarse_levels"):
        FocusConfig(coarse_levels=0)


def test_second_level_keeps_the_textureless_half_unreliable(tmp_path):
    """With a 16x level (an 88-px footprint) the textureless half within half a footprint
    of the textured one took the textured half's height (5 % of it, measured) before the
    energy-centroid check."""
    n = 160
    tex = texture("band", n, seed=10102, freq_cyc_px=0.2, contrast=0.25)
    radiance, height, textured = half_textured(size_px=n, low_mm=0.0, high_mm=1.0,
                                               texture=tex, seed=10102)
    z = np.arange(-0.2, 1.2 + 1e-9, 0.05)
    w = StackWriter(tmp_path / "half", pixel_size_mm=0.01)
    for frame, zn in zip(render_gather(radiance, height, z, blur_px_per_mm=0.3536 / 0.05,
                                       noise=GatherNoise(), seed=10102), z):
        w.add_frame(frame, float(zn))
    w.write_manifest()
    s = reconstruct(FocalStack.open(tmp_path / "half"), FocusConfig(coarse_levels=2))
    cols = np.arange(n)[None, :]
    flat = ~textured & (cols >= n // 2 + 12)
    tex_side = textured & (cols < n // 2 - 12)
    assert s.reliable[flat].mean() <= 0.01, s.reliable[flat].mean()
    assert s.reliable[tex_side].mean() >= 0.99
    err = np.abs(s.height_mm - height)[s.reliable] / 0.05
    assert np.mean(err <= 1) >= 0.99
