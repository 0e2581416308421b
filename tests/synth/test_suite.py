"""The gather renderer, the randomised scenes and textures, and random cases."""

import json

import cv2
import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.stack import FocalStack
from smdinspect.synth import (
    PSF_KINDS,
    SCENE_KINDS,
    TEST_SEEDS,
    TEXTURE_KINDS,
    TUNING_SEEDS,
    Case,
    GatherNoise,
    add_highlight,
    bore,
    case_stack,
    cone,
    half_textured,
    random_case,
    render_gather,
    slanted_plane,
    sphere_cap,
    steps,
    texture,
)

OFF16 = GatherNoise.off(bit_depth=16, exposure=1.0)
SCENES = (cone, slanted_plane, steps, sphere_cap, bore, half_textured)


def test_seed_ranges_are_disjoint():
    assert not set(TUNING_SEEDS) & set(TEST_SEEDS)


def test_random_case_is_deterministic():
    a, b = random_case(TEST_SEEDS[0], size_px=64), random_case(TEST_SEEDS[0], size_px=64)
    assert a.name == b.name and a.params == b.params
    np.testing.assert_array_equal(a.z_mm, b.z_mm)
    for fa, fb in zip(a.frames, b.frames, strict=True):
        np.testing.assert_array_equal(fa, fb)
    c = random_case(TEST_SEEDS[1], size_px=64)
    assert c.params != a.params
    json.dumps(a.params)  # the params go into stack.json


@pytest.mark.parametrize("seed", TEST_SEEDS[:16])
def test_random_case_fields_and_ranges(seed):
    c = random_case(seed, size_px=64)
    p = c.params
    assert isinstance(c, Case) and c.name.startswith(f"suite-{seed:05d}-")
    assert 6 <= len(c.frames) <= 40 and len(c.frames) == len(c.z_mm) == p["n_frames"]
    assert c.z_mm.dtype == np.float64 and np.all(np.diff(c.z_mm) > 0)
    np.testing.assert_allclose(np.diff(c.z_mm), c.step_mm)
    assert c.z_mm[0] < c.height_mm.min() and c.z_mm[-1] > c.height_mm.max()
    assert c.height_mm.shape == (64, 64) and c.height_mm.dtype == np.float32
    want = np.uint8 if p["noise"]["bit_depth"] == 8 else np.uint16
    shape = (64, 64) if p["tint"] is None else (64, 64, 3)
    assert all(f.shape == shape and f.dtype == want for f in c.frames)
    assert 0.3 <= p["step_per_dof"] <= 3.0
    np.testing.assert_allclose(p["blur_px_per_mm"] * c.step_mm,
                               p["step_per_dof"] / np.sqrt(2.0), rtol=1e-9)
    assert 1.0 <= p["magnification_change"] <= 2.0
    assert 0.005 <= p["contrast"] <= 0.3 and 0.03 <= p["freq_cyc_px"] <= 0.35
    assert p["scene"] in SCENE_KINDS and p["texture"] in TEXTURE_KINDS and p["psf"] in PSF_KINDS
    assert (c.textured is not None) == (p["scene"] == "half_textured")


def test_random_case_kind_forced():
    c = random_case(TEST_SEEDS[2], size_px=64, kind="half_textured")
    assert c.params["scene"] == "half_textured"
    assert c.textured.shape == (64, 64)
    assert c.textured[:, :32].all() and not c.textured[:, 32:].any()


@pytest.mark.parametrize("psf", PSF_KINDS)
def test_pixel_is_sharpest_in_the_frame_nearest_its_height(psf):
    rad, h = slanted_plane(size_px=96, low_mm=0.0, high_mm=1.0, seed=2)
    z = np.linspace(-0.05, 1.05, 12)
    frames = render_gather(rad, h, z, blur_px_per_mm=10.0, psf=psf, noise=OFF16, seed=1)
    energy = np.stack([
        cv2.boxFilter(cv2.Laplacian(f.astype(np.float32), cv2.CV_32F) ** 2, -1, (9, 9))
        for f in frames])
    best = energy.argmax(axis=0)[8:-8, 8:-8]
    nearest = np.abs(z[:, None, None] - h[None]).argmin(axis=0)[8:-8, 8:-8]
    assert np.mean(best == nearest) > 0.9
    assert np.all(np.abs(best - nearest) <= 1)


