"""The renderer: blur from the thin-lens optics, focus, occlusion, sensor, determinism."""

import json
import math

import cv2
import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.optics import Optics
from smdinspect.stack import FocalStack, read_image
from smdinspect.synth import (
    Lighting,
    Scene,
    SensorConfig,
    band_limited_texture,
    frame_rng,
    render_frame,
    render_optical,
    render_stack,
    shade,
    slanted_plane_scene,
    staircase_scene,
)

OFF = SensorConfig.preset("off")


def _dot_scene(n=96, height=0.0, dots=((48, 48),), pixel=0.015):
    alb = np.zeros((n, n), np.float32)
    for r, c in dots:
        alb[r, c] = 1.0
    return Scene(np.full((n, n), height, np.float32), alb, pixel)


def _moments(img):
    img = np.asarray(img, np.float64)
    r, c = np.indices(img.shape)
    w = img.sum()
    cr, cc = (img * r).sum() / w, (img * c).sum() / w
    return cr, cc, math.sqrt((img * (c - cc) ** 2).sum() / w)


@pytest.mark.parametrize("defocus_mm", [0.0, 0.2, 0.45, 1.2])
def test_rendered_blur_matches_thin_lens_sigma(defocus_mm):
    optics = Optics(sigma0_px=1.0)  # a sampled Gaussian of σ < 1 px has a smaller moment
    scene = _dot_scene(n=160 if defocus_mm > 1 else 96, dots=((80, 80),) if defocus_mm > 1
                       else ((48, 48),))
    img = render_optical(scene, defocus_mm, optics=optics,
                         lighting=Lighting(ambient=1.0, lights=((0, 90, 0.0),)))
    sigma = float(optics.blur_sigma_px(0.0, defocus_mm))
    # by hand: u = d_f + defocus, C = D v |1/f - 1/u - 1/v|, sigma = hypot(s0, k C / pitch)
    u = 100.0 + defocus_mm
    c = abs(50.0 * 100.0 * (1 / 50.0 - 1 / u - 1 / 100.0))
    assert sigma == pytest.approx(math.hypot(1.0, optics.k * c / 0.015), rel=1e-9)
    assert img.sum() == pytest.approx(1.0, rel=2e-3)  # energy is preserved
    _, _, s = _moments(img)
    assert s == pytest.approx(sigma, rel=0.04 if sigma < 4 else 0.06)


def _sml(frame, win=9):
    g = frame.astype(np.float32)
    k = np.array([[1, -2, 1]], np.float32)
    ml = np.abs(cv2.filter2D(g, -1, k)) + np.abs(cv2.filter2D(g, -1, k.T))
    return cv2.boxFilter(ml * ml, -1, (win, win))


def test_pixels_at_the_frame_height_are_sharpest_in_that_frame():
    scene = slanted_plane_scene(size_px=128, rise_mm=0.8, base_mm=0.1, seed=5)
    z = 0.1 + 0.05 * np.arange(17)  # 0.1 .. 0.9; the plane spans 0.1 .. 0.9
    frames = render_stack(scene, z, optics=Optics(), sensor=SensorConfig(), seed=1)
    fm = np.stack([_sml(f) for f in frames])
    best = fm.argmax(axis=0)
    h = scene.height_mm
    inner = np.zeros(h.shape, bool)
    inner[8:-8, 8:-8] = True
    for n in range(2, len(z) - 2):
        at = inner & (np.abs(h - z[n]) < 0.004)
        assert at.sum() > 50
        # the sharpest frame of those pixels is frame n, for nearly all of them
        assert np.mean(best[at] == n) > 0.9, n
        # and on average frame n beats its neighbours clearly
        assert fm[n][at].mean() > 1.3 * max(fm[n - 1][at].mean(), fm[n + 1][at].mean())


