"""Focus measure operators: per-pixel sharpness of one frame of a focal stack.

Every operator maps a grey frame ``g`` to a focus volume slice ``F`` of the same size:
``F >= 0`` and larger means sharper, each pixel's value aggregated over the square window
U (``window_px`` × ``window_px``) centred on it. The default is Nayar's sum of modified
Laplacian (``"sml"``), the hot path of the whole program; 24 more operators from the
six families compared by Pertuz, Puig & Garcia (2013, "Analysis of focus measure
operators for shape-from-focus", Pattern Recognition 46) are options:

=============  ==========================================================================
family         operators
=============  ==========================================================================
laplacian      ``sml`` ``lape`` ``lapm`` ``lapd`` ``lapv``
gradient       ``ten`` ``tenv`` ``gder`` ``grae`` ``grat``
statistics     ``glva`` ``glvn`` ``glvl`` ``cheb``
wavelet        ``wavs`` ``wavv`` ``wavr``
dct            ``dcte`` ``dctr``
miscellaneous  ``bren`` ``cont`` ``curv`` ``hel`` ``sfil`` ``vol4``
=============  ==========================================================================

All operators are whole-frame OpenCV/NumPy filters (no loops over pixels); borders are
handled with ``cv2.BORDER_REFLECT``. Moment-based operators (variances, ratios) accumulate
in float64 so that uint16 frames do not lose their texture to cancellation; the result is
always float32. The frame is converted once to float32 without rescaling: a uint8 frame
stays in 0..255 units, so focus values of frames of the same stack are comparable.

The adaptations to a per-pixel measure (window sums, variances and ratios over U, fixed
block sizes) are this module's own; each operator's docstring gives its formula.
"""

from __future__ import annotations

import logging
import math
import numbers
import warnings
from enum import Enum
from functools import lru_cache
from typing import Callable

import cv2
import numpy as np

from ..errors import InputError

__all__ = ["OPERATORS", "FocusOperator", "band_powers", "focus_measure", "focus_measure_moments",
           "magnification_exponent", "prefilter_sigma"]

log = logging.getLogger(__name__)

_BORDER = cv2.BORDER_REFLECT
_F32 = cv2.CV_32F
_F64 = cv2.CV_64F
# Window sums up to this side use a separable filter of ones (measured ~2x faster than
# cv2.boxFilter at 9 px on 1024² float32); wider windows use the O(1) running box filter.
_SEPARABLE_MAX_PX = 15
#: Side (px) of the blocks of the DCT and Chebyshev-moment operators.
BLOCK_PX = 8
#: Standard deviation (px) of the Gaussian of ``gder`` and ``sfil``.
GAUSS_SIGMA_PX = 1.0
_SUPPORTED_DTYPES = (np.uint8, np.uint16, np.float32, np.float64)


class FocusOperator(str, Enum):
    """Focus measure operators; the value is the short name ``focus_measure`` takes.

    ``FocusOperator.SML.family`` names the operator's family (Pertuz et al. 2013).
    """

    SML = "sml"
    # Laplacian family
    LAPE = "lape"
    LAPM = "lapm"
    LAPD = "lapd"
    LAPV = "lapv"
    # gradient family
    TEN = "ten"
    TENV = "tenv"
    GDER = "gder"
    GRAE = "grae"
    GRAT = "grat"
    # statistics family
    GLVA = "glva"
    GLVN = "glvn"
    GLVL = "glvl"
    CHEB = "cheb"
    # wavelet family
    WAVS = "wavs"
    WAVV = "wavv"
    WAVR = "wavr"
    # DCT family
    DCTE = "dcte"
    DCTR = "dctr"
    # miscellaneous
    BREN = "bren"
    CONT = "cont"
    CURV = "curv"
    HEL = "hel"
    SFIL = "sfil"
    VOL4 = "vol4"

    @property
    def family(self) -> str:
        """``"laplacian"``, ``"gradient"``, ``"statistics"``, ``"wavelet"``, ``"dct"`` or
        ``"miscellaneous"``."""
        return _FAMILY[self.value]

    @property
    def curve_power(self) -> float:
        """Exponent p of the focus curve F ∝ (σ0² + κ²Δz²)^(−p) this operator follows.

        Defocus blur σ_b grows linearly with the distance Δz from focus, and the power
        spectrum of natural texture falls as 1/ω², so what a derivative operator sees
        falls as a power of σ_b: p ≈ 2 for a squared (energy) operator, p ≈ 1 for an
        absolute-value (amplitude) one (p = 2 gave uniform sub-frame positions on a
        coarsely stepped plane where a Gaussian terraced). The ``power`` fit uses it.
        """
        return 1.0 if self.value in _AMPLITUDE else 2.0

    @property
    def magnification_exponent(self) -> float:
        """Exponent k such that F of a frame magnified by m changes as m^(−k).

        An image of the same (equally blurred) scene at a magnification m times larger is
        g(x / m): its d-th derivatives shrink by m^(−d), so a derivative operator's
        response shrinks by m^(−d) (amplitude) or m^(−2d) (energy). A lens that is not
        telecentric changes m from frame to frame, which biases the peak towards the
        least magnified frame unless each frame's focus is scaled by m_n^k (m_n relative
        to the reference frame). Statistics and ratio operators are not derivatives:
        k = 0 (their window also covers a different area, which no factor corrects).
        """
        return _DERIVATIVE_ORDER.get(self.value, 0) * self.curve_power

    @property
    def uses_threshold(self) -> bool:
        """True if the operator sums a per-pixel response that ``threshold`` applies to."""
        return self.value in _THRESHOLDED


_FAMILY = {
    **dict.fromkeys(("sml", "lape", "lapm", "lapd", "lapv"), "laplacian"),
    **dict.fromkeys(("ten", "tenv", "gder", "grae", "grat"), "gradient"),
    **dict.fromkeys(("glva", "glvn", "glvl", "cheb"), "statistics"),
    **dict.fromkeys(("wavs", "wavv", "wavr"), "wavelet"),
    **dict.fromkeys(("dcte", "dctr"), "dct"),
    **dict.fromkeys(("bren", "cont", "curv", "hel", "sfil", "vol4"), "miscellaneous"),
}

#: All operator names, sorted.
OPERATORS: tuple[str, ...] = tuple(sorted(op.value for op in FocusOperator))

# Operators whose value is a window sum of a non-negative per-pixel response R: with a
# threshold T > 0, R < T counts as 0 before summing (Nayar's rule, applied alike).
_THRESHOLDED = frozenset(
    ("sml", "lape", "lapm", "lapd", "ten", "gder", "grae", "grat", "wavs", "bren", "cont",
     "curv", "sfil")
)
# Operators that sum absolute values (amplitudes), not squares (energies).
_AMPLITUDE = frozenset(("lapm", "lapd", "grat", "wavs", "cont", "curv", "hel"))
# Derivative order of each operator's per-pixel response (magnification_exponent); the
# unlisted ones (variance, ratio and DCT-ratio operators) are invariant to a uniform scaling.
_DERIVATIVE_ORDER = {
    **dict.fromkeys(("sml", "lape", "lapm", "lapd", "lapv", "curv"), 2),
    **dict.fromkeys(("ten", "gder", "grae", "grat", "wavs", "wavv", "bren", "cont", "sfil",
                     "vol4"), 1),
    "tenv": 2,  # variance of the squared gradient: 4th power of a first derivative
}
# Ratio operators: a negative grey level makes them meaningless.
_NEEDS_NON_NEGATIVE = frozenset(("glvn", "cheb", "wavr", "dcte", "dctr", "hel"))
# Variance operators (glvn is a variance over a mean): a 1-px window makes them 0.
_NEEDS_WINDOW_3 = frozenset(("lapv", "tenv", "glva", "glvn", "glvl", "wavv"))


