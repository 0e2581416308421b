"""Peak tracking and the Gaussian fit against exact focus curves."""

import numpy as np
import pytest

from smdinspect.sff import FitMethod, PeakTracker, confidence_map, fit_peaks


def _gauss_curves(z, mu, sigma, amp, floor=0.0):
    """(n, H, W) exact Gaussian focus curves."""
    return (amp[None] * np.exp(-((z[:, None, None] - mu[None]) ** 2) / (2 * sigma[None] ** 2))
            + floor).astype(np.float32)


def _track(volume, k=3):
    n = volume.shape[0]
    tr = PeakTracker(volume.shape[1:], n, half_width=k)
    for i in range(n):
        tr.update(i, volume[i].copy())
    tr.finish()
    return tr


@pytest.fixture(scope="module")
def curves():
    rng = np.random.default_rng(1)
    z = np.arange(30) * 0.05
    mu = rng.uniform(0.3, 1.2, (20, 20))
    sigma = rng.uniform(0.05, 0.12, (20, 20))
    amp = rng.uniform(10, 1000, (20, 20))
    return z, mu, sigma, amp


@pytest.mark.parametrize("method", [FitMethod.GAUSS3, FitMethod.LSQ])
def test_exact_gaussian_recovered(curves, method):
    z, mu, sigma, amp = curves
    tr = _track(_gauss_curves(z, mu, sigma, amp))
    fit = fit_peaks(tr, z, method=method)
    assert fit.interior.all()
    np.testing.assert_allclose(fit.height_mm, mu, atol=2e-4)
    np.testing.assert_allclose(fit.sigma_mm, sigma, rtol=2e-3)
    np.testing.assert_allclose(fit.f_peak, amp, rtol=2e-3)
    assert np.all(fit.reliability_db > 40)
    assert np.all(fit.ambiguity < 0.05)


def test_tracker_matches_full_volume(curves):
    """The streaming state equals what the whole focus volume would give."""
    z, mu, sigma, amp = curves
    rng = np.random.default_rng(2)
    vol = _gauss_curves(z, mu, sigma, amp) + rng.uniform(0, 50, (len(z), 20, 20)).astype(np.float32)
    k = 3
    tr = _track(vol, k)
    best = vol.argmax(0)
    np.testing.assert_array_equal(tr.best_idx, best)
    padded = np.concatenate([np.full((k, 20, 20), np.nan, np.float32), vol,
                             np.full((k, 20, 20), np.nan, np.float32)])
    for j in range(2 * k + 1):
        expect = np.take_along_axis(padded, (best + j)[None], 0)[0]
        np.testing.assert_array_equal(tr.window[j], expect)
    idx = np.arange(len(z))[:, None, None]
    far = np.abs(idx - best[None]) > k
    np.testing.assert_array_equal(tr.alternative, np.where(far, vol, 0).max(0))


def test_edge_peaks_and_inverted_fits_are_unreliable():
    z = np.arange(10) * 0.1
    vol = np.ones((10, 1, 4), np.float32)
    vol[:, 0, 0] = np.linspace(10, 1, 10)  # peak on the first frame
    vol[:, 0, 1] = np.linspace(1, 10, 10)  # peak on the last frame
    vol[:, 0, 2] = 3.0  # a flat curve: the log-parabola degenerates (c = 0)
    vol[:, 0, 3] = np.exp(-((z - 0.42) ** 2) / (2 * 0.1**2)) * 10 + 0.1
    fit = fit_peaks(_track(vol, 2), z, method=FitMethod.GAUSS3)
    assert fit.interior.ravel().tolist() == [False, False, False, True]
    assert fit.height_mm[0, 0] == pytest.approx(0.0) and fit.height_mm[0, 1] == pytest.approx(0.9)
    assert np.isnan(fit.sigma_mm[0, 2])
    assert fit.height_mm[0, 3] == pytest.approx(0.42, abs=0.01)
    conf = confidence_map(fit)
    assert conf[0, :3].tolist() == [0, 0, 0] and conf[0, 3] > 0.5


def test_uneven_z_spacing():
    z = np.cumsum(np.r_[0, np.random.default_rng(3).uniform(0.04, 0.06, 24)])
    mu = np.full((3, 3), 0.61)
    vol = _gauss_curves(z, mu, np.full((3, 3), 0.08), np.full((3, 3), 100.0))
    fit = fit_peaks(_track(vol), z, method=FitMethod.GAUSS3)
    np.testing.assert_allclose(fit.height_mm, 0.61, atol=1e-4)