def test_staircase_terraces_peak_in_their_own_frame():
    scene = staircase_scene(size_px=128, n_steps=4, step_mm=0.25, seed=2)
    z = np.array([0.0, 0.25, 0.5, 0.75, 0.125, 0.375, 0.625, -0.1, 0.85])
    frames = render_stack(scene, z, optics=Optics(), seed=3)
    fm = np.stack([_sml(f) for f in frames])
    for k in range(4):
        cols = slice(k * 32 + 8, k * 32 + 24)  # terrace interiors, away from risers
        want = int(np.flatnonzero(np.isclose(z, 0.25 * k))[0])
        assert np.all(fm[:, 8:-8, cols].mean(axis=(1, 2)).argmax() == want)


def test_higher_edge_stays_sharp_over_defocused_background():
    optics = Optics(sigma0_px=0.0)
    n = 96
    h = np.zeros((n, n), np.float32)
    h[:, 48:] = 0.6  # raised block on the right, riser at col 48
    alb = band_limited_texture((n, n), seed=9, contrast=0.2)
    scene = Scene(h, alb, 0.015)
    light = Lighting(ambient=1.0, lights=((0, 90, 0.0),))  # pure albedo, no shading
    sharp = shade(scene, lighting=light)
    top = render_optical(scene, 0.6, optics=optics, lighting=light)
    # focused on the block: its pixels from the edge on are the sharp albedo
    np.testing.assert_allclose(top[:, 49:], sharp[:, 49:], atol=2e-3)
    # the defocused background next to it is blurred, and not blurred with the block
    bg = float(optics.blur_sigma_px(0.0, 0.6))
    assert bg > 6
    blurred_bg = cv2.GaussianBlur(sharp[:, :48], (0, 0), bg, borderType=cv2.BORDER_REFLECT)
    assert np.abs(top[:, :30] - blurred_bg[:, :30]).max() < 0.03
    # focused on the background: the defocused block spreads over it (the edge is soft)
    low = render_optical(scene, 0.0, optics=optics, lighting=light)
    far = np.abs(low[:, :20] - sharp[:, :20]).max()
    near = np.abs(low[:, 44:48] - sharp[:, 44:48]).mean()
    assert far < 2e-3 < 0.02 < near
    # a per-pixel blur would keep the block's edge pixel sharp; here it is blurred
    assert np.abs(low[:, 48] - sharp[:, 48]).mean() > 0.02


def test_same_seed_same_bytes_and_single_frames_match(tmp_path):
    scene = staircase_scene(size_px=64, n_steps=2, step_mm=0.2, seed=1)
    z = [0.3, 0.2, 0.1, 0.0]
    a = render_stack(scene, z, optics=Optics(), seed=11, out=tmp_path / "a", previews=False)
    b = render_stack(scene, z, optics=Optics(), seed=11, out=tmp_path / "b", previews=False)
    c = render_stack(scene, z, optics=Optics(), seed=12, out=tmp_path / "c", previews=False)
    for fa, fb, fc in zip(a.frames, b.frames, c.frames):
        assert fa.path.read_bytes() == fb.path.read_bytes()
        assert fa.path.read_bytes() != fc.path.read_bytes()
    # one frame alone (as the simulated camera renders it) equals the stack's frame
    alone = render_frame(scene, 0.1, optics=Optics(), sensor=SensorConfig(), rng=11)
    np.testing.assert_array_equal(alone, read_image(a.frames[1].path))
    alone2 = render_frame(scene, 0.1, optics=Optics(), rng=frame_rng(11, 0.1))
    np.testing.assert_array_equal(alone, alone2)


def test_sixteen_bit_frames(tmp_path):
    scene = slanted_plane_scene(size_px=64, rise_mm=0.3)
    st = render_stack(scene, [0.0, 0.1, 0.2], optics=Optics(),
                      sensor=SensorConfig(bit_depth=16), seed=0, out=tmp_path / "s",
                      previews=False)
    img = st.read_frame(0)
    assert img.dtype == np.uint16 and img.ndim == 2
    assert img.max() > 20000
    # 16-bit resolves levels finer than 8-bit: many distinct values within one 8-bit bin
    assert len(np.unique(img[(img >> 8) == np.median(img >> 8)])) > 20


