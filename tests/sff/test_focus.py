"""Tests of the focus measure operators (smdinspect.sff._focus)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff._focus import OPERATORS, FocusOperator, focus_measure

BLUR_SIGMAS_PX = (0.0, 0.5, 1.0, 2.0, 3.0)
FAMILIES = {"laplacian", "gradient", "statistics", "wavelet", "dct", "miscellaneous"}


def _blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    if sigma_px == 0:
        return image.copy()
    return cv2.GaussianBlur(image, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)


def _texture(seed: int = 0, shape=(128, 128), corr_px: float = 1.0) -> np.ndarray:
    """Band-limited random texture in 0..255 grey levels (mean 128, std ~40), float32.

    Real optics never pass pure pixel noise, so the "sharp" frame is white noise blurred
    by ``corr_px``; the operators are then measured on further Gaussian defocus.
    """
    rng = np.random.default_rng(seed)
    tex = _blur(rng.normal(0.0, 1.0, shape).astype(np.float32), corr_px)
    return np.clip(128.0 + 40.0 * tex / tex.std(), 0, 255).astype(np.float32)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    return _texture()


# --------------------------------------------------------------------------- the names


def test_operator_names_and_families():
    assert list(FocusOperator)[0] is FocusOperator.SML
    assert FocusOperator.SML.value == "sml"
    assert OPERATORS == tuple(sorted(OPERATORS))
    assert len(set(OPERATORS)) == len(OPERATORS) >= 16
    assert set(OPERATORS) == {op.value for op in FocusOperator}
    assert all(name == name.lower() and name.isalnum() for name in OPERATORS)
    assert {FocusOperator(name).family for name in OPERATORS} == FAMILIES
    assert FocusOperator.SML.family == "laplacian"
    assert FocusOperator("sml").uses_threshold


def test_enum_and_upper_case_names_are_accepted(texture):
    ref = focus_measure(texture, operator="ten")
    np.testing.assert_array_equal(focus_measure(texture, operator=FocusOperator.TEN), ref)
    np.testing.assert_array_equal(focus_measure(texture, operator="TEN"), ref)


# --------------------------------------------------------------------------- every operator


@pytest.mark.parametrize("operator", OPERATORS)
def test_shape_dtype_non_negative(operator, texture):
    frame = texture[:100, :70]  # not square, not a multiple of the DCT block
    out = focus_measure(frame, operator=operator, window_px=7)
    assert out.shape == frame.shape
    assert out.dtype == np.float32
    assert np.isfinite(out).all()
    assert (out >= 0).all()
    assert out.mean() > 0
    assert not np.shares_memory(out, frame)


@pytest.mark.parametrize("operator", OPERATORS)
def test_strictly_decreasing_with_blur(operator, texture):
    means = [float(focus_measure(_blur(texture, s), operator=operator).mean())
             for s in BLUR_SIGMAS_PX]
    assert all(a > b for a, b in zip(means, means[1:])), means
    # and not by a rounding error: σ = 3 px loses most of the focus value
    assert means[-1] < 0.75 * means[0], means


@pytest.mark.parametrize("operator", OPERATORS)
def test_peaks_at_the_sharp_frame(operator):
    # A 9-frame stack: frame n is the texture defocused by σ = 0.5·|n − n0| px, with
    # camera noise, the sharp frame off-centre.
    n0, n_frames = 3, 9
    rng = np.random.default_rng(7)
    sharp = _texture(seed=3)
    volume = []
    for n in range(n_frames):
        frame = _blur(sharp, 0.5 * abs(n - n0)) + rng.normal(0.0, 1.0, sharp.shape)
        volume.append(focus_measure(np.clip(frame, 0, 255).astype(np.float32),
                                    operator=operator))
    volume = np.stack(volume)
    assert int(np.argmax(volume.mean(axis=(1, 2)))) == n0
    peak = np.argmax(volume, axis=0)
    assert np.mean(peak == n0) > 0.97  # per pixel, not just on average


@pytest.mark.parametrize("operator", OPERATORS)
def test_uint8_uint16_float64_give_the_float32_result(operator):
    u8 = np.random.default_rng(1).integers(0, 256, (40, 48), dtype=np.uint8)
    u8 = cv2.GaussianBlur(u8, (0, 0), 0.8)
    ref = focus_measure(u8.astype(np.float32), operator=operator, window_px=5)
    for frame in (u8, u8.astype(np.uint16), u8.astype(np.float64)):
        np.testing.assert_array_equal(focus_measure(frame, operator=operator, window_px=5), ref)


@pytest.mark.parametrize("operator", OPERATORS)
def test_flat_image_scores_zero_and_measure_is_local(operator, texture):
    # "zero" up to float32 round-off of the filters, relative to a textured response
    tiny = 1e-6 * float(focus_measure(texture, operator=operator).mean())
    flat = np.full((64, 64), 100.0, np.float32)
    assert focus_measure(flat, operator=operator).max() <= tiny
    # texture on the left half only: the right half, farther than the window (4 px) plus
    # the operator's own support (<= 4 px) from the seam, scores 0
    half = flat.copy()
    half[:, :32] = texture[:64, :32]
    out = focus_measure(half, operator=operator, window_px=9)
    assert out[:, :24].min() > 1000 * tiny
    assert out[:, 41:].max() <= tiny


def test_input_is_not_modified(texture):
    frame = texture.copy()
    for operator in OPERATORS:
        focus_measure(frame, operator=operator, threshold=0.0)
    np.testing.assert_array_equal(frame, texture)


# --------------------------------------------------------------------------- sml reference


def _sml_reference(image: np.ndarray, window_px: int, threshold: float) -> np.ndarray:
    """Direct float64 computation, mirrored borders (cv2.BORDER_REFLECT == 'symmetric')."""
    g = np.pad(image.astype(np.float64), 1, mode="symmetric")
    dxx = g[1:-1, :-2] - 2.0 * g[1:-1, 1:-1] + g[1:-1, 2:]
    dyy = g[:-2, 1:-1] - 2.0 * g[1:-1, 1:-1] + g[2:, 1:-1]
    ml = dxx ** 2 + dyy ** 2
    ml[ml < threshold] = 0.0
    r = window_px // 2
    padded = np.pad(ml, r, mode="symmetric")
    out = np.empty_like(ml)
    for i in range(ml.shape[0]):
        for j in range(ml.shape[1]):
            out[i, j] = padded[i:i + window_px, j:j + window_px].sum()
    return out


@pytest.mark.parametrize("window_px", [1, 3, 9, 17])  # 17: the running box-filter path
def test_sml_matches_direct_reference(window_px):
    img = np.random.default_rng(2).integers(0, 256, (19, 23), dtype=np.uint8)
    got = focus_measure(img, operator="sml", window_px=window_px)
    np.testing.assert_allclose(got, _sml_reference(img, window_px, 0.0), rtol=1e-6)


def test_sml_threshold_matches_reference_including_the_boundary():
    img = np.random.default_rng(4).integers(0, 256, (19, 23), dtype=np.uint8)
    ml = _sml_reference(img, 1, 0.0)
    threshold = float(np.median(ml))  # an ML value that occurs: ML == T is kept
    assert np.any(ml == threshold)
    got = focus_measure(img, operator="sml", window_px=5, threshold=threshold)
    want = _sml_reference(img, 5, threshold)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert not np.allclose(want, _sml_reference(img, 5, 0.0))  # the threshold mattered
    per_pixel = focus_measure(img, operator="sml", window_px=1, threshold=threshold)
    np.testing.assert_array_equal(per_pixel, np.where(ml >= threshold, ml, 0.0))
    # T is compared in float32: the next float32 up drops the pixels equal to T
    above_t = float(np.nextafter(np.float32(threshold), np.float32(np.inf)))
    above = focus_measure(img, operator="sml", window_px=1, threshold=above_t)
    np.testing.assert_array_equal(above, np.where(ml > threshold, ml, 0.0))


def test_sml_docstring_numbers():
    frame = np.zeros((5, 5), np.uint8)
    frame[2, 2] = 10
    assert focus_measure(frame, window_px=1)[2, 2] == 800.0
    assert focus_measure(frame, window_px=3)[2, 2] == 1200.0


@pytest.mark.parametrize("operator", sorted(op.value for op in FocusOperator if op.uses_threshold))
def test_threshold_only_removes_response(operator, texture):
    plain = focus_measure(texture, operator=operator)
    assert (focus_measure(texture, operator=operator, threshold=1e12) == 0).all()
    mid = float(np.median(focus_measure(texture, operator=operator, window_px=1)))
    some = focus_measure(texture, operator=operator, threshold=mid)
    assert (some <= plain * (1 + 1e-6) + 1e-3).all()
    assert some.mean() < plain.mean()


# --------------------------------------------------------------------------- other references


def _window_reference(values: np.ndarray, window_px: int, reduce) -> np.ndarray:
    r = window_px // 2
    padded = np.pad(values, r, mode="symmetric")
    out = np.empty(values.shape)
    for i in range(values.shape[0]):
        for j in range(values.shape[1]):
            out[i, j] = reduce(padded[i:i + window_px, j:j + window_px])
    return out


def test_glva_is_the_window_variance():
    img = np.random.default_rng(5).integers(0, 65536, (15, 17), dtype=np.uint16)
    want = _window_reference(img.astype(np.float64), 5, np.var)
    np.testing.assert_allclose(focus_measure(img, operator="glva", window_px=5), want, rtol=1e-5)


def _block_dct_reference(image: np.ndarray, block_px: int = 8):
    """Orthonormal 2-D DCT of the block_px² block at every pixel (rows i-4..i+3)."""
    from scipy.fft import dctn

    h = block_px // 2
    padded = np.pad(image.astype(np.float64), h, mode="symmetric")
    coeffs = np.empty((*image.shape, block_px, block_px))
    for i in range(image.shape[0]):
        for j in range(image.shape[1]):
            coeffs[i, j] = dctn(padded[i:i + block_px, j:j + block_px], norm="ortho")
    return coeffs


def test_dct_operators_match_blockwise_dct():
    img = _texture(seed=6, shape=(14, 16))
    c = _block_dct_reference(img) ** 2
    dc = c[..., 0, 0]
    ac = c.sum(axis=(-1, -2)) - dc
    low = c[..., 0, 1] + c[..., 1, 0] + c[..., 0, 2] + c[..., 1, 1] + c[..., 2, 0]
    ws = lambda a: _window_reference(a, 5, np.sum)  # noqa: E731
    np.testing.assert_allclose(focus_measure(img, operator="dcte", window_px=5),
                               ws(ac) / ws(dc), rtol=1e-4)
    np.testing.assert_allclose(focus_measure(img, operator="dctr", window_px=5),
                               ws(low) / ws(dc), rtol=1e-4)


def test_curvature_fit_recovers_a_quadratic_surface():
    # z = 2x − y + 0.5x² + 0.25y² (+ offset): around (x0, y0) the local fit is exact, with
    # slopes b = 2 + x0, c = −1 + 0.5·y0 and curvatures d = 0.5, e = 0.25
    y, x = np.mgrid[0:12, 0:12].astype(np.float64) - 6.0
    z = 2 * x - y + 0.5 * x ** 2 + 0.25 * y ** 2 + 200.0
    got = focus_measure(z.astype(np.float32), operator="curv", window_px=1)
    want = np.abs(2 + x) + np.abs(-1 + 0.5 * y) + 0.5 + 0.25
    np.testing.assert_allclose(got[1:-1, 1:-1], want[1:-1, 1:-1], atol=1e-4)  # float32 of ~250


def _pad1(image):
    return np.pad(image.astype(np.float64), 1, mode="symmetric")


@pytest.mark.parametrize("operator, response", [
    # per-pixel responses (window_px = 1) written out with array slicing
    ("lapm", lambda p: np.abs(p[1:-1, :-2] - 2 * p[1:-1, 1:-1] + p[1:-1, 2:])
     + np.abs(p[:-2, 1:-1] - 2 * p[1:-1, 1:-1] + p[2:, 1:-1])),
    ("grae", lambda p: (p[1:-1, 2:] - p[1:-1, 1:-1]) ** 2 + (p[2:, 1:-1] - p[1:-1, 1:-1]) ** 2),
    ("grat", lambda p: np.abs(p[1:-1, 2:] - p[1:-1, 1:-1]) + np.abs(p[2:, 1:-1] - p[1:-1, 1:-1])),
    ("bren", lambda p: np.maximum((p[1:-1, 2:] - p[1:-1, :-2]) ** 2,
                                  (p[2:, 1:-1] - p[:-2, 1:-1]) ** 2)),
    ("ten", lambda p: ((p[:-2, 2:] + 2 * p[1:-1, 2:] + p[2:, 2:])
                       - (p[:-2, :-2] + 2 * p[1:-1, :-2] + p[2:, :-2])) ** 2
     + ((p[2:, :-2] + 2 * p[2:, 1:-1] + p[2:, 2:])
        - (p[:-2, :-2] + 2 * p[:-2, 1:-1] + p[:-2, 2:])) ** 2),
    ("cont", lambda p: sum(np.abs(p[1:-1, 1:-1] - p[1 + dr:p.shape[0] - 1 + dr,
                                                  1 + dc:p.shape[1] - 1 + dc])
                           for dr in (-1, 0, 1) for dc in (-1, 0, 1))),
    ("wavs", lambda p: (np.abs(p[1:-1, 1:-1] - p[1:-1, 2:] + p[2:, 1:-1] - p[2:, 2:])
                        + np.abs(p[1:-1, 1:-1] + p[1:-1, 2:] - p[2:, 1:-1] - p[2:, 2:])
                        + np.abs(p[1:-1, 1:-1] - p[1:-1, 2:] - p[2:, 1:-1] + p[2:, 2:])) / 2),
])
def test_per_pixel_responses_match_slicing(operator, response):
    img = np.random.default_rng(8).integers(0, 256, (13, 11), dtype=np.uint8)
    want = response(_pad1(img))
    got = focus_measure(img, operator=operator, window_px=1)
    # wavs/grae/grat use forward differences: the last row/col sees the mirrored border
    np.testing.assert_allclose(got[:-1, :-1], want[:-1, :-1], rtol=1e-6, atol=1e-3)
    np.testing.assert_allclose(focus_measure(img, operator=operator, window_px=3),
                               _window_reference(got.astype(np.float64), 3, np.sum), rtol=1e-5)


# --------------------------------------------------------------------------- errors


def test_unknown_operator_lists_the_choices(texture):
    with pytest.raises(InputError, match="unknown focus operator 'sharpest'; choose one of "
                                         + ", ".join(OPERATORS)):
        focus_measure(texture, operator="sharpest")
    with pytest.raises(InputError, match="unknown focus operator None"):
        focus_measure(texture, operator=None)


@pytest.mark.parametrize("window_px", [0, -3, 8, 2])
def test_window_must_be_odd_and_positive(window_px, texture):
    with pytest.raises(InputError, match=f"window_px must be an odd integer >= 1; got {window_px}"):
        focus_measure(texture, window_px=window_px)


@pytest.mark.parametrize("window_px", [9.0, "9", True, None])
def test_window_must_be_an_integer(window_px, texture):
    with pytest.raises(InputError, match="window_px must be an odd integer >= 1"):
        focus_measure(texture, window_px=window_px)


def test_window_larger_than_the_frame():
    frame = np.zeros((7, 30), np.uint8)
    focus_measure(frame, window_px=7)  # equal to the smaller side is fine
    with pytest.raises(InputError, match=r"window_px must be <= the frame's smaller side "
                                         r"\(7 px for a 7x30 frame\); got 9"):
        focus_measure(frame, window_px=9)


@pytest.mark.parametrize("shape", [(8, 8, 3), (64,), (), (1, 8, 8)])
def test_frame_must_be_2d(shape):
    with pytest.raises(InputError, match=r"frame must be a 2-D \(H, W\) grey image; got shape"):
        focus_measure(np.zeros(shape, np.uint8))


def test_colour_frame_hint():
    with pytest.raises(InputError, match="convert colour frames to grey first"):
        focus_measure(np.zeros((8, 8, 3), np.uint8))


def test_empty_frame():
    with pytest.raises(InputError, match=r"frame must not be empty; got shape \(0, 5\)"):
        focus_measure(np.zeros((0, 5), np.float32), window_px=1)


@pytest.mark.parametrize("dtype", [np.int32, np.bool_, np.complex64, np.float16, np.int8])
def test_unsupported_dtype(dtype):
    with pytest.raises(InputError, match=f"frame dtype must be uint8, uint16, float32 or "
                                         f"float64; got {np.dtype(dtype)}"):
        focus_measure(np.zeros((16, 16), dtype))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_non_finite_frame(bad, dtype, texture):
    frame = texture.astype(dtype)
    frame[5, 7] = bad
    with pytest.raises(InputError, match="frame holds NaN or infinite values"):
        focus_measure(frame)


def test_float64_frame_beyond_float32_range(texture):
    frame = texture.astype(np.float64)
    frame[0, 0] = 1e300
    with pytest.raises(InputError, match="beyond the float32 range"):
        focus_measure(frame)


@pytest.mark.parametrize("threshold", [-1.0, np.nan, np.inf, "5", None, True])
def test_bad_threshold(threshold, texture):
    with pytest.raises(InputError, match="threshold must be a finite number >= 0; got"):
        focus_measure(texture, threshold=threshold)


def test_threshold_with_an_operator_that_does_not_use_it(texture):
    focus_measure(texture, operator="glva", threshold=0.0)
    with pytest.raises(InputError, match="threshold applies only to operators that sum a "
                                         "per-pixel response .*; got threshold=5.0 with "
                                         "operator 'glva'"):
        focus_measure(texture, operator="glva", threshold=5.0)


@pytest.mark.parametrize("operator", ["glva", "lapv", "tenv", "wavv", "glvn", "glvl"])
def test_variance_operators_need_a_window(operator, texture):
    with pytest.raises(InputError, match=f"operator '{operator}' needs window_px >= 3; got 1"):
        focus_measure(texture, operator=operator, window_px=1)


@pytest.mark.parametrize("operator", ["glvn", "hel", "dcte", "dctr", "wavr", "cheb"])
def test_ratio_operators_need_non_negative_frames(operator, texture):
    with pytest.raises(InputError, match=f"operator '{operator}' is a ratio of grey levels and "
                                         f"needs a frame >= 0; got a minimum of -128"):
        focus_measure(texture - 128.0 - texture.min(), operator=operator)
    # every other operator ignores the grey-level offset
    assert focus_measure(texture - 300.0, operator="sml").mean() > 0