def _dots(n=96, radius=20.0):
    rad = np.full((n, n), 0.1, np.float32)
    c = (n - 1) / 2
    ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    for a in ang:
        cv2.circle(rad, (int(round(c + radius * np.cos(a))), int(round(c + radius * np.sin(a)))),
                   2, 0.9, -1)
    return cv2.GaussianBlur(rad, (0, 0), 1.0)


def _dot_radii(img):
    _, _, _, cen = cv2.connectedComponentsWithStats((img > img.mean() * 1.5).astype(np.uint8))
    c = (img.shape[0] - 1) / 2
    return np.hypot(cen[1:, 0] - c, cen[1:, 1] - c)


@pytest.mark.parametrize("m, factor", [(0.5, 1.5), (1.0, 2.0), (-0.3, 0.7)])
def test_magnification_scales_about_the_centre(m, factor):
    rad = _dots()
    h = np.zeros(rad.shape, np.float32)
    f0, f1 = render_gather(rad, h, [0.0, 1.0], blur_px_per_mm=0.0, magnification_per_mm=m,
                           z_ref_mm=0.0, noise=OFF16)
    r0, r1 = _dot_radii(f0), _dot_radii(f1)
    assert len(r0) == len(r1) == 8
    np.testing.assert_allclose(r0, 20.0, atol=0.6)
    np.testing.assert_allclose(r1.mean() / r0.mean(), factor, rtol=0.01)


@pytest.mark.parametrize("photons, read", [(0.0, 0.02), (1000.0, 0.0), (2000.0, 0.01)])
def test_noise_has_the_requested_std(photons, read):
    rad = np.full((128, 128), 0.5, np.float32)
    cfg = GatherNoise(photons_full_scale=photons, read_noise=read, exposure=1.0, bit_depth=16)
    (frame,) = render_gather(rad, rad * 0, [0.0], blur_px_per_mm=1.0, noise=cfg, seed=3)
    v = frame / 65535.0
    want = np.sqrt(0.5 / photons + read**2) if photons else read
    assert v.mean() == pytest.approx(0.5, abs=0.002)
    assert v.std() == pytest.approx(want, rel=0.05)


def test_flicker_and_vignetting():
    rad = np.full((64, 64), 0.5, np.float32)
    cfg = GatherNoise.off(flicker=0.05, vignetting=0.3, exposure=1.0, bit_depth=16)
    frames = render_gather(rad, rad * 0, np.arange(8.0), blur_px_per_mm=0.0, noise=cfg)
    centre = np.array([f[31:33, 31:33].mean() / 65535 for f in frames])
    assert np.all(np.abs(centre / 0.5 - 1) <= 0.05 + 1e-3) and centre.std() > 0.002
    f = frames[0].astype(float)
    assert f[0, 0] / f[31:33, 31:33].mean() == pytest.approx(0.7, abs=0.01)


def test_disc_and_gauss_differ_and_default_noise_is_deterministic():
    rad, h = cone(size_px=64, seed=4)
    g = render_gather(rad, h, [0.5], blur_px_per_mm=6.0, psf="gauss", seed=5)
    d = render_gather(rad, h, [0.5], blur_px_per_mm=6.0, psf="disc", seed=5)
    assert not np.array_equal(g[0], d[0])
    np.testing.assert_array_equal(g[0], render_gather(rad, h, [0.5], blur_px_per_mm=6.0,
                                                      psf="gauss", seed=5)[0])


@pytest.mark.parametrize("fn", SCENES)
def test_scene_shapes_and_height_range(fn):
    out = fn(size_px=64, low_mm=0.2, high_mm=0.9, seed=1)
    rad, h = out[0], out[1]
    assert rad.shape == h.shape == (64, 64) and rad.dtype == h.dtype == np.float32
    assert 0 <= rad.min() and rad.max() <= 1
    assert h.min() == pytest.approx(0.2, abs=1e-6) and h.max() == pytest.approx(0.9, abs=0.02)
    tex = np.dstack([texture("weave", 64, seed=2)] * 3)
    assert fn(size_px=64, texture=tex)[0].shape == (64, 64, 3)


