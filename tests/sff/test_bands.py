"""Frames larger than FocusConfig.band_mpixels are measured in bands of rows: the same
map as measured whole (within the choices taken from the middle band), in less memory."""

import tracemalloc

import cv2
import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.sff._align import Alignment
from smdinspect.sff._reconstruct import BAND_ALIGN_PX, BAND_MARGIN_PX, _bands
from smdinspect.stack import FocalStack, StackWriter


@pytest.mark.parametrize("shape, mpx", [((3072, 4096), 3.5), ((1536, 2048), 1.0),
                                        ((1000, 333), 0.25), ((517, 640), 0.25)])
def test_band_cores_tile_the_rows_once_on_block_boundaries(shape, mpx):
    bands = _bands(shape, FocusConfig(band_mpixels=mpx))
    assert len(bands) > 1
    covered = np.zeros(shape[0], int)
    for lo, hi, core_lo, core_hi in bands:
        covered[core_lo:core_hi] += 1
        assert core_lo % BAND_ALIGN_PX == 0 and lo % BAND_ALIGN_PX == 0
        assert lo == max(0, core_lo - BAND_MARGIN_PX) and hi == min(shape[0], core_hi + BAND_MARGIN_PX)
        # within the limit wherever the margins leave room for a core
        if mpx * 1e6 / shape[1] >= 2 * BAND_MARGIN_PX + 2 * BAND_ALIGN_PX:
            assert (hi - lo) * shape[1] <= mpx * 1e6
    assert (covered == 1).all()


def test_a_frame_within_the_limit_is_one_band():
    assert _bands((1536, 2048), FocusConfig()) == [(0, 1536, 0, 1536)]
    assert _bands((3072, 4096), FocusConfig(band_mpixels=0)) == [(0, 3072, 0, 3072)]
    with pytest.raises(InputError, match="band_mpixels"):
        FocusConfig(band_mpixels=0.1)


def test_a_band_of_the_reference_grid_is_warped_from_its_source_rows_only():
    rng = np.random.default_rng(3)
    frame = cv2.GaussianBlur(rng.random((400, 300), dtype=np.float32), (0, 0), 2.0)
    a = np.array([[0.97, 0.01, 4.0], [-0.012, 0.96, 6.5], [0, 0, 1]])  # ref -> frame
    al = Alignment(transforms=[a], reference=0, shape=(400, 300), field=np.ones((400, 300), bool))
    whole = al.warp(frame, 0)
    for rows in ((0, 64), (128, 272), (336, 400)):
        first, end = al.source_rows(0, rows, pad=2)
        part = al.warp(frame[first:end], 0, rows=rows, src_row=first)
        np.testing.assert_allclose(part, whole[rows[0]:rows[1]], atol=1e-5)


def _cone_stack(root, *, shape=(1024, 384), n_frames=12, zoom_per_frame=0.0, seed=0):
    rng = np.random.default_rng(seed)
    h, w = shape
    tex = cv2.GaussianBlur(rng.random(shape, dtype=np.float32), (0, 0), 1.0)
    tex = (tex - tex.mean()) / tex.std()
    yy, xx = np.mgrid[:h, :w] - np.array([h / 2, w / 2])[:, None, None]
    # a cone on a slope: every band holds a part of the relief
    height = np.clip(1.0 - np.hypot(xx, yy) / (0.45 * w), 0, None) + 0.3 * yy / h + 0.15
    writer = StackWriter(root, pixel_size_mm=0.01)
    for n, z in enumerate(np.linspace(-0.1, 1.1, n_frames)):
        sigma = np.round(np.clip(np.abs(height - z) * 8.0, 0.3, 6.0), 1)
        img = np.zeros(shape, np.float32)
        for s in np.unique(sigma):  # blur by level, pick per pixel
            sel = sigma == s
            img[sel] = cv2.GaussianBlur(tex, (0, 0), float(s))[sel]
        img = 128 + 40 * img + rng.normal(0, 1.0, img.shape)
        if zoom_per_frame:  # an ordinary lens: the image shrinks as z goes up
            m = cv2.getRotationMatrix2D((w / 2, h / 2), 0.0, 1.0 - zoom_per_frame * n)
            img = cv2.warpAffine(img, m, (w, h), borderMode=cv2.BORDER_REFLECT)
        writer.add_frame(np.clip(img, 0, 255).astype(np.uint8), float(z))
    writer.write_manifest()
    return FocalStack.open(root)


def _peak(stack, config):
    tracemalloc.start()
    try:
        surface = reconstruct(stack, config)
        return surface, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("align", [False, True])
def test_bands_give_the_whole_frames_map_in_less_memory(tmp_path, align):
    stack = _cone_stack(tmp_path / "s", zoom_per_frame=0.004 if align else 0.0)
    base = dict(align=align, workers=2)
    reconstruct(stack, FocusConfig(**base))  # warm caches (noise tables, imports)
    whole, whole_peak = _peak(stack, FocusConfig(band_mpixels=0, **base))
    banded, banded_peak = _peak(stack, FocusConfig(band_mpixels=0.25, **base))
    assert "bands" not in whole.meta and len(banded.meta["bands"]["rows"]) == 3
    assert banded.shape == whole.shape and banded.aif.shape == whole.aif.shape
    assert whole.coverage > 0.5
    # the same pixels reliable (the halo reach and the width cue's typical width come
    # from the middle band: a few flips) ...
    assert (banded.reliable != whole.reliable).mean() < 0.005
    both = banded.reliable & whole.reliable
    step = abs(stack.step_mm)
    err = np.abs(banded.height_mm - whole.height_mm)[both] / step
    # ... at the same heights: no seam at the bands' edges
    assert np.percentile(err, 99.9) < 0.01, np.percentile(err, [99, 99.9, 100])
    assert banded.meta["curve_power"] == whole.meta["curve_power"]
    # a band holds a third of the rows and its margins, 608 of 1024
    assert banded_peak < 0.85 * whole_peak, (banded_peak, whole_peak)
