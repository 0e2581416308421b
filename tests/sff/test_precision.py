"""The precision of a measured height from the even/odd split of its focus curve, the
precision cue built on it, and the slope bound on coarse fills. Stacks from the
independent gather renderer (smdinspect.synth._suite), test seeds only."""

import numpy as np

from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.sff._depth import _split_difference
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import GatherNoise, render_gather, slanted_plane, texture

STEP = 0.07


def _stack(tmp_path, frames, z, name):
    w = StackWriter(tmp_path / name, pixel_size_mm=0.01)
    for f, zn in zip(frames, z):
        w.add_frame(f, float(zn))
    w.write_manifest()
    return FocalStack.open(tmp_path / name)


def _weak_plane(tmp_path, *, noise_seed, contrast=0.08, high_mm=1.0, name="p", seed=10_013):
    """A weakly textured slanted plane at a fine step (0.6 depth of field per step: wide
    focus curves), rendered with sensor noise drawn from ``noise_seed``."""
    n = 128
    tex = texture("band", n, seed=seed, freq_cyc_px=0.12, contrast=contrast)
    radiance, height = slanted_plane(size_px=n, low_mm=0.0, high_mm=high_mm, texture=tex,
                                     seed=seed)
    z = np.arange(-0.2, high_mm + 0.2 + 1e-9, STEP)
    frames = render_gather(radiance, height, z, blur_px_per_mm=0.6 * 0.3536 / STEP,
                           sigma0_px=0.5, noise=GatherNoise(), seed=noise_seed)
    return _stack(tmp_path, frames, z, name), height


def test_split_difference_of_an_exact_peak_is_zero():
    # q = (u - 0.3)^2 + 1 sampled at -3..3: both halves find the vertex at 0.3
    u = [np.full((2, 2), j - 3.0, np.float32) for j in range(7)]
    q = [(a - 0.3) ** 2 + 1 for a in u]
    y = [a ** -0.5 for a in q]
    support = [np.ones((2, 2), bool)] * 7
    d = _split_difference(u, q, y, support, k=3)
    np.testing.assert_allclose(d, 0.0, atol=1e-5)
    # a half without 3 supported samples gives no estimate
    support = [np.ones((2, 2), bool)] * 7
    support[5] = np.zeros((2, 2), bool)  # k + 2 missing: the even half has 2 samples
    assert np.isnan(_split_difference(u, q, y, support, k=3)).all()


def test_precision_matches_the_spread_of_repeated_sweeps(tmp_path):
    """Two sweeps of the same scene with independent noise: their heights differ by the
    random error alone, RMS √2·σ. The precision each sweep reports from its own frames
    must match that σ (no ground truth needed: this is how a user checks a gauge)."""
    cfg = FocusConfig(prefilter_px=0, coarse_factor=0, min_confidence=0.0, support_steps=0)
    a, _ = _weak_plane(tmp_path, noise_seed=10_101, name="a")
    b, _ = _weak_plane(tmp_path, noise_seed=10_102, name="b")
    sa, sb = reconstruct(a, cfg), reconstruct(b, cfg)
    both = (sa.confidence > 0) & (sb.confidence > 0)
    m = 12  # away from the border
    inner = np.zeros_like(both)
    inner[m:-m, m:-m] = True
    diff = (sa.height_mm - sb.height_mm)[both & inner] / STEP
    observed = 1.4826 * np.median(np.abs(diff)) / np.sqrt(2)  # robust σ of one sweep
    reported = np.nanmedian(np.concatenate([s.precision_mm[both & inner] for s in (sa, sb)])) / STEP
    assert 0.7 < reported / observed < 1.4, (reported, observed)  # measured 0.90