# --------------------------------------------------------------------------- kernels


def _k(rows) -> np.ndarray:
    return np.asarray(rows, dtype=np.float32)


_K_XX = _k([[1, -2, 1]])  # ∂²/∂x², step 1
_K_IMMERKAER = _k([[1, -2, 1], [-2, 4, -2], [1, -2, 1]])  # noise_sigma
_K_YY = np.ascontiguousarray(_K_XX.T)
_K_UU = _k([[1, 0, 0], [0, -2, 0], [0, 0, 1]]) * 0.5  # ∂² along a diagonal (step √2)
_K_VV = _k([[0, 0, 1], [0, -2, 0], [1, 0, 0]]) * 0.5
_K_LAP4 = _k([[0, 1, 0], [1, -4, 1], [0, 1, 0]])  # 4-neighbour Laplacian
_K_LAP8 = _k([[1, 4, 1], [4, -20, 4], [1, 4, 1]]) / 6.0  # isotropic 8-neighbour Laplacian
_K_FWD_X = _k([[0, -1, 1]])  # g(x+1) - g(x)
_K_FWD_Y = np.ascontiguousarray(_K_FWD_X.T)
_K_CEN_X = _k([[-1, 0, 1]])  # g(x+1) - g(x-1)
_K_CEN_Y = np.ascontiguousarray(_K_CEN_X.T)
# Vollath F4 in shift-invariant form: differences at lag 1 and lag 2 (see _op_vol4).
_K_LAG1_X = _k([[0, 0, -1, 1, 0]])
_K_LAG2_X = _k([[0, 0, -1, 0, 1]])
_K_LAG1_Y = np.ascontiguousarray(_K_LAG1_X.T)
_K_LAG2_Y = np.ascontiguousarray(_K_LAG2_X.T)
# One-level orthonormal 2-D Haar analysis, undecimated: 2x2 kernels anchored at (0, 0).
_HAAR_LL = _k([[1, 1], [1, 1]]) * 0.5
_HAAR_LH = _k([[1, -1], [1, -1]]) * 0.5  # high-pass along x (vertical edges)
_HAAR_HL = _k([[1, 1], [-1, -1]]) * 0.5  # high-pass along y (horizontal edges)
_HAAR_HH = _k([[1, -1], [-1, 1]]) * 0.5  # diagonal detail
_HAAR_ANCHOR = (0, 0)
# Differences to the 8 neighbours (image contrast).
_K_NEIGHBOURS = tuple(
    _k([[(1.0 if (r, c) == (1, 1) else 0.0) - (1.0 if (r, c) == (1 + dr, 1 + dc) else 0.0)
         for c in range(3)] for r in range(3)])
    for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)
)


def _curvature_kernels() -> tuple[np.ndarray, ...]:
    """3x3 least-squares kernels of z = a + b·x + c·y + d·x² + e·y²; returns b, c, d, e."""
    cols, rows = np.meshgrid(np.arange(3) - 1.0, np.arange(3) - 1.0)
    x, y = cols.ravel(), rows.ravel()
    design = np.stack([np.ones(9), x, y, x * x, y * y], axis=1)  # (9, 5)
    pinv = np.linalg.pinv(design)  # (5, 9): coefficient i = pinv[i] · patch
    # The exact kernels are integers / 6; snapping the pinv round-off makes them sum to
    # exactly 0 in float32, so a flat patch scores exactly 0.
    pinv = np.round(pinv * 6.0) / 6.0
    return tuple(np.ascontiguousarray(pinv[i].reshape(3, 3), dtype=np.float32)
                 for i in (1, 2, 3, 4))


_K_CURV = _curvature_kernels()


@lru_cache(maxsize=None)
def _ones(n: int, dtype=np.float32) -> np.ndarray:
    a = np.ones(n, dtype=dtype)
    a.flags.writeable = False
    return a