def test_sensor_noise_and_flicker_statistics():
    n = 128
    scene = Scene(np.zeros((n, n), np.float32), np.full((n, n), 0.5, np.float32), 0.015)
    sensor = SensorConfig()
    light = Lighting(ambient=1.0, lights=((0, 90, 0.0),))
    means = []
    for i, z in enumerate(np.linspace(-0.5, 0.5, 12)):
        f = render_frame(scene, z, optics=Optics(), sensor=sensor, rng=4, lighting=light)
        assert f.dtype == np.uint8
        e = 0.5 * sensor.exposure * sensor.full_well_e
        want = math.sqrt(e + sensor.read_noise_e**2) * 255 / sensor.full_well_e
        assert f.astype(float).std() == pytest.approx(want, rel=0.15)
        means.append(f.mean())
    nominal = 0.5 * sensor.exposure * 255
    rel = np.array(means) / nominal - 1
    assert np.abs(rel).max() < sensor.flicker + 0.004
    assert rel.std() > 0.002  # frames do flicker
    # no noise at all with the "off" preset
    f = render_frame(scene, 0.0, optics=Optics(), sensor=OFF, rng=0, lighting=light)
    assert f.std() == 0


def test_jitter_shifts_by_the_documented_draws():
    scene = _dot_scene(n=64, dots=((32, 32),))
    optics = Optics(sigma0_px=1.0)
    light = Lighting(ambient=1.0, lights=((0, 90, 0.0),))
    sensor = SensorConfig(bit_depth=16, shot_noise=False, read_noise_e=0.0, flicker=0.0,
                          jitter_px=0.7, exposure=0.02)
    still = render_frame(scene, 0.0, optics=optics, sensor=SensorConfig(
        bit_depth=16, shot_noise=False, read_noise_e=0.0, flicker=0.0, exposure=0.02),
        rng=5, lighting=light)
    moved = render_frame(scene, 0.0, optics=optics, sensor=sensor, rng=5, lighting=light)
    g = frame_rng(5, 0.0)
    g.uniform(-1, 1)
    dx, dy = g.standard_normal(2) * 0.7
    r0, c0, _ = _moments(still)
    r1, c1, _ = _moments(moved)
    assert c1 - c0 == pytest.approx(dx, abs=0.05)
    assert r1 - r0 == pytest.approx(dy, abs=0.05)


def test_ordinary_lens_changes_magnification_with_height():
    n = 129
    dots = ((64, 34), (64, 94))
    scene = _dot_scene(n=n, dots=dots)
    light = Lighting(ambient=1.0, lights=((0, 90, 0.0),))
    ordinary = Optics(telecentric=False, sigma0_px=1.0)
    tele = Optics(telecentric=True, sigma0_px=1.0)
    z = 0.6  # the dots lie 0.6 mm below the focused plane: u = 100.6 mm, scale 100/100.6
    for optics, want in ((tele, 1.0), (ordinary, 100.0 / 100.6)):
        img = render_optical(scene, z, optics=optics, lighting=light)
        left, right = img[:, :64].copy(), img[:, 65:].copy()
        _, cl, _ = _moments(left)
        _, cr, _ = _moments(right)
        assert (cr + 65 - cl) / 60.0 == pytest.approx(want, abs=0.001)
    assert float(ordinary.scale_at(0.0, z)) == pytest.approx(100 / 100.6)
    # a point on the focused plane keeps its place
    assert float(ordinary.scale_at(z, z)) == 1.0


