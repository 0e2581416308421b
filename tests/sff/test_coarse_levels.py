"""Coarse focus levels: the energy-centroid check that keeps a coarse window from giving
a textureless pixel its textured neighbour's height, and the optional second level."""

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.sff._reconstruct import _coarse_factors, _energy_offset_px
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import GatherNoise, half_textured, render_gather, sphere_cap, texture


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
    assert _coarse_factors(FocusConfig(coarse_levels=1), (300, 400)) == [4]
    assert _coarse_factors(FocusConfig(), (300, 400)) == [4, 16]
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


def test_footprint_check_against_the_finer_map():
    from smdinspect.sff._reconstruct import _footprint_agrees

    h, w, step = 60, 80, 0.05
    cols = np.arange(w)[None, :].repeat(h, 0).astype(np.float32)
    plane = 0.5 + 0.001 * cols  # 0.02 steps per px: spread 0.02·21/√12 = 0.12 step
    rel = np.ones((h, w), bool)
    assert _footprint_agrees(plane, rel, plane, step=step, window_px=21)[30, 40]
    # a reading 2 steps off what the footprint measured
    assert not _footprint_agrees(plane, rel, plane + 2 * step, step=step, window_px=21)[30, 40]
    # a footprint holding two depths 4 steps apart: spread 2 steps
    two = np.where(cols < 40, 0.5, 0.5 + 4 * step).astype(np.float32)
    assert not _footprint_agrees(two, rel, two, step=step, window_px=21)[30, 40]
    assert _footprint_agrees(two, rel, two, step=step, window_px=21)[30, 10]
    # too little of the footprint measured (10 %)
    sparse = np.zeros((h, w), bool)
    sparse[::10, :] = True
    assert not _footprint_agrees(plane, sparse, plane, step=step, window_px=21)[30, 40]


def test_second_level_leaves_a_cap_narrower_than_its_footprint_unfilled(tmp_path):
    """A weakly textured sphere cap 87 px wide on a plane: the 16x level's 88-px
    footprint reads its flanks at the plane's height. Its own heights see no slope there,
    so the slope bound alone let them through (here 3 207 px off by more than a step,
    74 % of the reliable ones within one); the finer map's footprint check keeps them
    out."""
    n, step = 128, 0.0127
    seed = 10207
    tex = texture("grain", n, seed=seed, freq_cyc_px=0.18, contrast=0.015)
    radiance, height = sphere_cap(size_px=n, low_mm=0.31, high_mm=0.59, radius_frac=0.34,
                                  cap_deg=37.0, texture=tex, seed=seed)
    radiance = radiance * (0.66 / radiance.mean())
    z = np.arange(0.31 - 2 * step, 0.59 + 2 * step, step)
    w = StackWriter(tmp_path / "cap", pixel_size_mm=0.028)
    for frame, zn in zip(render_gather(radiance, height, z, blur_px_per_mm=21.4,
                                       sigma0_px=0.9, psf="disc", noise=GatherNoise(),
                                       seed=seed), z):
        w.add_frame(frame, float(zn))
    w.write_manifest()
    stack = FocalStack.open(tmp_path / "cap")
    one = reconstruct(stack, FocusConfig(coarse_levels=1))
    two = reconstruct(stack, FocusConfig(coarse_levels=2))
    for s in (one, two):
        err = np.abs(s.height_mm - height)[s.reliable] / step
        assert np.mean(err <= 1) >= 0.98, (s.coverage, np.mean(err <= 1))
    assert two.reliable.sum() >= one.reliable.sum()


@pytest.mark.parametrize("radius_px", [3, 44])
def test_near_step_equals_the_whole_map_distance(radius_px):
    """_near_step measures distances over the steps' bounding box grown by the radius:
    the same pixels as the Euclidean distance over the whole map."""
    import cv2

    from smdinspect.sff._confidence import step_levels
    from smdinspect.sff._reconstruct import _near_step

    rng = np.random.default_rng(radius_px)
    height = np.zeros((160, 220), np.float32)
    height[60:75, 90:120] = 1.0  # a part inside the map
    height[:6, 200:] = 1.0  # and one at a corner
    reliable = rng.random(height.shape) < 0.9
    step = np.isfinite(step_levels(height, reliable, jump_mm=0.5, span_px=5))
    dist = cv2.distanceTransform((~step).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    got = _near_step(height, reliable, jump_mm=0.5, radius_px=radius_px)
    assert got.any() and np.array_equal(got, dist <= radius_px)