@lru_cache(maxsize=None)
def _gaussian_pair(sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Sampled 1-D Gaussian (sum 1) and its derivative, radius ceil(3σ)."""
    r = max(1, int(math.ceil(3.0 * sigma_px)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-x * x / (2.0 * sigma_px * sigma_px))
    g /= g.sum()
    dg = -x / (sigma_px * sigma_px) * g
    out = (g.astype(np.float32), dg.astype(np.float32))
    for a in out:
        a.flags.writeable = False
    return out


@lru_cache(maxsize=None)
def _dct_basis(n: int) -> np.ndarray:
    """(n, n) orthonormal DCT-II basis; row k is c_k(x) = α_k cos(π(2x+1)k / 2n)."""
    x = np.arange(n, dtype=np.float64)
    k = np.arange(n, dtype=np.float64)[:, None]
    c = np.cos(np.pi * (2.0 * x + 1.0) * k / (2.0 * n)) * math.sqrt(2.0 / n)
    c[0] /= math.sqrt(2.0)
    c.flags.writeable = False
    return c


@lru_cache(maxsize=None)
def _chebyshev_basis(n: int) -> np.ndarray:
    """(n, n) orthonormal discrete Chebyshev (Tchebichef) polynomials on n points.

    Row p is the degree-p polynomial, from Gram–Schmidt (QR) of the monomials on the
    centred grid; rows are orthonormal, so the basis is complete (Parseval holds).
    """
    x = np.arange(n, dtype=np.float64) - (n - 1) / 2.0
    vander = np.vander(x / max(1.0, (n - 1) / 2.0), n, increasing=True)
    q, r = np.linalg.qr(vander)
    q = q * np.sign(np.diag(r))  # positive leading coefficients
    t = np.ascontiguousarray(q.T)
    t.flags.writeable = False
    return t


# --------------------------------------------------------------------------- helpers


def _filter(src: np.ndarray, kernel: np.ndarray, *, ddepth=_F32, dst=None, anchor=(-1, -1)):
    return cv2.filter2D(src, ddepth, kernel, dst=dst, anchor=anchor, borderType=_BORDER)


def _window_sum(src: np.ndarray, window_px: int, *, dst=None) -> np.ndarray:
    """Σ over the window_px × window_px neighbourhood (same dtype as ``src``)."""
    if window_px == 1:
        if dst is None:
            return src.copy()
        np.copyto(dst, src)
        return dst
    if window_px <= _SEPARABLE_MAX_PX:
        one = _ones(window_px, src.dtype.type)
        return cv2.sepFilter2D(src, -1, one, one, dst=dst, borderType=_BORDER)
    return cv2.boxFilter(src, -1, (window_px, window_px), dst=dst, normalize=False,
                         borderType=_BORDER)


def _window_mean(src: np.ndarray, window_px: int) -> np.ndarray:
    return cv2.boxFilter(src, -1, (window_px, window_px), normalize=True, borderType=_BORDER)


def _window_var(src: np.ndarray, window_px: int) -> np.ndarray:
    """Variance over the window, accumulated in float64; float64, >= 0."""
    x = src.astype(np.float64)
    mean = _window_mean(x, window_px)
    np.multiply(x, x, out=x)
    var = _window_mean(x, window_px)
    np.multiply(mean, mean, out=mean)
    var -= mean
    np.maximum(var, 0.0, out=var)
    return var


def _abs(a: np.ndarray) -> np.ndarray:
    """In place |a| (fresh 4 MB temporaries cost page faults: work in place)."""
    return np.abs(a, out=a)


def _sum_of_squares(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """In place a = a² + b²."""
    cv2.multiply(a, a, dst=a)
    cv2.accumulateSquare(b, a)
    return a


def _sum_of_abs_responses(g: np.ndarray, kernels) -> tuple[np.ndarray, np.ndarray]:
    """Σ_k |g ⋆ k| (float32) and a spare buffer of the same shape."""
    acc = _abs(_filter(g, kernels[0]))
    tmp = np.empty_like(acc)
    for kernel in kernels[1:]:
        acc += _abs(_filter(g, kernel, dst=tmp))
    return acc, tmp


def _apply_threshold(resp: np.ndarray, threshold: float) -> np.ndarray:
    """In place: values ``< float32(threshold)`` become 0 (values ``>=`` it are kept)."""
    if threshold > 0.0:
        # THRESH_TOZERO keeps src > t; the float32 just below T makes it src >= T.
        t = float(np.nextafter(np.float32(threshold), np.float32(-np.inf)))
        cv2.threshold(resp, t, 0.0, cv2.THRESH_TOZERO, dst=resp)
    return resp


def _thresholded_sum(resp: np.ndarray, window_px: int, threshold: float, *,
                     dst=None) -> np.ndarray:
    """Σ_U of ``resp`` (modified in place by the threshold); into ``dst`` if given."""
    return _window_sum(_apply_threshold(resp, threshold), window_px, dst=dst)


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den where den > 0, else 0; float32."""
    out = np.zeros(num.shape, dtype=np.float64)
    np.divide(num, den, out=out, where=den > 0)
    np.maximum(out, 0.0, out=out)
    return out.astype(np.float32)


def _f32(a: np.ndarray) -> np.ndarray:
    out = a.astype(np.float32, copy=False)
    np.maximum(out, 0.0, out=out)
    return out


# --------------------------------------------------------------------------- Laplacian


def _op_sml(g, window_px, threshold):
    """Sum of modified Laplacian (Laplacian family; Nayar & Nakagawa 1994). The hot path.

    ML(x, y) = (∂²g/∂x²)² + (∂²g/∂y²)², the second derivatives taken with the step-1
    stencil [1, -2, 1] (the squared form of the ARCHITECTURE map; Nayar's own ML sums
    absolute values, see ``lapm``). SML = Σ_U ML·[ML >= T] with Nayar's threshold T.

    About 1 ms per 1024² float32 frame with a 9-px window on 2 cores: two 1x3
    filter2D, in-place square and accumulate, and a separable sum of ones (measured
    faster than Sobel(dx=2, ksize=1) and than boxFilter). Preallocated buffers
    (an ``out=`` variant) measured no faster, so there is none.
    """
    dxx = _filter(g, _K_XX)
    dyy = _filter(g, _K_YY)
    ml = _sum_of_squares(dxx, dyy)  # in place: dxx = dxx² + dyy²
    return _thresholded_sum(ml, window_px, threshold, dst=dyy)


def _op_lapm(g, window_px, threshold):
    """Modified Laplacian, Nayar's absolute form (Laplacian family).

    ML_abs = |2g(x,y) − g(x−1,y) − g(x+1,y)| + |2g(x,y) − g(x,y−1) − g(x,y+1)|;
    F = Σ_U ML_abs·[ML_abs >= T].
    """
    acc, tmp = _sum_of_abs_responses(g, (_K_XX, _K_YY))
    return _thresholded_sum(acc, window_px, threshold, dst=tmp)


def _op_lape(g, window_px, threshold):
    """Energy of Laplacian (Laplacian family; Subbarao et al.).

    F = Σ_U (Δg)², Δg from the isotropic 8-neighbour stencil [[1,4,1],[4,−20,4],[1,4,1]]/6.
    """
    lap = _filter(g, _K_LAP8)
    cv2.multiply(lap, lap, dst=lap)
    return _thresholded_sum(lap, window_px, threshold)


def _op_lapd(g, window_px, threshold):
    """Diagonal Laplacian (Laplacian family; Thelen et al. 2009).

    LD = |g_xx| + |g_yy| + |g_uu| + |g_vv|, u and v the two diagonals, whose second
    differences are divided by 2 (step √2); F = Σ_U LD·[LD >= T].
    """
    acc, tmp = _sum_of_abs_responses(g, (_K_XX, _K_YY, _K_UU, _K_VV))
    return _thresholded_sum(acc, window_px, threshold, dst=tmp)


def _op_lapv(g, window_px, threshold):
    """Variance of Laplacian (Laplacian family; Pech-Pacheco et al. 2000).

    F = Var_U(Δg), Δg from the 4-neighbour stencil [[0,1,0],[1,−4,1],[0,1,0]].
    """
    return _f32(_window_var(_filter(g, _K_LAP4), window_px))


# --------------------------------------------------------------------------- gradient


def _sobel_sq(g):
    """(Gx² + Gy², spare buffer), Gx, Gy the 3x3 Sobel responses."""
    gx = cv2.Sobel(g, _F32, 1, 0, ksize=3, borderType=_BORDER)
    gy = cv2.Sobel(g, _F32, 0, 1, ksize=3, borderType=_BORDER)
    return _sum_of_squares(gx, gy), gy


def _op_ten(g, window_px, threshold):
    """Tenengrad (gradient family; Tenenbaum 1970, Krotkov 1987).

    F = Σ_U (Gx² + Gy²)·[Gx² + Gy² >= T], Gx, Gy the 3x3 Sobel responses.
    """
    g2, spare = _sobel_sq(g)
    return _thresholded_sum(g2, window_px, threshold, dst=spare)


def _op_tenv(g, window_px, threshold):
    """Tenengrad variance (gradient family; Pech-Pacheco et al. 2000).

    F = Var_U(Gx² + Gy²), Gx, Gy the 3x3 Sobel responses.
    """
    return _f32(_window_var(_sobel_sq(g)[0], window_px))


def _gauss_gradient(g):
    gauss, dgauss = _gaussian_pair(GAUSS_SIGMA_PX)
    gx = cv2.sepFilter2D(g, _F32, dgauss, gauss, borderType=_BORDER)
    gy = cv2.sepFilter2D(g, _F32, gauss, dgauss, borderType=_BORDER)
    return gx, gy


def _op_gder(g, window_px, threshold):
    """Gaussian derivative (gradient family; Geusebroek et al. 2000).

    F = Σ_U ((g ∗ ∂G_σ/∂x)² + (g ∗ ∂G_σ/∂y)²), σ = ``GAUSS_SIGMA_PX`` = 1 px; threshold
    on the per-pixel sum of squares.
    """
    gx, gy = _gauss_gradient(g)
    return _thresholded_sum(_sum_of_squares(gx, gy), window_px, threshold, dst=gy)


def _op_grae(g, window_px, threshold):
    """Gradient energy (gradient family; Subbarao et al. 1993).

    F = Σ_U ((g(x+1,y) − g(x,y))² + (g(x,y+1) − g(x,y))²).
    """
    gx = _filter(g, _K_FWD_X)
    gy = _filter(g, _K_FWD_Y)
    return _thresholded_sum(_sum_of_squares(gx, gy), window_px, threshold, dst=gy)


def _op_grat(g, window_px, threshold):
    """Thresholded absolute gradient (gradient family; Santos et al. 1997).

    F = Σ_U (|g(x+1,y) − g(x,y)| + |g(x,y+1) − g(x,y)|), per-pixel values < T set to 0.
    """
    acc, tmp = _sum_of_abs_responses(g, (_K_FWD_X, _K_FWD_Y))
    return _thresholded_sum(acc, window_px, threshold, dst=tmp)


# --------------------------------------------------------------------------- statistics


def _op_glva(g, window_px, threshold):
    """Grey-level variance (statistics family; Krotkov 1987).

    F = Var_U(g) = mean_U(g²) − mean_U(g)².
    """
    return _f32(_window_var(g, window_px))


def _op_glvn(g, window_px, threshold):
    """Normalised grey-level variance (statistics family; Groen et al. 1985).

    F = Var_U(g) / mean_U(g) (0 where the mean is 0); needs g >= 0, so F <= max g.
    """
    x = g.astype(np.float64)
    mean = _window_mean(x, window_px)
    var = _window_mean(x * x, window_px) - mean * mean
    return _ratio(var, mean)


def _op_glvl(g, window_px, threshold):
    """Grey-level local variance (statistics family; Pech-Pacheco et al. 2000).

    v = Var over the 3x3 neighbourhood of g; F = Var_U(v).
    """
    return _f32(_window_var(_window_var(g, 3), window_px))


def _block_moment_ratio(g, window_px, basis, low_orders):
    """Σ_U(high-order energy) / Σ_U(low-order energy) of the BLOCK_PX² block transform.

    ``basis`` is a complete orthonormal 1-D basis (rows), so by Parseval the energy of
    all coefficients of a block is Σ_block g²; the low-order coefficients (p, q) in
    ``low_orders`` come from separable correlations with basis rows p (x) and q (y),
    and high = total − low.
    """
    x = g.astype(np.float64)
    n = basis.shape[0]
    total = cv2.boxFilter(x * x, _F64, (n, n), normalize=False, borderType=_BORDER)
    low = np.zeros_like(x)
    for p, q in low_orders:
        c = cv2.sepFilter2D(x, _F64, basis[p], basis[q], borderType=_BORDER)
        low += c * c
    high = total - low
    np.maximum(high, 0.0, out=high)
    return _ratio(_window_sum(high, window_px), _window_sum(low, window_px))


def _op_cheb(g, window_px, threshold):
    """Chebyshev-moment ratio (statistics family; after Yap & Raveendran 2004).

    T_pq = Σ_block t_p(x)·t_q(y)·g over BLOCK_PX² blocks, t the orthonormal discrete
    Chebyshev polynomials; F = Σ_U Σ_{p+q>2} T_pq² / Σ_U Σ_{p+q<=2} T_pq².
    """
    low = [(p, q) for p in range(3) for q in range(3) if p + q <= 2]
    return _block_moment_ratio(g, window_px, _chebyshev_basis(BLOCK_PX), low)


# --------------------------------------------------------------------------- wavelet


def _haar_details(g):
    return tuple(_filter(g, k, anchor=_HAAR_ANCHOR) for k in (_HAAR_LH, _HAAR_HL, _HAAR_HH))


def _op_wavs(g, window_px, threshold):
    """Sum of wavelet coefficients (wavelet family; Yang & Nelson 2003).

    One-level undecimated orthonormal Haar transform (full resolution);
    F = Σ_U (|LH| + |HL| + |HH|), per-pixel sums < T set to 0.
    """
    lh, hl, hh = _haar_details(g)
    acc = _abs(lh)
    acc += _abs(hl)
    acc += _abs(hh)
    return _thresholded_sum(acc, window_px, threshold, dst=hl)


def _op_wavv(g, window_px, threshold):
    """Variance of wavelet coefficients (wavelet family; Yang & Nelson 2003).

    F = Var_U(LH) + Var_U(HL) + Var_U(HH), undecimated one-level Haar detail bands.
    """
    acc = None
    for band in _haar_details(g):
        v = _window_var(band, window_px)
        acc = v if acc is None else acc + v
    return _f32(acc)


def _op_wavr(g, window_px, threshold):
    """Ratio of wavelet coefficients (wavelet family; Xie et al. 2006).

    F = Σ_U (LH² + HL² + HH²) / Σ_U LL², undecimated one-level Haar bands.
    """
    x = g.astype(np.float64)
    hi = np.zeros_like(x)
    band = np.empty_like(x)
    for kernel in (_HAAR_LH, _HAAR_HL, _HAAR_HH):
        _filter(x, kernel, ddepth=_F64, dst=band, anchor=_HAAR_ANCHOR)
        np.multiply(band, band, out=band)
        hi += band
    ll = _filter(x, _HAAR_LL, ddepth=_F64, dst=band, anchor=_HAAR_ANCHOR)
    np.multiply(ll, ll, out=ll)
    return _ratio(_window_sum(hi, window_px, dst=x), _window_sum(ll, window_px))


# --------------------------------------------------------------------------- DCT


def _op_dcte(g, window_px, threshold):
    """DCT energy ratio (DCT family; Shen & Chen 2006).

    Over BLOCK_PX² blocks, AC energy / DC energy of the orthonormal 2-D DCT. By Parseval,
    AC = Σ_block g² − F00² and F00 = Σ_block g / BLOCK_PX, so no transform is needed;
    F = Σ_U AC / Σ_U F00².
    """
    x = g.astype(np.float64)
    n = BLOCK_PX
    s1 = cv2.boxFilter(x, _F64, (n, n), normalize=False, borderType=_BORDER)
    s2 = cv2.boxFilter(x * x, _F64, (n, n), normalize=False, borderType=_BORDER)
    dc = s1 * s1 / (n * n)
    ac = s2 - dc
    np.maximum(ac, 0.0, out=ac)
    return _ratio(_window_sum(ac, window_px), _window_sum(dc, window_px))


def _op_dctr(g, window_px, threshold):
    """DCT reduced energy ratio (DCT family; Lee et al. 2008).

    F_uv the orthonormal 2-D DCT of the BLOCK_PX² block, computed at every pixel by
    separable correlation with the basis vectors;
    F = Σ_U (F01² + F10² + F02² + F11² + F20²) / Σ_U F00².
    """
    x = g.astype(np.float64)
    c = _dct_basis(BLOCK_PX)
    dc = cv2.sepFilter2D(x, _F64, c[0], c[0], borderType=_BORDER)
    dc *= dc
    ac = np.zeros_like(x)
    for u, v in ((0, 1), (1, 0), (0, 2), (1, 1), (2, 0)):
        f = cv2.sepFilter2D(x, _F64, c[u], c[v], borderType=_BORDER)
        ac += f * f
    return _ratio(_window_sum(ac, window_px), _window_sum(dc, window_px))


# --------------------------------------------------------------------------- miscellaneous


def _op_bren(g, window_px, threshold):
    """Brenner's measure (miscellaneous; Brenner et al. 1976, Santos et al. 1997).

    B = max((g(x+1,y) − g(x−1,y))², (g(x,y+1) − g(x,y−1))²) (lag 2);
    F = Σ_U B·[B >= T].
    """
    dx = _filter(g, _K_CEN_X)
    dy = _filter(g, _K_CEN_Y)
    cv2.multiply(dx, dx, dst=dx)
    cv2.multiply(dy, dy, dst=dy)
    np.maximum(dx, dy, out=dx)
    return _thresholded_sum(dx, window_px, threshold, dst=dy)


def _op_cont(g, window_px, threshold):
    """Image contrast (miscellaneous; Nanda & Cutler 2001).

    C = Σ over the 8 neighbours n of |g(x,y) − g(n)|; F = Σ_U C·[C >= T].
    """
    acc, tmp = _sum_of_abs_responses(g, _K_NEIGHBOURS)
    return _thresholded_sum(acc, window_px, threshold, dst=tmp)


def _op_curv(g, window_px, threshold):
    """Image curvature (miscellaneous; Helmli & Scherer 2001).

    Least-squares fit of z = a + b·x + c·y + d·x² + e·y² to every 3x3 neighbourhood
    (each coefficient is one 3x3 correlation); K = |b| + |c| + |d| + |e|;
    F = Σ_U K·[K >= T].
    """
    acc, tmp = _sum_of_abs_responses(g, _K_CURV)
    return _thresholded_sum(acc, window_px, threshold, dst=tmp)


def _op_hel(g, window_px, threshold):
    """Helmli and Scherer's mean ratio (miscellaneous; Helmli & Scherer 2001).

    μ the 3x3 mean of g; R = max(μ, g) / min(μ, g) >= 1, computed as
    R − 1 = |g − μ| / (min(μ, g) + ε), ε = 10⁻³ × the frame's mean grey level (guards
    dark pixels); F = mean_U(R − 1), so a flat patch scores 0 like every other
    operator. Needs g >= 0.
    """
    eps = np.float32(1e-3 * float(cv2.mean(g)[0]) + 1e-12)
    mu = _window_mean(g, 3)
    ratio = cv2.absdiff(g, mu)
    np.minimum(mu, g, out=mu)
    mu += eps
    np.divide(ratio, mu, out=ratio)
    return _window_mean(ratio, window_px)


def _op_sfil(g, window_px, threshold):
    """Steerable filters (miscellaneous; Minhas et al. 2009).

    Gaussian first-derivative filters (σ = 1 px) steered to θ = 0°, 45°, 90°,
    135°:
    R_θ = cos θ·Gx + sin θ·Gy; S = max_θ |R_θ| (the 8 directions of 45°, as the sign
    flips with θ + 180°); F = Σ_U S·[S >= T].
    """
    gx, gy = _gauss_gradient(g)
    h = math.sqrt(0.5)
    best = _abs(cv2.addWeighted(gx, h, gy, h, 0.0))
    tmp = _abs(cv2.addWeighted(gx, h, gy, -h, 0.0))
    np.maximum(best, tmp, out=best)
    np.maximum(best, _abs(gx), out=best)
    np.maximum(best, _abs(gy), out=best)
    return _thresholded_sum(best, window_px, threshold, dst=tmp)


def _op_vol4(g, window_px, threshold):
    """Vollath's F4 autocorrelation (miscellaneous; Vollath 1987).

    F4 = Σ g(x)·g(x+1) − Σ g(x)·g(x+2) along x, plus the same along y. Written in its
    shift-invariant form V = ½[(g(x+2) − g(x))² − (g(x+1) − g(x))²] (+ the y terms),
    which equals F4 over a whole line up to a telescoping boundary term and ignores the
    mean grey level; F = max(0, Σ_U V).
    """
    acc = np.zeros(g.shape, dtype=np.float32)
    d1 = np.empty_like(acc)
    d2 = np.empty_like(acc)
    for lag1, lag2 in ((_K_LAG1_X, _K_LAG2_X), (_K_LAG1_Y, _K_LAG2_Y)):
        _filter(g, lag2, dst=d2)
        _filter(g, lag1, dst=d1)
        cv2.accumulateSquare(d2, acc)
        cv2.multiply(d1, d1, dst=d1)
        acc -= d1
    acc *= 0.5
    out = _window_sum(acc, window_px, dst=d1)
    np.maximum(out, 0.0, out=out)
    return out


_OPERATORS: dict[str, Callable[[np.ndarray, int, float], np.ndarray]] = {
    "sml": _op_sml,
    "lape": _op_lape,
    "lapm": _op_lapm,
    "lapd": _op_lapd,
    "lapv": _op_lapv,
    "ten": _op_ten,
    "tenv": _op_tenv,
    "gder": _op_gder,
    "grae": _op_grae,
    "grat": _op_grat,
    "glva": _op_glva,
    "glvn": _op_glvn,
    "glvl": _op_glvl,
    "cheb": _op_cheb,
    "wavs": _op_wavs,
    "wavv": _op_wavv,
    "wavr": _op_wavr,
    "dcte": _op_dcte,
    "dctr": _op_dctr,
    "bren": _op_bren,
    "cont": _op_cont,
    "curv": _op_curv,
    "hel": _op_hel,
    "sfil": _op_sfil,
    "vol4": _op_vol4,
}


# --------------------------------------------------------------------------- validation


def _check_window(window_px, shape) -> None:
    if isinstance(window_px, bool) or not isinstance(window_px, numbers.Integral):
        raise InputError(f"window_px must be an odd integer >= 1; got {window_px!r}")
    if window_px < 1 or window_px % 2 == 0:
        raise InputError(f"window_px must be an odd integer >= 1; got {window_px}")
    if window_px > min(shape):
        raise InputError(
            f"window_px must be <= the frame's smaller side ({min(shape)} px for a "
            f"{shape[0]}x{shape[1]} frame); got {window_px}"
        )


def _check_threshold(threshold) -> None:
    if (isinstance(threshold, bool) or not isinstance(threshold, numbers.Real)
            or not math.isfinite(threshold) or threshold < 0):
        raise InputError(f"threshold must be a finite number >= 0; got {threshold!r}")


def _operator_name(operator) -> str:
    if isinstance(operator, FocusOperator):
        return operator.value
    if isinstance(operator, str) and operator.lower() in _OPERATORS:
        return operator.lower()
    raise InputError(
        f"unknown focus operator {operator!r}; choose one of {', '.join(OPERATORS)}"
    )


def _as_float32(frame) -> np.ndarray:
    """The one conversion on entry: (H, W) float32, C-contiguous, values unchanged."""
    a = np.asarray(frame)
    if a.ndim != 2:
        hint = " (convert colour frames to grey first)" if a.ndim == 3 else ""
        raise InputError(f"frame must be a 2-D (H, W) grey image; got shape {a.shape}{hint}")
    if a.dtype.type not in _SUPPORTED_DTYPES:
        raise InputError(f"frame dtype must be uint8, uint16, float32 or float64; got {a.dtype}")
    if a.size == 0:
        raise InputError(f"frame must not be empty; got shape {a.shape}")
    if a.dtype == np.float32:
        g = np.ascontiguousarray(a)
    else:
        with np.errstate(over="ignore"):
            g = a.astype(np.float32, order="C")
    if a.dtype.kind == "f" and not np.isfinite(g).all():
        raise InputError("frame holds NaN or infinite values (or values beyond the float32 "
                         "range); focus measures need finite grey levels")
    return g


# --------------------------------------------------------------------------- public


def focus_measure(frame, *, operator="sml", window_px=9, threshold=0.0) -> np.ndarray:
    """Per-pixel focus measure of one grey frame (one slice of the focus volume).

    Parameters
    ----------
    frame : (H, W) uint8, uint16, float32 or float64
        Grey frame. Converted once to float32 without rescaling (uint8 stays in 0..255
        units); must be finite. Colour frames must be converted to grey first.
    operator : str or FocusOperator
        One of :data:`OPERATORS` (see the module docstring for the families). The
        default ``"sml"`` is Nayar's sum of modified Laplacian with the squared ML of
        the ARCHITECTURE map: ML = (∂²g/∂x²)² + (∂²g/∂y²)², SML = Σ_U ML·[ML >= T].
        Nayar's original absolute-value ML,
        |2g(x,y) − g(x−1,y) − g(x+1,y)| + |2g(x,y) − g(x,y−1) − g(x,y+1)|, is ``"lapm"``.
    window_px : int
        Odd side of the square window U each pixel's value is aggregated over,
        ``1 <= window_px <= min(H, W)``; the variance operators (``lapv tenv glva glvn
        glvl wavv``) need >= 3.
    threshold : float
        Nayar's threshold T >= 0, in the units of the per-pixel response (grey levels
        squared for ``sml``): responses below T (compared in float32) count as 0 before
        the window sum. Only operators that sum a per-pixel response use it (``sml lape
        lapm lapd ten gder grae grat wavs bren cont curv sfil``; see
        ``FocusOperator(op).uses_threshold``); T > 0 with any other operator is an error.

    Returns
    -------
    focus : (H, W) float32
        >= 0, larger is sharper; a new array on every call.

    Raises
    ------
    InputError
        Unknown operator, a frame that is not a finite 2-D grey image of a supported
        dtype, a bad ``window_px`` or ``threshold``, or a negative frame for a ratio
        operator (``glvn cheb wavr dcte dctr hel``).

    Examples
    --------
    >>> import numpy as np
    >>> frame = np.zeros((5, 5), np.uint8); frame[2, 2] = 10
    >>> f = focus_measure(frame, window_px=1)
    >>> float(f[2, 2])  # (−20)² + (−20)²
    800.0
    >>> float(focus_measure(frame, window_px=3)[2, 2])  # + 4 neighbours at 10² each
    1200.0
    """
    name = _operator_name(operator)
    g = _as_float32(frame)
    _check_window(window_px, g.shape)
    _check_threshold(threshold)
    window_px = int(window_px)
    if threshold > 0 and name not in _THRESHOLDED:
        raise InputError(
            f"threshold applies only to operators that sum a per-pixel response "
            f"({', '.join(sorted(_THRESHOLDED))}); got threshold={threshold!r} with "
            f"operator {name!r}"
        )
    if window_px < 3 and name in _NEEDS_WINDOW_3:
        raise InputError(f"operator {name!r} needs window_px >= 3; got {window_px}")
    if name in _NEEDS_NON_NEGATIVE:
        low = float(g.min())
        if low < 0:
            raise InputError(
                f"operator {name!r} is a ratio of grey levels and needs a frame >= 0; got a "
                f"minimum of {low:g}"
            )
    return _OPERATORS[name](g, window_px, float(threshold))


def focus_measure_moments(frame, *, operator="sml", window_px=9, threshold=0.0, own_px=0):
    """The focus measure and the first moments of its per-pixel response over the window.

    For the operators that sum a per-pixel response r over the window U
    (``FocusOperator(op).uses_threshold``), returns ``(F, Mx, My)`` with F = Σ_U r (the same
    as :func:`focus_measure`) and Mx = Σ_U r·(x_q − x_p), My = Σ_U r·(y_q − y_p): Mx/F,
    My/F is the offset (px) of the window's energy centroid from its centre. A window on a
    slope measures the height under that centroid, not under its centre; the SFF core
    uses the offset to move the height back (``smdinspect.sff.centroid_correction``). For
    every other operator Mx and My are None. Two more separable filters per frame.

    With ``own_px`` > 0 a fourth value is returned: Σ of r over the ``own_px`` square
    (the same focus measure with a smaller window; None for the other operators).
    """
    name = _operator_name(operator)
    if name not in _THRESHOLDED:
        focus = focus_measure(frame, operator=name, window_px=window_px, threshold=threshold)
        return (focus, None, None, None) if own_px else (focus, None, None)
    g = _as_float32(frame)
    _check_window(window_px, g.shape)
    _check_threshold(threshold)
    window_px = int(window_px)
    resp = np.ascontiguousarray(_OPERATORS[name](g, 1, float(threshold)), dtype=np.float32)
    focus = _window_sum(resp, window_px)
    ones = _ones(window_px, np.float32)
    ramp = np.arange(window_px, dtype=np.float32) - np.float32(window_px // 2)
    # sepFilter2D correlates: kernel tap j multiplies r(p + j − h), i.e. offset j − h
    mx = cv2.sepFilter2D(resp, -1, ramp, ones, borderType=_BORDER)
    my = cv2.sepFilter2D(resp, -1, ones, ramp, borderType=_BORDER)
    if own_px:
        return focus, mx, my, _window_sum(resp, int(own_px))
    return focus, mx, my


def noise_sigma(frame: np.ndarray) -> float:
    """Standard deviation of a frame's white sensor noise (Immerkær 1996).

    The 3x3 mask [[1, −2, 1], [−2, 4, −2], [1, −2, 1]] cancels every linear and quadratic
    intensity pattern; for white noise of σ its response has E|·| = σ·6·√(2/π), so
    σ ≈ √(π/2)/6 · mean|g ⋆ mask| over the interior (of a central 1024² crop of larger
    frames). Texture and edges leak in, so on a sharp, textured frame this overestimates
    σ; on defocused frames it is close.
    """
    g = _as_float32(frame)
    if min(g.shape) < 3:
        return 0.0
    h, w = g.shape
    if h * w > 1 << 20:  # a central 1024² crop is plenty for one number
        r0, c0 = max(0, (h - 1024) // 2), max(0, (w - 1024) // 2)
        g = g[r0:r0 + 1024, c0:c0 + 1024]
    r = _filter(np.ascontiguousarray(g), _K_IMMERKAER)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2) / 6.0 * np.mean(np.abs(r), dtype=np.float64))


# --------------------------------------------------------------------------- noise band

#: Tiles (side, px; grid per axis) whose power spectra :func:`band_powers` measures.
BAND_TILE_PX = 64
BAND_GRID = 4
#: Upper edges (cycles/px) of the radial frequency bands, up to Nyquist.
BAND_EDGES = np.linspace(0.05, 0.5, 10)
#: Upper edges of the fine radial bins :func:`band_powers` measures; :func:`prefilter_sigma`
#: groups them into the bands of :data:`BAND_EDGES` on the output grid's frequencies
#: (each frame's bins moved by its scale: with a magnification change the same texture
#: lies at higher frequencies of a less magnified frame's own pixels).
FINE_EDGES = np.linspace(0.01, 0.5, 50)
#: Their centres.
FINE_CENTRES = FINE_EDGES - (FINE_EDGES[1] - FINE_EDGES[0]) / 2
#: A band is informative when defocus changes its power by at least this factor: the
#: power is texture + noise in the sharpest frame and about noise alone in the most
#: blurred one, so the factor is 1 + the band's signal-to-noise ratio (1 here).
BAND_MODULATION_MIN = 2.0
#: Frames (evenly spaced) whose spectra :func:`prefilter_sigma` compares at most.
BAND_MAX_FRAMES = 16


@lru_cache(maxsize=4)
def _band_layout(tile: int):
    y, x = np.mgrid[:tile, :tile]
    r = np.hypot(np.minimum(y, tile - y), np.minimum(x, tile - x)) / tile
    fine = np.minimum(np.searchsorted(FINE_EDGES, r, side="right"), len(FINE_EDGES))
    counts = np.bincount(fine.ravel(), minlength=len(FINE_EDGES) + 1)[:len(FINE_EDGES)]
    window = np.outer(np.hanning(tile), np.hanning(tile)).astype(np.float32)
    return fine.ravel(), counts, window


def band_powers(gray: np.ndarray, *, gain: float = 1.0) -> np.ndarray | None:
    """(tiles, fine bins) power spectrum of :data:`BAND_GRID`² tiles of one grey frame,
    summed over the radial bins ending at :data:`FINE_EDGES` (frequencies in the frame's
    own pixels; :func:`prefilter_sigma` groups them into bands); None for frames smaller
    than a tile.

    ``gain`` scales the grey levels first (as ``band_powers(gray * float32(gain))``, only
    the tiles are scaled: no whole-frame copy)."""
    h, w = gray.shape
    t = BAND_TILE_PX
    if min(h, w) < t:
        return None
    fine, _, window = _band_layout(t)
    out = np.empty((BAND_GRID * BAND_GRID, len(FINE_EDGES)))
    for i in range(BAND_GRID):
        for j in range(BAND_GRID):
            r0 = min(max(0, int((i + 0.5) * h / BAND_GRID) - t // 2), h - t)
            c0 = min(max(0, int((j + 0.5) * w / BAND_GRID) - t // 2), w - t)
            tile = gray[r0:r0 + t, c0:c0 + t].astype(np.float32)
            if gain != 1.0:
                tile *= np.float32(gain)
            tile = (tile - tile.mean()) * window
            power = np.abs(np.fft.fft2(tile)) ** 2
            out[i * BAND_GRID + j] = np.bincount(fine, power.ravel(),
                                                 minlength=len(FINE_EDGES) + 1)[:len(FINE_EDGES)]
    return out


def _in_bands(fine: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(tiles, bands) mean power per band of :data:`BAND_EDGES` from :func:`band_powers`'
    fine bins, a frame whose pixel is 1/``scale`` output pixels: its bin at f cycles per
    own pixel lies at f·scale cycles per output pixel. A band beyond the frame's own
    Nyquist (f·scale above 0.5·scale) holds no bin: NaN."""
    counts = _band_layout(BAND_TILE_PX)[1]
    band = np.searchsorted(BAND_EDGES, FINE_CENTRES * scale, side="right")
    keep = band < len(BAND_EDGES)
    n = np.bincount(band[keep], counts[keep], minlength=len(BAND_EDGES))
    out = np.stack([np.bincount(band[keep], row[keep], minlength=len(BAND_EDGES))
                    for row in fine])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, out / np.maximum(n, 1), np.nan)


def _modulation(powers: np.ndarray) -> np.ndarray:
    """Per band: max/min power over the frames, upper quartile over the tiles (the textured
    parts of the field decide). ``powers``: (frames, tiles, bands), NaN where a frame
    does not reach a band (the band then compares the frames that do)."""
    with np.errstate(invalid="ignore", divide="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a band no frame reaches
        ratio = np.nanmax(powers, axis=0) / np.maximum(np.nanmin(powers, axis=0), 1e-12)
        ratio[np.isfinite(powers).sum(axis=0) < 2] = np.nan  # one frame: nothing to compare
        return np.nanpercentile(ratio, 75, axis=0)


@lru_cache(maxsize=32)
def _noise_modulation(frames: int) -> np.ndarray:
    """:func:`_modulation` of white noise in ``frames`` frames (fixed seed)."""
    rng = np.random.default_rng(0)
    side = BAND_TILE_PX * BAND_GRID
    return _modulation(np.asarray([_in_bands(band_powers(rng.standard_normal((side, side))
                                                         .astype(np.float32)))
                                   for _ in range(frames)]))


def prefilter_sigma(powers, operator: str = "sml", *, scales=None) -> tuple[float, list[float]]:
    """Gaussian pre-filter (σ, px) that keeps an operator off the noise-only frequencies.

    ``powers``: :func:`band_powers` of several frames of a sweep; ``scales``: for each,
    the size of an output pixel in that frame's pixels (``Alignment.scale``; 1 for all
    when omitted), so that every frame's spectrum is read on the output grid's
    frequencies and σ is in output pixels. (Read in each frame's own pixels, a texture
    seen 1.4× less magnified spreads into a band 1.4× higher, which then looks
    modulated by defocus too: the cut-off rose a band and σ fell 0.75 → 0.64 px on a
    noisy cone through an ordinary lens.) In each band and tile,
    defocus moves the power between texture + noise (sharp) and noise alone (blurred); the
    band's modulation is the ratio of its largest to its smallest power over the frames,
    its upper quartile over the tiles (the textured parts of the field decide). A power
    estimate fluctuates, so white noise alone shows some modulation too (the same
    statistic over as many frames of simulated white noise, M_noise). The cut-off f_c is
    the lower edge of the first band (from 0.1 cycles/px up) whose modulation is below
    :data:`BAND_MODULATION_MIN` × M_noise: above it the sensor noise outweighs the
    texture. A derivative operator of order d multiplies
    the power at f by f^2d, so it listens mostly to the highest, noisiest frequencies; a
    Gaussian of σ = √d / (2π f_c) puts the peak of f^2d·exp(−4π²σ²f²) at f_c. No
    noise-only band, no informative band at all (a textureless field: blurring cannot
    help) or an operator that is not a derivative (d = 0): σ = 0.
    Returns (σ, the modulation per band).
    """
    scales = [1.0] * len(powers) if scales is None else list(scales)
    stack = [(p, s) for p, s in zip(powers, scales) if p is not None]
    order = _DERIVATIVE_ORDER.get(_operator_name(operator), 0)
    if len(stack) < 2:
        return 0.0, []
    if len(stack) > BAND_MAX_FRAMES:  # evenly spaced, as many as the calibration has
        stack = [stack[i] for i in np.linspace(0, len(stack) - 1, BAND_MAX_FRAMES).round().astype(int)]
    modulation = _modulation(np.asarray([_in_bands(p, s) for p, s in stack]))
    # a power estimate fluctuates, so even pure noise has max/min > 1: compare with the
    # same statistic on white noise seen in as many frames
    noisy = np.nonzero(modulation[1:] < BAND_MODULATION_MIN * _noise_modulation(len(stack))[1:])[0]
    # 1e6: "no noise at all"; None: a band no two frames reach
    table = [round(float(min(m, 1e6)), 2) if np.isfinite(m) else None for m in modulation]
    if order == 0 or noisy.size == 0 or noisy[0] == 0:
        return 0.0, table  # no noise-only band, or no texture at all: nothing to gain
    f_c = float(BAND_EDGES[noisy[0]])  # the noisy band's lower edge
    return math.sqrt(order) / (2 * math.pi * f_c), table


def magnification_exponent(operator: str, powers, scales, sigma_px: float = 0.0) -> float:
    """The exponent k of the focus's change with magnification (F ∝ m^(−k)) for the
    texture this sweep shows, from the operator's discrete response.

    :attr:`FocusOperator.magnification_exponent` (d × p: d the derivative order, p the
    curve power) is the continuous derivative's law, |2 sin(πf)|^d ≈ (2πf)^d, which holds
    for texture far below Nyquist. A difference operator's amplitude response is
    (2 sin πf)^d, whose log-slope is d·πf·cot(πf): at 0.15 cycles/px 0.93 d, at 0.3
    0.69 d. Here it is averaged over the frequencies the operator responds to in the
    sharpest sampled frame (its fine spectrum from :func:`band_powers` less the sweep's
    floor in each bin, the sensor noise whose focus is not scaled, weighted by the
    response's power and the pre-filter's; ``scales`` as in :func:`prefilter_sigma`,
    ``sigma_px`` in output pixels). Not exact: the camera's own blur and the defocus
    are not in it (a noise-free cone through a 1.5× ordinary lens: 3.2 from this for
    SML, where the heights' bias vanishes at 3.5; −0.01 Δd instead of +0.02 at 4; a
    slanted plane under a 2× change: 3.4 where 4 is best, −0.038 Δd instead of
    +0.011). The frames around a peak are partly defocused, their spectra closer to
    the continuous law, so the right k lies between this and the nominal one.
    Returns the nominal exponent without usable spectra."""
    op = FocusOperator(operator)
    nominal = op.magnification_exponent
    d = _DERIVATIVE_ORDER.get(op.value, 0)
    pairs = [(pw, s) for pw, s in zip(powers, scales) if pw is not None]
    if not d or not pairs:
        return nominal
    centre = FINE_CENTRES
    resp = np.sin(np.pi * centre) ** (2 * d)
    # the sharpest frame (the most response-weighted power), less the sweep's floor in
    # each bin (its most blurred frames: sensor noise, whose own focus is not scaled)
    spectra = [pw.sum(axis=0) for pw, _ in pairs]
    k = int(np.argmax([float(np.sum(sp * resp)) for sp in spectra]))
    texture = np.clip(spectra[k] - np.min(spectra, axis=0), 0.0, None)
    s = pairs[k][1]
    w = texture * resp * np.exp(-4.0 * np.pi ** 2 * (sigma_px * s) ** 2 * centre ** 2)
    if not np.sum(w) > 0:
        return nominal
    x = np.pi * centre
    slope = float(np.sum(w * x / np.tan(x)) / np.sum(w))
    return d * slope * op.curve_power


def prefilter(gray: np.ndarray, sigma_px: float) -> np.ndarray:
    """The grey frame smoothed by a Gaussian of ``sigma_px`` (itself when 0)."""
    if sigma_px <= 0:
        return gray
    return cv2.GaussianBlur(gray, (0, 0), sigma_px, borderType=_BORDER)


@lru_cache(maxsize=256)
def noise_focus_spread(operator: str, window_px: int, threshold: float = 0.0,
                       prefilter_px: float = 0.0) -> float:
    """Relative spread (std / mean) of the focus measure of white noise, after the
    Gaussian pre-filter of ``prefilter_px``. Without one it falls as 1/window_px (the
    window sums window_px² independent responses); a pre-filter correlates neighbouring
    responses, so fewer independent ones are summed and a noise-only curve can fake a
    larger peak-to-floor ratio (the confidence's noise test scales with it)."""
    f = _noise_focus_sample(operator, window_px, threshold, prefilter_px, side=192, seed=1,
                            margin=8).astype(np.float64)
    return float(f.std() / f.mean()) if f.mean() > 0 else 0.0


@lru_cache(maxsize=256)
def noise_focus(operator: str, window_px: int, threshold: float = 0.0,
                prefilter_px: float = 0.0) -> float:
    """Median focus measure of white noise of σ = 1 (grey levels) around a mid grey
    (after the Gaussian pre-filter of ``prefilter_px``, if any).

    An energy operator's noise response scales as σ², an amplitude one's as σ
    (``FocusOperator.curve_power``); with a threshold the scaling is only approximate.
    """
    return float(np.median(_noise_focus_sample(operator, window_px, threshold, prefilter_px,
                                               side=96, seed=0, margin=4)))


def _noise_focus_sample(operator: str, window_px: int, threshold: float, prefilter_px: float,
                        *, side: int, seed: int, margin: int) -> np.ndarray:
    """Focus measure of a ``side``² frame of white noise of σ = 1 around a mid grey (after
    the pre-filter), without the ``margin`` + half-window border the window reflects."""
    rng = np.random.default_rng(seed)
    g = prefilter((128.0 + rng.standard_normal((side, side))).astype(np.float32), prefilter_px)
    f = focus_measure(g, operator=operator, window_px=window_px, threshold=threshold)
    m = window_px // 2 + margin
    return f[m:-m, m:-m]