def test_precision_cue_rejects_imprecise_heights_and_keeps_precise_ones(tmp_path):
    stack, truth = _weak_plane(tmp_path, noise_seed=10_103)
    # without the noise pre-filter the 9-px window is noise-dominated: RMS ~0.37 Δd
    raw = reconstruct(stack, FocusConfig(prefilter_px=0, coarse_factor=0))
    # the pre-filter keeps the derivative off the noise-only band: RMS ~0.13 Δd
    clean = reconstruct(stack, FocusConfig(coarse_factor=0))
    assert clean.meta["prefilter"]["sigma_px"] > 0
    assert raw.reliable.mean() < 0.25, raw.reliable.mean()
    assert clean.reliable.mean() > 0.85, clean.reliable.mean()
    err = np.abs(clean.height_mm - truth)[clean.reliable] / STEP
    assert np.mean(err > 1) < 0.01
    # the reported precision is finite where the heights are reliable and small there
    p = clean.precision_mm[clean.reliable] / STEP
    assert np.isfinite(p).mean() > 0.9
    assert np.nanmedian(p) < 0.2


def test_precision_is_unknown_at_coarse_steps(tmp_path):
    """Two samples a side of a narrow peak: a half misses it, nothing to split; the cue
    does not judge (NaN precision, heights kept by the other cues)."""
    tex = texture("band", 96, seed=10_104, freq_cyc_px=0.2, contrast=0.25)
    radiance, height = slanted_plane(size_px=96, low_mm=0.0, high_mm=1.0, texture=tex,
                                     seed=10_104)
    z = np.arange(-0.2, 1.2 + 1e-9, 0.12) + 0.013
    frames = render_gather(radiance, height, z, blur_px_per_mm=3.0 * 0.3536 / 0.12,
                           sigma0_px=0.5, noise=GatherNoise(read_noise=0.002), seed=10_104)
    s = reconstruct(_stack(tmp_path, frames, z, "coarse"), FocusConfig())
    assert s.reliable.mean() > 0.7
    assert np.isnan(s.precision_mm[s.reliable]).mean() > 0.9


def test_coarse_fills_stop_where_the_slope_under_the_window_could_bias_them(tmp_path):
    """A coarse window reads its footprint's energy-weighted mean height: on a plane
    steep against its footprint it is not filled from; on a gentle one it is."""
    cfg = FocusConfig(prefilter_px=0)
    fills = {}
    # 0.6 mm over the 181-px diagonal: 0.047 steps/px, |∇h|·28/4 px = 0.33 step (filled);
    # 2.5 mm: 0.2 steps/px, 1.4 steps (not filled)
    for name, high in (("gentle", 0.6), ("steep", 2.5)):
        stack, truth = _weak_plane(tmp_path, noise_seed=10_105, contrast=0.12, high_mm=high,
                                   name=name)
        s = reconstruct(stack, cfg)
        fills[name] = s.meta["coarse_fraction"]
        err = np.abs(s.height_mm - truth)[s.reliable] / STEP
        assert np.mean(err > 1) < 0.01, (name, np.mean(err > 1))
    assert fills["gentle"] > 0.08, fills  # measured 0.16
    assert fills["steep"] < 0.03, fills  # measured 0.014


def test_reconstruct_command_reports_the_random_error(tmp_path, capsys):
    import re

    from smdinspect.cli import main

    _weak_plane(tmp_path, noise_seed=10_106, name="cli")
    assert main(["-q", "reconstruct", str(tmp_path / "cli"), "--out", str(tmp_path / "out"),
                 "--outputs", "precision_mm.tiff"]) == 0
    out = capsys.readouterr().out
    m = re.search(r"random error \(1σ, from the frames' noise\) median ([0-9.]+) µm, known for "
                  r"([0-9]+)% of the reliable pixels", out)
    assert m, out
    assert 0 < float(m.group(1)) < 0.2 * STEP * 1000 and int(m.group(2)) > 80
    assert (tmp_path / "out" / "precision_mm.tiff").is_file()
    # and per point in the cloud, as Open3D reads it
    import open3d as o3d
    import tifffile

    assert main(["-q", "reconstruct", str(tmp_path / "cli"), "--out", str(tmp_path / "out2"),
                 "--outputs", "cloud.ply,precision_mm.tiff,confidence.tiff"]) == 0
    cloud = o3d.t.io.read_point_cloud(str(tmp_path / "out2" / "cloud.ply"))
    per_point = cloud.point.precision.numpy().ravel()
    conf = tifffile.imread(tmp_path / "out2" / "confidence.tiff")
    plane = tifffile.imread(tmp_path / "out2" / "precision_mm.tiff")
    np.testing.assert_array_equal(np.sort(per_point), np.sort(plane[conf >= 0.5]))
