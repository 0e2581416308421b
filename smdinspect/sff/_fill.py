"""The dense surface: measured heights plus edge-aware fill where nothing was measured.

Measured (reliable) heights are never changed. Elsewhere the height is a
confidence-weighted, edge-aware average of the measured heights around it, with the
all-in-focus image as the guide: the normalised form of Min et al.'s fast global
smoother (a weighted-least-squares filter, OpenCV ``ximgproc``),

    h_fill = FGS(c·h) / FGS(c),

c the confidence of the measured pixels (0 elsewhere). The guide's edges stop the
propagation, so a filled pixel takes the height of the measured pixels that look like
it (the same part), not of whatever is nearest. Its uncertainty is the spread of those
heights (the same filter on c·(h − h_fill)²) combined with how far it lies from any
measurement (``spread_per_px_mm`` per pixel of distance, 0.1 frame step by default).
"""

from __future__ import annotations

import numpy as np

__all__ = ["fill_surface"]

#: Smoothness weight of the fast global smoother (large: propagates far).
FGS_LAMBDA = 2000.0
#: Colour scale of the guide's edges (8-bit grey levels).
FGS_SIGMA_COLOR = 12.0


def fill_surface(height_mm: np.ndarray, reliable: np.ndarray, guide: np.ndarray, *,
                 confidence: np.ndarray | None = None, step_mm: float = 1.0,
                 spread_per_px_mm: float | None = None, beyond: np.ndarray | None = None,
                 z_range_mm: tuple[float, float] | None = None):
    """Fill the unmeasured pixels of a height map, guided by the all-in-focus image.

    Parameters
    ----------
    height_mm : (H, W) float32
    reliable : (H, W) bool
        Measured pixels (kept as they are).
    guide : (H, W) or (H, W, 3) array
        The all-in-focus image (any dtype; scaled to 8 bits for the filter).
    confidence : (H, W) float32, optional
        Weights of the measured pixels (1 when omitted).
    step_mm : float
        Frame step; sets the default distance term of the uncertainty.
    beyond : (H, W) int8, optional
        −1 / +1 for pixels sharpest on the first / last frame (``Surface.beyond``):
        they take that end of ``z_range_mm`` (a bound: the surface is there or beyond)
        and count as sources of the fill, with uncertainty one step.
    z_range_mm : (z_first, z_last)
        Needed with ``beyond``.

    Returns
    -------
    filled_height_mm : (H, W) float32
        Equal to ``height_mm`` where ``reliable``.
    filled : (H, W) bool
        True where the height was filled (``~reliable``).
    sigma_mm : (H, W) float32
        Uncertainty of the filled heights (0 where measured).
    """
    import cv2

    if not hasattr(cv2, "ximgproc"):
        raise ImportError("the dense surface needs OpenCV's ximgproc module: "
                          "pip install opencv-contrib-python-headless")
    h = np.asarray(height_mm, np.float32)
    rel = np.asarray(reliable, bool)
    filled = ~rel
    anchor = np.zeros(h.shape, bool)
    if beyond is not None and z_range_mm is not None:
        b = np.asarray(beyond)
        anchor = (b != 0) & ~rel
        h = np.where(b < 0, np.float32(z_range_mm[0]),
                     np.where(b > 0, np.float32(z_range_mm[1]), h)).astype(np.float32)
        h = np.where(rel, np.asarray(height_mm, np.float32), h)
    src = rel | anchor
    if not src.any():
        return h.copy(), np.ones(h.shape, bool), np.full(h.shape, np.inf, np.float32)
    if rel.all():
        return h.copy(), filled, np.zeros(h.shape, np.float32)
    g = _guide8(guide)
    # one plane at a time, in place: the fill of a 12-Mpixel map stays within a few
    # planes of the surface (the smoother itself needs about three more)
    w = np.ones(h.shape, np.float32) if confidence is None else np.clip(
        confidence, 0, 1).astype(np.float32)
    w *= rel
    w[anchor] = 0.5
    base = float(np.median(h[src]))
    hz = h - np.float32(base)  # centred: better float32 sums
    hz[~src] = 0.0

    def smooth(src: np.ndarray) -> np.ndarray:
        return cv2.ximgproc.fastGlobalSmootherFilter(g, src, FGS_LAMBDA, FGS_SIGMA_COLOR)

    den = smooth(w)
    tiny = np.float32(1e-6)
    none = den <= tiny  # no source reaches: the estimate is 0 there
    np.maximum(den, tiny, out=den)
    est = w * hz
    est = smooth(est)
    est /= den
    est[none] = 0.0
    del none
    # the spread of the sources' heights about the estimate, by the same filter
    hz -= est
    np.square(hz, out=hz)
    hz *= w
    del w
    var = smooth(hz)
    del hz
    var /= den
    del den
    est += np.float32(base)
    np.copyto(est, h, where=src)
    out = est
    sigma = cv2.distanceTransform((~src).astype(np.uint8), cv2.DIST_L2, 3)
    sigma *= np.float32(0.1 * abs(step_mm) if spread_per_px_mm is None else spread_per_px_mm)
    np.square(sigma, out=sigma)
    np.maximum(var, 0, out=var)
    sigma += var
    del var
    np.sqrt(sigma, out=sigma)
    sigma[anchor] = abs(step_mm)
    sigma[rel] = 0.0
    return out, filled, sigma


def _guide8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    img = img.astype(np.float32)
    hi = float(np.percentile(img, 99.5)) or 1.0
    lo = float(np.percentile(img, 0.5))
    return np.clip((img - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255).astype(np.uint8)
