"""The local plane through the reliable heights (FocusConfig.plane_px): unbiased on any
slope, through holes; lowers the random error; leaves gaps and unreliable pixels alone.
Stacks from the independent gather renderer, test seeds only."""

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff import FocusConfig, local_plane, reconstruct

from .test_precision import STEP, _weak_plane


def _slope(shape=(120, 90), *, z0=-50.0):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return (z0 + 0.05 * xx - 0.03 * yy).astype(np.float32)  # a steep plane far from z = 0


def test_a_plane_through_holes_is_kept_exactly():
    """With a fifth of the pixels missing the square around a pixel is lopsided: a mean
    of the heights there is pulled along the slope, a plane through them is not."""
    h = _slope()
    ok = np.random.default_rng(10_200).random(h.shape) > 0.2
    out, used = local_plane(h, ok, side_px=5)
    assert used.mean() > 0.7
    np.testing.assert_allclose(out[used], h[used], atol=2e-5)
    # the naive mean over the same squares is not (what the test would miss otherwise)
    import cv2
    w = ok.astype(np.float32)
    mean = (cv2.boxFilter(np.where(ok, h + 50, 0).astype(np.float32), -1, (5, 5), normalize=False)
            / np.maximum(cv2.boxFilter(w, -1, (5, 5), normalize=False), 1)) - 50
    assert np.abs(mean - h)[used].max() > 0.01


def test_the_random_error_is_averaged():
    truth = _slope()
    rng = np.random.default_rng(10_201)
    h = truth + rng.normal(0, 0.01, truth.shape).astype(np.float32)
    ok = rng.random(h.shape) > 0.1
    out, used = local_plane(h, ok, side_px=5)
    inner = used.copy()
    inner[:4], inner[-4:], inner[:, :4], inner[:, -4:] = False, False, False, False
    before = np.std((h - truth)[inner])
    after = np.std((out - truth)[inner])
    assert after < before / 3, (before, after)  # independent errors: about 1/4.5


def test_gaps_and_unreliable_pixels_keep_their_reading():
    h = _slope((40, 40)) + np.random.default_rng(10_202).normal(0, 0.01, (40, 40)).astype(np.float32)
    ok = np.zeros(h.shape, bool)
    ok[5:35, 5:35] = True
    ok[20, 20] = False          # an unreliable pixel inside: untouched
    ok[8:12, 25:35] = False     # a hole: the pixels along its rim lack support
    ok[10, 30] = True           # a lone reliable pixel in the hole: 3 of 25 reliable
    out, used = local_plane(h, ok, side_px=5)
    assert not used[~ok].any() and out[20, 20] == h[20, 20]
    assert not used[10, 30] and out[10, 30] == h[10, 30]
    assert used[20, 10] and out[20, 10] != h[20, 10]


def test_chunks_do_not_change_the_result():
    h = _slope((70, 50)) + np.random.default_rng(10_203).normal(0, 0.02, (70, 50)).astype(np.float32)
    ok = np.random.default_rng(10_204).random(h.shape) > 0.3
    whole, used = local_plane(h, ok, side_px=5)
    parts, used2 = local_plane(h, ok, side_px=5, rows_per_chunk=7)
    assert np.array_equal(used, used2)
    np.testing.assert_allclose(parts, whole, atol=1e-5)


def test_reconstruct_planes_the_reliable_heights(tmp_path):
    """A weakly textured noisy slanted plane: the same pixels are reliable, with a lower
    error (measured 0.147 -> 0.127 Δd), none of them moved by more than the noise."""
    stack, truth = _weak_plane(tmp_path, noise_seed=10_103)
    raw = reconstruct(stack, FocusConfig(coarse_factor=0, plane_px=0))
    planed = reconstruct(stack, FocusConfig(coarse_factor=0))
    assert "plane" not in raw.meta
    assert planed.meta["plane"]["side_px"] == 5
    assert planed.meta["plane"]["fraction_of_reliable"] > 0.9
    assert np.array_equal(raw.reliable, planed.reliable)
    r = planed.reliable
    rmse = {k: float(np.sqrt(np.mean(((s.height_mm - truth)[r] / STEP) ** 2)))
            for k, s in (("raw", raw), ("planed", planed))}
    assert rmse["planed"] < 0.93 * rmse["raw"], rmse
    assert np.abs(planed.height_mm - raw.height_mm)[r].max() < 1.0 * STEP
    np.testing.assert_array_equal(planed.height_mm[~r], raw.height_mm[~r])


@pytest.mark.parametrize("bad", [2, 4, -1, True, 3.0])
def test_plane_px_must_be_odd_or_off(bad):
    with pytest.raises(InputError, match="plane_px"):
        FocusConfig(plane_px=bad)


def test_reconstruct_command_takes_plane_px(tmp_path, capsys):
    import json

    from smdinspect.cli import main

    _weak_plane(tmp_path, noise_seed=10_108, name="cli")
    out = tmp_path / "out"
    assert main(["-q", "reconstruct", str(tmp_path / "cli"), "--out", str(out),
                 "--outputs", "height_mm.tiff"]) == 0
    assert json.loads((out / "summary.json").read_text())["plane"]["side_px"] == 5
    assert main(["-q", "reconstruct", str(tmp_path / "cli"), "--out", str(out),
                 "--outputs", "height_mm.tiff", "--plane-px", "0"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert "plane" not in summary and summary["config"]["plane_px"] == 0
    capsys.readouterr()
    before = sorted(p.name for p in out.iterdir())
    assert main(["-q", "reconstruct", str(tmp_path / "cli"), "--out", str(out),
                 "--plane-px", "4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "plane_px must be" in err[0], err
    assert sorted(p.name for p in out.iterdir()) == before  # nothing replaced