def test_specular_solder_glints_where_its_normal_bisects_a_light():
    n = 96
    r, c = np.indices((n, n))
    dist = np.hypot(r - 47.5, c - 47.5) * 0.015
    h = np.clip(0.4 - 0.4 * (dist / 0.6) ** 2, 0, None).astype(np.float32)  # dome
    scene = Scene(h, np.full((n, n), 0.8, np.float32), 0.015,
                  specular=np.where(h > 0, 1.0, 0.0).astype(np.float32))
    rad = shade(scene)
    dome = h > 0.02
    board = dist > 0.65
    # bright glint bands and dark slopes on the metal; the flat matte board is uniform
    assert rad[dome].max() > 1.0
    assert np.percentile(rad[dome], 10) < 0.3
    assert rad[board].std() < 1e-4


def test_render_validation(tmp_path):
    scene = slanted_plane_scene(size_px=32)
    with pytest.raises(InputError, match="differs from the optics' object pixel"):
        render_optical(scene, 0.0, optics=Optics(magnification=2.0))
    with pytest.raises(InputError, match="same height twice"):
        render_stack(scene, [0.0, 0.1, 0.1], optics=Optics())
    with pytest.raises(InputError, match="at least 3"):
        render_stack(scene, [0.0, 0.1], optics=Optics())
    with pytest.raises(InputError, match="bit_depth must be 8 or 16; got 12"):
        SensorConfig(bit_depth=12)
    with pytest.raises(InputError, match="noise preset must be one of off, low, normal, high"):
        SensorConfig.preset("loud")
    with pytest.raises(InputError, match="albedo must lie in \\[0, 1\\]"):
        Scene(np.zeros((8, 8)), np.full((8, 8), 2.0), 0.015)
    with pytest.raises(InputError, match="albedo must have shape"):
        Scene(np.zeros((8, 8)), np.zeros((8, 9)), 0.015)
    with pytest.raises(InputError, match="height_mm must be finite"):
        Scene(np.full((8, 8), np.nan), np.zeros((8, 8)), 0.015)
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        render_stack(scene, [0.0, 0.1, 0.2], optics=Optics(), out=tmp_path / "x")


def test_stack_manifest_and_truth(tmp_path):
    scene = staircase_scene(size_px=64, n_steps=2, step_mm=0.2, color=True)
    z = [0.3, 0.25, 0.2, 0.15, 0.1]
    st = render_stack(scene, z, optics=Optics(), seed=2, out=tmp_path / "s")
    assert isinstance(st, FocalStack)
    np.testing.assert_allclose(st.z_mm, sorted(z))
    assert st.pixel_size_mm == pytest.approx(0.015)
    assert st.read_frame(0).shape == (64, 64, 3)
    doc = json.loads((tmp_path / "s" / "stack.json").read_text())
    rig = doc["rig"]
    # h_n = d - (d_f + n * step) reproduces every frame's z
    for i, f in enumerate(doc["frames"]):
        assert rig["d_mm"] - (rig["d_f_mm"] + i * rig["step_mm"]) == pytest.approx(f["z_mm"])
    assert Optics.from_dict(doc["optics"]) == Optics()
    truth = tmp_path / "s" / "truth"
    import tifffile

    h = tifffile.imread(truth / "height_mm.tiff")
    assert h.dtype == np.float32
    np.testing.assert_array_equal(h, scene.height_mm)
    np.testing.assert_array_equal(np.load(truth / "height_mm.npy"), scene.height_mm)
    meta = json.loads((truth / "scene.json").read_text())
    assert meta["name"] == "staircase" and meta["seed"] == 2
    for png in ("height_mm.png", "radiance.png", "frames.png"):
        assert (truth / png).stat().st_size > 1000
    # overwrite removes the earlier stack and writes a fresh one
    st2 = render_stack(scene, z[:3], optics=Optics(), seed=2, out=tmp_path / "s",
                       overwrite=True, previews=False)
    assert len(st2) == 3 and not (truth / "frames.png").exists()
