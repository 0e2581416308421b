"""Over-exposure: pixels clipped white in the all-in-focus image are counted and named."""

import numpy as np
import pytest

from smdinspect.sff import FocusConfig, clipped_white, reconstruct
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import GatherNoise, render_gather, slanted_plane, texture


def test_clipped_white_per_dtype():
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[0, 0] = 255
    rgb[0, 1] = (255, 255, 200)          # one channel below white: not clipped
    rgb[1, 1] = 254                      # a level short (JPEG, resampling): clipped
    assert clipped_white(rgb).tolist()[0][:2] == [True, False] and clipped_white(rgb)[1, 1]
    grey = np.full((3, 3), 65535, np.uint16)
    grey[0, 0] = 60000
    assert clipped_white(grey).sum() == 8
    assert clipped_white(np.ones((3, 3), np.float32)) is None   # no known white level


def test_reconstruct_counts_and_warns_about_a_clipped_glint(tmp_path, caplog):
    n = 128
    tex = texture("band", n, seed=10_041, freq_cyc_px=0.2, contrast=0.3)
    radiance, height = slanted_plane(size_px=n, low_mm=0.0, high_mm=0.5, texture=tex,
                                     seed=10_041)
    z = np.arange(-0.1, 0.6 + 1e-9, 0.05)
    frames = render_gather(radiance, height, z, blur_px_per_mm=4.0, noise=GatherNoise(),
                           seed=10_041)
    glint = np.zeros((n, n), bool)
    glint[40:80, 40:80] = True          # a glint at full scale in every frame
    w = StackWriter(tmp_path / "s", pixel_size_mm=0.01)
    for f, zn in zip(frames, z):
        img = np.round(np.clip(f, 0, 1) * 200).astype(np.uint8)
        img[glint] = 255
        w.add_frame(img, float(zn))
    w.write_manifest()
    with caplog.at_level("WARNING", logger="smdinspect.sff._reconstruct"):
        s = reconstruct(FocalStack.open(tmp_path / "s"), FocusConfig())
    share = s.meta["clipped_white"]
    assert share["fraction_of_field"] == pytest.approx(glint.mean(), abs=0.01)
    inner = np.zeros_like(glint)
    inner[50:70, 50:70] = True           # a window clear of the glint's edges
    assert not s.reliable[inner].any()
    assert share["fraction_of_unreliable"] >= 0.5 * glint.mean()
    warned = [r.getMessage() for r in caplog.records if "clipped white" in r.getMessage()]
    assert len(warned) == 1 and "lower the exposure" in warned[0]
