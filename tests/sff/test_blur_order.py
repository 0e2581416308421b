"""The blur-order check (smdinspect/sff/_blur_order.py): a focus peak must be the
sharpest picture of its neighbourhood. Scenes from the independent gather renderer."""

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.sff._blur_order import blur_order_suspect, reduce_frame
from smdinspect.stack import FocalStack
from smdinspect.synth import GatherNoise, render_gather, slanted_plane, texture


def _bars(size: int, seed: int) -> np.ndarray:
    """Vertical black and white bars 4–31 px wide (a barcode)."""
    rng = np.random.default_rng(seed)
    row = np.zeros(size, np.float32)
    x, v = 0, 0.15
    while x < size:
        w = int(rng.integers(4, 32))
        row[x:x + w] = v
        v = 0.9 if v < 0.5 else 0.15
        x += w
    return np.tile(row, (size, 1))


def _jpeg_stack(tmp_path, frames, z_mm, quality=85):
    import cv2

    paths = []
    for i, f in enumerate(frames):
        f8 = f if f.dtype == np.uint8 else (f // 257).astype(np.uint8)
        p = tmp_path / f"f{i}.jpg"
        assert cv2.imwrite(str(p), f8, [cv2.IMWRITE_JPEG_QUALITY, quality])
        paths.append(p)
    step = float(z_mm[1] - z_mm[0])
    return FocalStack.from_images(paths, step_mm=step, z0_mm=float(z_mm[0]))


def test_a_frame_that_is_a_blur_of_its_neighbour_is_flagged():
    """Frames of one texture in focus at frame 2 (blur 2 px per frame away from it): a
    pixel claiming its peak at frame 2 passes, one claiming frame 4 (a blur of frame 3)
    or frame 0 (a blur of frame 1) is flagged. Frames that differ by no blur at all
    explain each other equally: nothing is flagged."""
    import cv2

    tex = texture("grain", 128, seed=5, contrast=0.4) * 200 + 20
    frames = [cv2.GaussianBlur(tex, (0, 0), max(0.3, 2.0 * abs(i - 2))) for i in range(6)]
    rng = np.random.default_rng(1)
    frames = [f + rng.normal(0, 1.0, f.shape).astype(np.float32) for f in frames]
    shape = tex.shape

    def run(frames, claimed: int) -> np.ndarray:
        best = np.full(shape, claimed, np.int16)
        asked = []

        def read(i):
            asked.append(i)
            return reduce_frame(frames[i])

        out = blur_order_suspect(read, len(frames), best, box_px=15, ratio=2.0)
        assert asked == list(range(len(frames)))  # one pass, in frame order
        return out

    assert run(frames, 2).mean() < 0.01
    assert run(frames, 4).mean() > 0.95
    assert run(frames, 0).mean() > 0.95
    same = [frames[2] + rng.normal(0, 1.0, shape).astype(np.float32) for _ in range(6)]
    assert run(same, 3).mean() < 0.01


def test_bars_sharp_on_the_first_frame_give_no_false_heights(tmp_path):
    """A barcode in focus on the first frame, 6 px more blur per frame, saved as JPEG:
    the bars' interiors peak a frame later (the blurred edges reach in) and those peaks
    passed every other cue, one frame (0.3 mm) off. The blur-order check drops them:
    frame 1 there is a blur of frame 0."""
    size = 160
    z = np.arange(7) * 0.3 - 0.05
    frames = render_gather(_bars(size, 0), np.zeros((size, size), np.float32), z,
                           blur_px_per_mm=20.0, sigma0_px=0.7,
                           noise=GatherNoise(read_noise=0.004), seed=0)
    stack = _jpeg_stack(tmp_path, frames, z)
    truth_pos = np.interp(0.0, stack.z_mm, np.arange(len(z)))
    wrong = {}
    for ratio in (0.0, 2.0):
        s = reconstruct(stack, FocusConfig(blur_order_ratio=ratio))
        pos = np.interp(s.height_mm, stack.z_mm, np.arange(len(z)))
        wrong[ratio] = int((s.reliable & (np.abs(pos - truth_pos) > 0.5)).sum())
        if ratio:
            assert s.meta["blur_order"]["ratio"] == 2.0
    assert wrong[0.0] > 200      # the failure is there without the check ...
    assert wrong[2.0] < 0.05 * wrong[0.0]   # ... and gone with it


@pytest.mark.parametrize("dof_per_step", [1.0, 3.0])
def test_a_textured_slope_keeps_its_heights(tmp_path, dof_per_step):
    """On a textured slanted plane (fine and coarse steps) the check costs < 1 % of the
    reliable heights."""
    tex = texture("band", 160, seed=10_003, freq_cyc_px=0.2, contrast=0.25)
    radiance, height = slanted_plane(size_px=160, low_mm=0.0, high_mm=1.0, texture=tex,
                                     seed=10_003)
    step = 0.12
    z = np.arange(-0.2, 1.2 + 1e-9, step) + 0.013
    frames = render_gather(radiance, height, z, blur_px_per_mm=dof_per_step * 0.3536 / step,
                           sigma0_px=0.5, noise=GatherNoise(read_noise=0.002), seed=10_003)
    stack = _jpeg_stack(tmp_path, frames, z, quality=95)
    off = reconstruct(stack, FocusConfig(blur_order_ratio=0.0)).reliable
    on = reconstruct(stack, FocusConfig()).reliable
    assert off.mean() > 0.5
    assert (off & ~on).sum() < 0.01 * off.sum()


@pytest.mark.parametrize("bad", [0.5, -1, float("nan"), True, "2"])
def test_blur_order_ratio_is_validated(bad):
    with pytest.raises(InputError, match="blur_order_ratio"):
        FocusConfig(blur_order_ratio=bad)


def test_the_second_pass_runs_only_where_the_check_is_judged(tmp_path, monkeypatch):
    """The check reads the frames again after the fit, and only when the stack's blur per
    frame reaches the smallest blur it tries: a fine-step sweep (κ < 1 px/frame) is not
    read twice; the coarse bars sweep is, once, in frame order."""
    import smdinspect.sff._reconstruct as R

    calls = []
    real = R.blur_order_suspect

    def counting(read, n, best, **kw):
        calls.append(n)
        return real(read, n, best, **kw)

    monkeypatch.setattr(R, "blur_order_suspect", counting)
    tex = texture("band", 96, seed=10_005, freq_cyc_px=0.2, contrast=0.25)
    radiance, height = slanted_plane(size_px=96, low_mm=0.0, high_mm=0.5, texture=tex,
                                     seed=10_005)
    z = np.arange(-0.2, 0.7 + 1e-9, 0.05) + 0.013
    frames = render_gather(radiance, height, z, blur_px_per_mm=0.5 * 0.3536 / 0.05,
                           sigma0_px=0.5, noise=GatherNoise(read_noise=0.002), seed=10_005)
    fine = reconstruct(_jpeg_stack(tmp_path, frames, z, quality=95), FocusConfig())
    assert fine.meta["blur_order"]["judged"] is False and calls == []
    bars = render_gather(_bars(96, 1), np.zeros((96, 96), np.float32), np.arange(7) * 0.3,
                         blur_px_per_mm=20.0, sigma0_px=0.7, noise=GatherNoise(read_noise=0.004),
                         seed=1)
    (tmp_path / "b").mkdir()
    coarse = reconstruct(_jpeg_stack(tmp_path / "b", bars, np.arange(7) * 0.3), FocusConfig())
    assert coarse.meta["blur_order"]["judged"] is True and calls == [7]
