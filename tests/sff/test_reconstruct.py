"""Shape from focus end to end on rendered stacks with known heights."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.optics import Optics
from smdinspect.sff import FitMethod, FocusConfig, estimate_alignment, reconstruct
from smdinspect.stack import FocalStack, StackWriter
from smdinspect.synth import (TEST_SEEDS, SensorConfig, cone_scene, half_textured_scene,
                              render_frame, render_stack, staircase_scene)

STEP = 0.05
PIXEL = 0.015


def _z(top_mm, step=STEP):
    """Frames from below the base to above the top, offset so no true height sits on a frame."""
    return np.round(np.arange(-0.1, top_mm + 0.1 + 1e-9, step) + 0.013, 6)


@pytest.fixture(scope="module")
def optics():
    return Optics.for_pixel_size(PIXEL)


@pytest.fixture(scope="module")
def cone(tmp_path_factory, optics):
    # 512 px: the flank rises 0.14 Δd per pixel, a slope SFF's 9 px window can follow
    scene = cone_scene(size_px=512, pixel_size_mm=PIXEL, height_mm=1.6, seed=3)
    root = tmp_path_factory.mktemp("cone")
    stack = render_stack(scene, _z(1.6), optics=optics, seed=5, out=root, previews=False)
    return scene, stack


def _rmse_steps(surface, truth, mask):
    err = (surface.height_mm - truth)[mask]
    return float(np.sqrt(np.mean(err**2)) / STEP)


def test_cone_gauss3_accuracy_and_interpolation_beats_argmax(cone):
    scene, stack = cone
    assert len(stack) >= 30
    g3 = reconstruct(stack, FocusConfig(fit="gauss3"))
    am = reconstruct(stack, FocusConfig(fit="argmax"))
    mask = g3.reliable  # the same pixels for both
    assert g3.coverage > 0.95
    rmse_g3 = _rmse_steps(g3, scene.height_mm, mask)
    rmse_am = _rmse_steps(am, scene.height_mm, mask)
    assert rmse_g3 <= 0.10, rmse_g3
    assert rmse_am > 1.5 * rmse_g3, (rmse_am, rmse_g3)


def test_cone_lsq_fit_is_close(cone):
    """Over ±3 frames the SML curve is not quite Gaussian: lsq is a little worse than gauss3."""
    scene, stack = cone
    s = reconstruct(stack, FocusConfig(fit=FitMethod.LSQ))
    assert _rmse_steps(s, scene.height_mm, s.reliable) <= 0.15


def test_staircase_terraces(tmp_path, optics):
    scene = staircase_scene(size_px=160, pixel_size_mm=PIXEL, n_steps=4, step_mm=0.2, seed=1)
    stack = render_stack(scene, _z(0.6), optics=optics, seed=2, out=tmp_path / "s", previews=False)
    s = reconstruct(stack)
    cols = np.arange(160)
    for k in range(4):
        # terrace interior: risers are depth edges, unreliable for half a window + 2 px
        band = (cols >= k * 40 + 12) & (cols < (k + 1) * 40 - 12)
        sel = s.reliable[:, band]
        assert sel.mean() > 0.9
        measured = float(np.median(s.height_mm[:, band][sel]))
        assert abs(measured - 0.2 * k) <= 0.1 * STEP, (k, measured)


def test_half_textured_confidence(tmp_path, optics):
    scene = half_textured_scene(size_px=128, pixel_size_mm=PIXEL, seed=4)
    stack = render_stack(scene, _z(float(scene.height_mm.max()) + 0.3), optics=optics, seed=1,
                         out=tmp_path / "h", previews=False)
    s = reconstruct(stack)
    textured = scene.meta.get("textured_side", "left")
    left, right = s.reliable[:, :54], s.reliable[:, 74:]
    tex, flat = (left, right) if textured == "left" else (right, left)
    assert tex.mean() > 0.9, tex.mean()
    assert flat.mean() < 0.05, flat.mean()
    assert s.confidence.min() >= 0 and s.confidence.max() <= 1


def test_alignment_recovers_magnification_change(tmp_path, optics):
    """0.2 % magnification change per frame: --align restores the accuracy."""
    scene = cone_scene(size_px=192, pixel_size_mm=PIXEL, height_mm=1.2, seed=8)
    z = _z(1.2)
    w = StackWriter(tmp_path / "m", pixel_size_mm=PIXEL)
    plain = StackWriter(tmp_path / "p", pixel_size_mm=PIXEL)
    c = (192 - 1) / 2
    for n, zn in enumerate(z):
        frame = render_frame(scene, zn, optics=optics, sensor=SensorConfig(), rng=n)
        plain.add_frame(frame, zn)
        m = cv2.getRotationMatrix2D((c, c), 0.0, 1.0 + 0.002 * n)
        w.add_frame(cv2.warpAffine(frame, m, (192, 192), flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REFLECT), zn)
    # no noise pre-filter: the resampled frames' spectra differ from the plain ones, and
    # the comparison is of the alignment alone
    ref = reconstruct(FocalStack.open(tmp_path / "p"), FocusConfig(prefilter_px=0))
    raw = reconstruct(FocalStack.open(tmp_path / "m"), FocusConfig(prefilter_px=0))
    aligned = reconstruct(FocalStack.open(tmp_path / "m"), FocusConfig(align=True, prefilter_px=0))
    # the focus ring of a cone moving outwards looks a little like zoom: allow 15 %
    info = aligned.meta["alignment"]
    # the reference grid is the most magnified frame's (the last); frame 0 is the smallest
    assert info["reference_frame"] >= len(z) - 3 and info["ok"]
    per_step = (1 / info["scale_range"][0]) ** (1 / (len(z) - 1)) - 1
    assert per_step == pytest.approx(0.002, rel=0.15)
    assert aligned.field.mean() > 0.95
    assert aligned.coverage > 0.8
    # the output grid is the reference frame's: bring the truth onto it
    m = cv2.getRotationMatrix2D((c, c), 0.0, 1.0 + 0.002 * info["reference_frame"])
    truth = cv2.warpAffine(scene.height_mm, m, (192, 192), flags=cv2.INTER_LINEAR)
    inner = np.zeros((192, 192), bool)
    inner[8:-8, 8:-8] = True
    err_aligned = _rmse_steps(aligned, truth, aligned.reliable & inner)
    err_ref = _rmse_steps(ref, scene.height_mm, ref.reliable & inner)
    err_raw = _rmse_steps(raw, scene.height_mm, raw.reliable & inner)
    assert err_aligned <= 1.5 * err_ref + 0.02
    assert err_aligned < err_raw


def test_colour_stack_keeps_colour_in_aif(tmp_path, optics):
    scene = cone_scene(size_px=96, pixel_size_mm=PIXEL, height_mm=0.4, seed=1, color=True)
    stack = render_stack(scene, _z(0.4), optics=optics, seed=1, out=tmp_path / "c", previews=False)
    s = reconstruct(stack)
    assert s.aif.shape == (96, 96, 3) and s.aif.dtype == np.uint8
    assert np.abs(s.aif[..., 0].astype(int) - s.aif[..., 2]).mean() > 2


def test_mismatched_frame_size_is_an_input_error(tmp_path):
    w = StackWriter(tmp_path / "bad", pixel_size_mm=0.01)
    rng = np.random.default_rng(0)
    for i in range(3):
        w.add_frame(rng.integers(0, 255, (32, 32 if i < 2 else 30), dtype=np.uint8), 0.1 * i)
    with pytest.raises(InputError, match="frame_0002.png is 30x32 px .* all frames must match"):
        reconstruct(FocalStack.open(tmp_path / "bad"))


def test_window_larger_than_image(tmp_path):
    w = StackWriter(tmp_path / "small", pixel_size_mm=0.01)
    for i in range(3):
        w.add_frame(np.zeros((8, 8), np.uint8), 0.1 * i)
    with pytest.raises(InputError, match="window_px must be <= the frame's smaller side"):
        reconstruct(FocalStack.open(tmp_path / "small"))


def test_import_sff_does_not_load_open3d():
    code = "import sys, smdinspect.sff; print('open3d' in sys.modules, 'trimesh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_parallax_moves_a_raised_point_to_its_in_focus_position():
    """Geometry of the correction on an exact alignment: 1 %/mm of magnification lost per
    mm of z, a 2 mm block off centre, the board at 0 with noisy heights in one corner."""
    from smdinspect.sff._align import Alignment

    n = 201
    z = np.linspace(-0.5, 2.5, 13)
    c = (n - 1) / 2

    def about_centre(s):
        return np.array([[s, 0, c - s * c], [0, s, c - s * c], [0, 0, 1.0]])

    scales = np.exp(-0.01 * (z - z[0]))          # the lowest frame is the most magnified
    al = Alignment([about_centre(s) for s in scales], 0, (n, n), np.ones((n, n), bool))
    h = np.zeros((n, n), np.float32)
    h[20:40, 150:180] = 2.0
    rng = np.random.default_rng(TEST_SEEDS[0] + 7)
    h[120:190, 10:80] = rng.normal(0.0, 0.5, (70, 70))   # noise: no pixel should scatter
    h[120:190, 178:198] = np.linspace(1.9, 0.0, 20)[None, :]   # a ramp falling outwards
    rel = np.ones((n, n), bool)
    rel[150:160, 150:160] = False                # an unreliable patch stays put
    src, info = al.parallax_sources(z, h, rel)
    assert info["corrected"] and info["scale_per_mm"] == pytest.approx(np.expm1(-0.01), abs=1e-6)
    assert info["reference_height_mm"] == 0.0
    assert info["pixel_scale"] == pytest.approx(np.exp(-0.01 * (0 - z[0])), rel=1e-6)
    out = h.reshape(-1)[np.where(src < 0, 0, src)] * (src >= 0)
    f2 = np.exp(-0.02)
    rows, cols = np.nonzero(out == 2.0)
    assert rows.mean() == pytest.approx(c + (29.5 - c) * f2, abs=0.3)
    assert cols.mean() == pytest.approx(c + (164.5 - c) * f2, abs=0.3)
    assert rows.size >= 0.9 * 20 * 30           # a shrinking part keeps its area
    assert (src[125:185, 15:75] >= 0).all()      # a noisy flat patch keeps every pixel
    assert (src[125:185, 178:196] >= 0).all()    # no rounding gaps on a steep slope
    assert (src < 0).any() and (src[150:160, 150:160] >= 0).all()
    assert np.all(src.reshape(-1)[np.ravel_multi_index(([150], [150]), (n, n))] ==
                  np.ravel_multi_index(([150], [150]), (n, n)))
    # a magnification that grows with z (focusing with the lens) is left alone
    grow = Alignment([about_centre(1 / s) for s in scales], 12, (n, n), np.ones((n, n), bool))
    assert grow.parallax_sources(z, h, rel)[0] is None


def test_parallax_tears_no_holes_where_measured_pixels_border_unreliable_ones():
    """A smooth dome off centre, 8 %/mm of magnification lost per mm (metal-bore's lens),
    with an unreliable patch on its flank and sparse junk heights on the board: where the
    measured pixels move off and nothing measured comes, the surface's move (unreliable
    pixels carried by the heights around them) fills the place. Before, such places were
    'hidden' (2.5 % of metal-bore's field with --step-mm 0.1); only a raised edge hides."""
    from smdinspect.sff._align import Alignment

    n = 241
    z = np.linspace(0.0, 1.2, 13)
    c = (n - 1) / 2

    def about_centre(s):
        return np.array([[s, 0, c - s * c], [0, s, c - s * c], [0, 0, 1.0]])

    scales = np.exp(-0.08 * (z - z[0]))
    al = Alignment([about_centre(s) for s in scales], 0, (n, n), np.ones((n, n), bool))
    yy, xx = np.mgrid[0:n, 0:n]
    h = (1.0 * np.exp(-((yy - 60) ** 2 + (xx - 180) ** 2) / (2 * 30.0 ** 2))).astype(np.float32)
    rel = np.ones((n, n), bool)
    rel[45:65, 150:170] = False                   # the dome's flank, unreliable
    rng = np.random.default_rng(TEST_SEEDS[0] + 9)
    junk = np.zeros((n, n), bool)
    junk[160:230, 20:90] = True
    rel[junk] = rng.random(junk.sum()) < 0.03     # a weak-texture board: sparse peaks
    h[junk & rel] = rng.uniform(0.0, 1.2, (junk & rel).sum())
    src, info = al.parallax_sources(z, h, rel)
    assert info["corrected"]
    # nothing is hidden on a surface without steps, patch and junk included
    assert (src[20:110, 130:230] >= 0).all() and (src[150:235, 10:100] >= 0).all()
    assert (src[2:-2, 2:-2] < 0).mean() < 0.001  # (the image's edge row: out of view)


def _block_stack(tmp_path):
    """A moving camera with an ordinary lens over a textured board with a 1.6 mm block
    far from the centre (up and right); above z ~ 1 mm only the block is sharp."""
    from smdinspect.synth import Scene

    n, p = 480, 0.02
    optics = Optics.for_pixel_size(p, telecentric=False)
    height = np.zeros((n, n), np.float32)
    height[40:100, 380:440] = 1.6
    rng = np.random.default_rng(TEST_SEEDS[0] + 5)
    albedo = cv2.GaussianBlur(rng.random((n, n)).astype(np.float32), (0, 0), 1.2)
    albedo = (0.3 + 0.4 * (albedo - albedo.min()) / np.ptp(albedo)).astype(np.float32)
    z = np.arange(-0.3, 1.95, 0.075)
    stack = render_stack(Scene(height, albedo, p, name="block"), z, optics=optics,
                         seed=TEST_SEEDS[0] + 6, out=tmp_path / "b", previews=False)
    return stack, optics, albedo


def test_defocused_frames_follow_the_lens_not_their_own_registration(tmp_path, caplog):
    """Where only the raised block is sharp, ECC's per-step scale is noise and bias;
    those steps follow the thin-lens scale fitted to the frames that show the board
    (chained steps were 1.7 px off at the image corners, the truth being a pure scale
    about the centre by the board's magnification)."""
    stack, optics, _ = _block_stack(tmp_path)
    z = np.array([f.z_mm for f in stack.frames])
    order = np.argsort(z)
    frames = [cv2.imread(str(stack.frames[i].path), cv2.IMREAD_UNCHANGED) for i in order]
    with caplog.at_level("DEBUG", logger="smdinspect.sff._align"):
        al = estimate_alignment(lambda k: frames[k].astype(np.float32).mean(axis=-1)
                                if frames[k].ndim == 3 else frames[k].astype(np.float32),
                                len(z), z_mm=z[order])
    assert al.model["modelled_steps"] > 0 and al.trusted
    # the steps ECC got wrong on the blurred frames are replaced by the model: said at
    # debug level only (a warning would send the user after a problem already solved)
    wrong = [r for r in caplog.records if "alignment step" in r.getMessage()]
    assert al.failed and wrong and all(r.levelname == "DEBUG" for r in wrong)
    m = np.array([float(optics.magnification_at(0.0, zz)) for zz in z[order]])
    h, w = al.shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
    err = [np.abs(corners @ a[:2, :2].T + a[:2, 2] - (c + (corners - c) * m[k] / m[al.reference]))
           .max() for k, a in enumerate(al.transforms)]
    assert max(err) < 1.0, np.round(err, 2)


def test_ordinary_lens_parallax_puts_raised_points_at_their_metric_position(tmp_path):
    """A moving camera with an ordinary lens images a raised point larger than the board
    in the aligned grid; the surface puts it back where it lies."""
    stack, optics, albedo = _block_stack(tmp_path)
    n, p = albedo.shape[0], 0.02
    s = reconstruct(stack, FocusConfig(align=True))
    info = s.meta["alignment"]["parallax"]
    # d ln m / dz = -1 / d_f on the board
    assert info["corrected"] and info["scale_per_mm"] == pytest.approx(
        -1 / optics.working_distance_mm, rel=0.3)
    top = s.reliable & (s.height_mm > 1.2)
    assert top.sum() > 0.5 * 60 * 60
    # the output grid keeps the board (the median height) in place: its pixel is the
    # focused plane's times the scale of the board's frame against the reference frame
    assert info["reference_height_mm"] == pytest.approx(0.0, abs=0.02)
    assert s.pixel_size_mm == pytest.approx(p * info["pixel_scale"])
    assert 0.99 < info["pixel_scale"] < 1.0
    assert info["hidden_fraction"] < 0.01
    # The top's texture lies where the truth's does (in x within 0.3 px; in y the
    # alignment itself is off by ~1 px on this stack, with or without the correction:
    # the steps' sideways shifts). Uncorrected it lay ~2 px further out in x.
    a = s.aif.astype(np.float32)
    ps = info["pixel_scale"]
    c = (n - 1) / 2
    m = np.array([[1 / ps, 0, c - c / ps], [0, 1 / ps, c - c / ps]], np.float32)
    metric = cv2.warpAffine(a, m, (n, n), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    win = (slice(48, 92), slice(388, 432))
    (dx, dy), _ = cv2.phaseCorrelate((albedo[win] - albedo[win].mean()).astype(np.float64),
                                     (metric[win] - metric[win].mean()).astype(np.float64))
    assert abs(dx) < 0.3 and abs(dy) < 2.0, (dx, dy)
    board = s.reliable & (np.abs(s.height_mm) < 0.1)
    assert board[300:, :150].mean() > 0.8
