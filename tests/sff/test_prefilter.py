"""The noise pre-filter: a Gaussian chosen from the frequencies where defocus no longer
changes the power (sensor noise only), gather renderer, test seeds."""

import numpy as np
import pytest

from smdinspect.sff import FocusConfig, band_powers, prefilter_sigma, reconstruct
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import TEST_SEEDS, GatherNoise, cone, render_gather, texture

SEED, N, STEP = TEST_SEEDS[0] + 11, 128, 0.05


def _cone_stack(tmp_path, noise, name):
    tex = texture("band", N, seed=SEED, freq_cyc_px=0.15, contrast=0.2)
    radiance, height = cone(size_px=N, low_mm=0.1, high_mm=0.7, texture=tex, seed=SEED)
    z = np.arange(-0.1, 0.9 + 1e-9, STEP) + 0.013
    w = StackWriter(tmp_path / name, pixel_size_mm=0.01)
    for frame, zn in zip(render_gather(radiance, height, z, blur_px_per_mm=0.3536 / STEP,
                                       noise=noise, seed=SEED), z):
        w.add_frame(frame, float(zn))
    w.write_manifest()
    return FocalStack.open(tmp_path / name), height


def _grey(stack, i):
    f = stack.read_frame(i).astype(np.float32)
    return f if f.ndim == 2 else f.mean(axis=2)


def test_sigma_is_zero_without_noise_or_without_texture(tmp_path):
    clean, _ = _cone_stack(tmp_path, GatherNoise.off(), "clean")
    assert prefilter_sigma([band_powers(_grey(clean, i)) for i in range(len(clean))])[0] == 0.0
    rng = np.random.default_rng(5)
    noise = [band_powers((128 + 3 * rng.standard_normal((256, 256))).astype(np.float32))
             for _ in range(12)]
    assert prefilter_sigma(noise)[0] == 0.0  # nothing to measure: blurring cannot help
    assert prefilter_sigma(noise[:1])[0] == 0.0
    assert band_powers(np.zeros((32, 32), np.float32)) is None  # smaller than a tile


def test_noisy_stack_gets_a_prefilter_that_lowers_the_error(tmp_path):
    stack, height = _cone_stack(tmp_path, GatherNoise(read_noise=0.02), "noisy")
    sigma, modulation = prefilter_sigma([band_powers(_grey(stack, i)) for i in range(len(stack))])
    assert 0.4 < sigma <= 1.5, (sigma, modulation)
    assert modulation[2] > 10 and modulation[-1] < 2  # texture band vs noise-only band
    out = {}
    for pf in (0, "auto"):
        s = reconstruct(stack, FocusConfig(prefilter_px=pf))
        e = (s.height_mm - height)[s.reliable] / STEP
        out[pf] = (float(np.sqrt(np.mean(e ** 2))), float(s.reliable.mean()))
    assert s.meta["prefilter"]["sigma_px"] == pytest.approx(min(sigma, 9 / 6), abs=1e-3)
    assert out["auto"][0] < 0.75 * out[0][0], out
    assert out["auto"][1] >= out[0][1] - 0.01, out


def test_bad_prefilter_values_are_refused():
    from smdinspect.errors import InputError

    for bad in (-1, "sometimes", float("nan"), True, 17):
        with pytest.raises(InputError, match="prefilter_px"):
            FocusConfig(prefilter_px=bad)


def test_spectra_are_read_on_the_output_grid_frequencies():
    """Through an ordinary lens the same texture lies at higher frequencies of a less
    magnified frame's own pixels; given each frame's scale (an output pixel in its
    pixels), every frame's power is read at the scene's frequency, so the texture's
    modulation stays in its own band instead of spreading into the bands above it (which
    raised the cut-off and lowered σ)."""
    rng = np.random.default_rng(SEED)
    y, x = np.mgrid[:256, :256]
    scales = np.linspace(0.6, 1.0, 9)  # 1.67x magnification change over the sweep
    contrast = np.exp(-0.5 * ((np.arange(9) - 4) / 1.5) ** 2)  # in focus mid-sweep
    f_out = 0.12  # cycles per output pixel: band [0.10, 0.15)
    powers = []
    for s, c in zip(scales, contrast):
        f_own = f_out / s  # the same texture in this frame's own (larger) pixels
        frame = 128 + 40 * c * np.sin(2 * np.pi * f_own * (x + 0.7 * y) / np.hypot(1, 0.7))
        powers.append(band_powers((frame + 2 * rng.standard_normal(frame.shape)).astype(np.float32)))
    _, mod_own = prefilter_sigma(powers)
    sigma, mod_out = prefilter_sigma(powers, scales=scales)
    assert mod_out[2] > 100 and max(mod_out[3:]) < 3, mod_out  # one band: the texture's
    assert max(mod_own[3:5]) > 10, mod_own  # read in own pixels it spreads to 0.2 c/px
    # the cut-off is the band above the texture's: f_c = 0.15 cycles per output pixel
    assert sigma == pytest.approx(np.sqrt(2) / (2 * np.pi * 0.15), rel=1e-6)
    assert prefilter_sigma(powers, scales=np.ones(9)) == prefilter_sigma(powers)


def test_magnification_exponent_follows_the_operators_discrete_response():
    """F of a frame seen m× less magnified grows as m^k. For a derivative operator of
    order d and curve power p the continuous law gives k = d·p (4 for SML); a difference
    operator's response (2 sin πf)^d has the log-slope d·πf·cot(πf), lower the finer the
    texture. Read from the sharpest frame's spectrum less the sweep's floor (the noise,
    whose focus is not scaled)."""
    from smdinspect.sff import magnification_exponent

    rng = np.random.default_rng(SEED)
    y, x = np.mgrid[:256, :256]
    for f in (0.12, 0.3):
        powers = []
        for amp in (40.0, 10.0, 0.0):  # in focus, blurred, texture gone: the noise floor
            frame = 128 + amp * np.sin(2 * np.pi * f * x) + 2 * rng.standard_normal(x.shape)
            powers.append(band_powers(frame.astype(np.float32)))
        k = magnification_exponent("sml", powers, [1.0] * 3)
        expect = 4 * np.pi * f / np.tan(np.pi * f)
        assert k == pytest.approx(expect, abs=0.15), (f, k, expect)
    assert magnification_exponent("sml", [None, None], [1.0, 1.0]) == 4.0  # no spectra
    assert magnification_exponent("glva", powers, [1.0] * 3) == 0.0  # not a derivative