def test_scene_geometry():
    _, h = bore(size_px=64, low_mm=0.0, high_mm=1.0)
    assert h[32, 32] == 0.0 and h[0, 0] == 1.0
    _, h = steps(size_px=64, n_steps=4)
    np.testing.assert_allclose(np.unique(h), [0, 1 / 3, 2 / 3, 1], atol=1e-6)
    _, h = steps(size_px=64, n_steps=4, riser_px=3.0)
    assert len(np.unique(h)) > 4
    _, h = cone(size_px=65)
    assert h[32, 32] == pytest.approx(1.0) and h[0, 0] == 0.0
    rad, _, mask = half_textured(size_px=64)
    assert np.ptp(rad[:, 32:]) == 0 and rad[:, :32].std() > 0.05 and mask.sum() == 64 * 32


@pytest.mark.parametrize("kind", TEXTURE_KINDS)
def test_textures(kind):
    t = texture(kind, 64, seed=1, freq_cyc_px=0.1, contrast=0.1)
    assert t.shape == (64, 64) and t.dtype == np.float32 and 0 <= t.min() and t.max() <= 1
    np.testing.assert_array_equal(t, texture(kind, 64, seed=1, freq_cyc_px=0.1, contrast=0.1))
    assert not np.array_equal(t, texture(kind, 64, seed=2, freq_cyc_px=0.1, contrast=0.1))
    if kind != "marks":  # marks: contrast is the depth of the marks, not the RMS
        assert t.std() / t.mean() == pytest.approx(0.1, rel=0.05)


def test_band_texture_peaks_at_its_frequency():
    t = texture("band", 128, seed=1, freq_cyc_px=0.2, contrast=0.1)
    p = np.abs(np.fft.rfft2(t - t.mean())) ** 2
    f = np.hypot(np.fft.fftfreq(128)[:, None], np.fft.rfftfreq(128)[None, :])
    bins = np.digitize(f, np.linspace(0, 0.5, 21))
    radial = [p[bins == k].mean() for k in range(1, 21)]
    assert abs((np.argmax(radial) + 0.5) * 0.025 - 0.2) <= 0.03


def test_highlight_is_smooth_and_bright():
    rad = texture("band", 64, seed=1, contrast=0.05)
    out = add_highlight(rad, seed=3, strength=0.4)
    diff = out - rad
    assert diff.max() > 0.3 and diff.min() >= 0 and out.max() <= 1


def test_case_stack_round_trip(tmp_path):
    case = random_case(TEST_SEEDS[3], size_px=64)
    root = case_stack(case, tmp_path / "s")
    stack = FocalStack.open(root)
    np.testing.assert_allclose(stack.z_mm, case.z_mm)
    assert stack.pixel_size_mm == pytest.approx(case.pixel_size_mm)
    np.testing.assert_array_equal(stack.read_frame(0), case.frames[0])
    assert stack.meta["params"]["scene"] == case.params["scene"]
    assert (root / "truth" / "height_mm.tiff").is_file()