def test_flat_noisy_curves_get_low_confidence_and_two_peaks_are_ambiguous():
    rng = np.random.default_rng(4)
    z = np.arange(30) * 0.05
    flat = 100 + rng.normal(0, 5, (30, 30, 30)).astype(np.float32)
    good = _gauss_curves(z, np.full((30, 30), 0.7), np.full((30, 30), 0.08),
                         np.full((30, 30), 100.0)) + rng.normal(0, 1, (30, 30, 30)).astype(np.float32) + 5
    twin = good + _gauss_curves(z, np.full((30, 30), 0.2), np.full((30, 30), 0.08),
                                np.full((30, 30), 90.0))
    conf = [confidence_map(fit_peaks(_track(v), z, method=FitMethod.GAUSS3)) for v in (flat, good, twin)]
    assert np.mean(conf[0] >= 0.5) < 0.05
    assert np.mean(conf[1] >= 0.5) > 0.95
    assert np.mean(conf[2] >= 0.5) < 0.05


def test_tracker_memory_is_constant_in_frames():
    """State size depends on the image and k, never on the number of frames."""
    def state_bytes(n):
        tr = PeakTracker((50, 60), n, half_width=3)
        return sum(a.nbytes for a in vars(tr).values() if isinstance(a, np.ndarray))
    assert state_bytes(10) == state_bytes(1000)


@pytest.mark.parametrize("shape", [(20, 20), (300, 300)])  # one block; blocks in threads
def test_heights_only_fit_is_the_full_fit_heights(shape, monkeypatch):
    """fit_peaks(heights_only=True) gives the full fit's heights and interior mask, in
    one block and in row blocks fitted by threads (the second fit of the chosen curve
    shape in reconstruct relies on it)."""
    import smdinspect.sff._depth as depth

    monkeypatch.setattr(depth, "FIT_BLOCK_PX", 300 * 64)  # 300 x 300 -> 5 blocks
    rng = np.random.default_rng(7)
    z = np.arange(12) * 0.05
    mu = rng.uniform(0.0, 0.6, shape)  # some peaks on the first / last frame
    sigma = rng.uniform(0.04, 0.1, shape)
    amp = rng.uniform(10, 1000, shape)
    vol = _gauss_curves(z, mu, sigma, amp, floor=2.0)
    vol += rng.normal(0, 3.0, vol.shape).astype(np.float32)
    tr = _track(np.maximum(vol, 0))
    for p in (1.0, 3.0):
        full = fit_peaks(tr, z, method=FitMethod.POWER, power=p, workers=2)
        height, interior = fit_peaks(tr, z, method=FitMethod.POWER, power=p, workers=2,
                                     heights_only=True)
        assert 0 < interior.sum() < interior.size
        np.testing.assert_array_equal(interior, full.interior)
        np.testing.assert_array_equal(height, full.height_mm)


def test_power_fit_judges_a_clean_gaussian_peak_by_its_noise_not_its_shape(curves):
    """Pertuz's R measures the noise on a focus curve: a clean peak shaped as a Gaussian
    (a narrow-band texture, a disc-like PSF) is as reliable under the power fit as under
    a Gaussian one, while the same peak with noise of 15 % of its height is not."""
    z, mu, sigma, amp = curves
    sigma = np.maximum(sigma, 0.08)   # wide peaks: 5-7 samples of support, R is judged
    clean = _gauss_curves(z, mu, sigma, amp)
    fit = fit_peaks(_track(clean), z, method=FitMethod.POWER, power=1.0)
    assert fit.interior.all()
    assert np.all(fit.reliability_db > 40)
    # the power law alone misjudges it: this is what R read before both shapes were tried
    p1 = (amp / (1 + ((z[:, None, None] - mu) / sigma) ** 2)).astype(np.float32)
    assert np.all(fit_peaks(_track(p1), z, method=FitMethod.POWER, power=1.0).reliability_db > 40)
    rng = np.random.default_rng(3)
    noisy = clean + (0.15 * amp * rng.standard_normal(clean.shape)).astype(np.float32)
    r = fit_peaks(_track(noisy), z, method=FitMethod.POWER, power=1.0).reliability_db
    assert np.median(r) < 26