@pytest.mark.parametrize("call, match", [
    (lambda r, h: render_gather(r, h, [0.0], blur_px_per_mm=-1.0), "blur_px_per_mm must be >= 0"),
    (lambda r, h: render_gather(r, h, [0.0], blur_px_per_mm=1.0, sigma0_px=float("nan")),
     "sigma0_px must be a finite number"),
    (lambda r, h: render_gather(r, h, [0.0], blur_px_per_mm=1.0, psf="box"), "psf must be one of"),
    (lambda r, h: render_gather(r, h, [], blur_px_per_mm=1.0), "z_mm must be a non-empty"),
    (lambda r, h: render_gather(r, h[:8], [0.0], blur_px_per_mm=1.0), "height_mm must have shape"),
    (lambda r, h: render_gather(r - 1, h, [0.0], blur_px_per_mm=1.0), "radiance must be >= 0"),
    (lambda r, h: render_gather(r, h, [0.0, 10.0], blur_px_per_mm=1.0, magnification_per_mm=-1),
     "magnification_per_mm"),
    (lambda r, h: render_gather(r, h, [0.0], blur_px_per_mm=1.0, noise="high"),
     "noise must be a GatherNoise"),
    (lambda r, h: render_gather(r, h, [0.0], blur_px_per_mm=1.0, seed=-1), "seed must be"),
    (lambda r, h: GatherNoise(read_noise=-0.1), "read_noise must be >= 0"),
    (lambda r, h: GatherNoise(bit_depth=12), "bit_depth must be 8 or 16"),
    (lambda r, h: texture("stripes", 64, seed=0), "kind must be one of"),
    (lambda r, h: texture("band", 64, seed=0, freq_cyc_px=0.7), "freq_cyc_px must be <= 0.5"),
    (lambda r, h: cone(size_px=8), "size_px must be an integer >= 16"),
    (lambda r, h: cone(low_mm=1.0, high_mm=0.5), "high_mm must be >= low_mm"),
    (lambda r, h: steps(size_px=64, n_steps=1), "n_steps must be an integer"),
    (lambda r, h: random_case(TEST_SEEDS[0], kind="torus"), "kind must be one of"),
    (lambda r, h: case_stack("case", "/tmp/x"), "case must be a Case"),
])
def test_bad_arguments_raise_input_error(call, match):
    rad, h = slanted_plane(size_px=32)
    with pytest.raises(InputError, match=match):
        call(rad, h)


# --------------------------------------------------------------------------------------
# A board scene photographed by the gather model (benchmarks/inspection.py --renderer gather)


def _flat_scene(albedo, height_mm=0.0, specular=None, pixel_mm=0.02):
    from smdinspect.synth import Scene

    h = np.full(albedo.shape[:2], height_mm, np.float32)
    return Scene(height_mm=h, albedo=albedo, pixel_size_mm=pixel_mm, specular=specular)


def test_shade_dome_keeps_a_flat_matte_surface_at_its_albedo_and_flat_metal_glints():
    from smdinspect.synth._suite import shade_dome

    alb = np.full((64, 64), 0.5, np.float32)
    for seed in range(5):
        rad, params = shade_dome(_flat_scene(alb), np.random.default_rng(seed))
        # the second texture modulates the albedo around its mean, nothing else changes
        assert abs(float(rad.mean()) - 0.5) < 0.02, params
        spec = np.ones_like(alb)
        metal, params = shade_dome(_flat_scene(alb, specular=spec), np.random.default_rng(seed))
        # flat metal mirrors the coaxial light: env·albedo + coaxial gain·tint (+ the ring's tail)
        assert float(metal.mean()) > 0.75 * 0.4 * params["coaxial_gain"], params


def test_gather_board_stack_sees_heights_and_the_parallax_of_a_moving_camera(tmp_path):
    import dataclasses

    from smdinspect.optics import Optics
    from smdinspect.synth._suite import gather_board_stack

    h0 = 0.6
    scene = _flat_scene(_dots(160, 60.0), height_mm=h0)
    optics = dataclasses.replace(Optics.for_pixel_size(0.02, telecentric=False),
                                 aperture_mm=0.2)   # sharp dots: their centres, not blur
    z = [-2.0, h0, 4.0]

    def radii(stack):
        out = []
        for k in range(len(stack)):
            img = stack.read_frame(k).astype(np.float32)
            r = _dot_radii(img.mean(axis=2) if img.ndim == 3 else img)
            assert len(r) == 8
            out.append(r.mean())
        return np.array(out)

    stack = gather_board_stack(scene, z, tmp_path / "ord", optics=optics, noise=OFF16,
                               seed=3)
    assert isinstance(stack, FocalStack) and len(stack) == 3
    # a point at height h0 seen from the frame focused at z: scale_at(h0, z) times as far
    # from the centre as in the frame focused on it (±2.3 % here)
    r = radii(stack)
    np.testing.assert_allclose(r / r[1], optics.scale_at(h0, np.array(z)), rtol=0.002)
    tele = gather_board_stack(scene, z, tmp_path / "tele",
                              optics=dataclasses.replace(optics, telecentric=True),
                              noise=OFF16, seed=3)
    np.testing.assert_allclose(radii(tele), r[1], rtol=0.002)
