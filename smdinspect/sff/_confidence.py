"""Per-pixel confidence in [0, 1] from the fitted focus peak.

Six cues, each mapped to [0, 1] by a smooth ramp and multiplied (R over the fit's
support only: a 3-sample fit is exact and R does not judge it):

* **Reliability R** (Pertuz et al.): 20·log10(F_peak / mean|F − model|) over the ±k
  frames around the peak. A clean Gaussian peak gives R ≫ 20 dB; a noise-only
  (textureless) curve or a distorted one gives R around or below 20 dB. Ramp from
  ``r_low_db`` = 14 dB (0) to ``r_high_db`` = 26 dB (1); 20 dB maps to 0.5.
* **Peak width σ_F**: a focus peak cannot be narrower than the optics allow; a peak
  much wider than the stack's typical width (the median σ_F of the pixels with
  R ≥ 20 dB) is a weak, low-texture one. Ramp from 1 at 2× to 0 at 4× the typical width.
* **Noise test** on the peak-to-floor ratio A/b (A the highest sampled focus above the
  floor b): a textureless pixel's curve is the sensor noise's focus measure, whose
  spread relative to its mean falls as 1/√N with the N = window² pixels summed, so the
  ratio is scaled by window/9 and ramped from 1.2 (0) to 2.2 (1).
* **Ambiguity** A = (strongest focus more than k frames away from the peak) / F_peak,
  less the fitted Gaussian's own value k+½ frames out (the tail of a wide peak is not a
  second peak). Flat, textureless curves have A near 1; a second peak (a defocused
  edge of a taller part bleeding over low texture) gives a large A. Ramp from 1 at
  A = 0.35 to 0 at 0.7.

* **Second mode**: within ±k frames, the largest rise of the curve after a dip, over
  A. One surface point has a unimodal focus curve; two modes mean two depths in the
  window (a defocused edge's blur next to weak texture) or noise, and in a short stack
  (7 frames, k = 3) the ambiguity above sees nothing. Ramp from 1 at 0.15 to 0 at 0.35.

* **Precision** (when :func:`precision_steps` is given): the heights' random error
  from the even/odd split of each curve, the noise's part only. Ramp from 1 at
  σ = 0.2 Δd to 0 at 0.4 Δd; unknown (curves too narrow to split) is not judged.

Finally, **depth edges**: a focus window that straddles a height step mixes two depths,
and the sharp edge of the higher part (a component body) wins over the weak texture of
the lower one (solder mask), so a band of lower pixels takes the higher height. No focus
curve shows this, so :func:`depth_edge_mask` looks for it in the result: pixels within
half a window of a place where the reliable heights in a 5 × 5 square differ by more
than ``edge_jump_steps`` frame steps (default 3), and above that step's middle level,
are made unreliable. The low side keeps its depths: a
fillet at the foot of a termination is measured, the termination's rim is not. A
fillet at 45° rises about one step over five pixels, far from a step.

The same bleeding seen from the low side's own pixels: :func:`borrowed_mask` flags a
pixel whose small centred window (``FocusConfig.own_window_px``) is clearly peaked
elsewhere than the main window, whose height therefore came from an edge inside it;
:func:`depth_edge_mask` also looks across a gap of unreliable pixels at a step.

Pixels whose peak lies on the first or last frame, or whose fit is inverted (σ² ≤ 0)
or lands outside its neighbours, get confidence 0. The default reliability threshold
on the product is 0.5 (``FocusConfig.min_confidence``).
"""

from __future__ import annotations

import numpy as np

from ._depth import PeakFit

__all__ = ["blur_px_per_frame", "borrowed_mask", "confidence_map", "defocus_halo_mask",
           "depth_edge_mask", "halo_mask", "hidden_step_mask", "precision_steps",
           "step_levels", "unsupported_mask"]

R_LOW_DB, R_HIGH_DB = 14.0, 26.0
WIDTH_OK, WIDTH_BAD = 2.0, 4.0
AMBIG_OK, AMBIG_BAD = 0.35, 0.70
SECOND_OK, SECOND_BAD = 0.15, 0.35
SNR_BAD, SNR_OK = 1.2, 2.2
#: Side of the square (in focus windows) over which :func:`precision_steps` averages the
#: split differences. The windows around a pixel share its noise, so one window holds
#: about one independent draw; 3 × 3 windows hold about nine, and the precision is a
#: property of a region's texture and noise, not of one pixel.
PRECISION_BOX_WINDOWS = 3
#: Precision cue ramp (1σ, frame steps): 1 at 0.2 Δd, 0 at 0.4 Δd, 0.5 at 0.3 Δd, where
#: an error of one step is 3.3σ.
PRECISION_OK, PRECISION_BAD = 0.2, 0.4
#: Share of a square that must hold split estimates for its precision to be told.
PRECISION_MIN_SHARE = 0.3
#: Below this share of its own peak (above the floor), a small window centred on the
#: pixel says the main window's peak frame is not where the pixel's own texture is sharp.
OWN_SHARE_MIN = 0.2


def _ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """0 below ``lo``, 1 above ``hi``, smoothstep between (reversed when lo > hi)."""
    t = np.subtract(x, lo)
    np.divide(t, hi - lo, out=t)
    np.clip(t, 0.0, 1.0, out=t)
    u = np.multiply(t, 2.0)  # t·t·(3 − 2t), in place: the same operations in order
    np.subtract(3.0, u, out=u)
    np.multiply(t, t, out=t)
    np.multiply(t, u, out=t)
    return t


def confidence_map(fit: PeakFit, *, window_px: int = 9,
                   cues: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """Confidence of every pixel's height.

    Parameters
    ----------
    fit : PeakFit
    window_px : int
        The focus window the fit's curves were measured with (scales the noise test).
    cues : dict, optional
        :func:`confidence_cues` already computed for ``fit``.

    Returns
    -------
    confidence : (H, W) float32 in [0, 1]
    """
    conf = np.ones(fit.interior.shape, np.float32)
    for cue in (cues or confidence_cues(fit, window_px=window_px)).values():
        conf *= cue
    conf[~fit.interior] = 0.0
    return conf


def confidence_cues(fit: PeakFit, *, window_px: int = 9, noise_spread_gain: float = 1.0,
                    precision: np.ndarray | None = None,
                    memo: dict | None = None) -> dict[str, np.ndarray]:
    """The cues of :func:`confidence_map`, each (H, W) in [0, 1]: five from the fit, and
    a sixth, ``precision``, when the heights' random error (steps, NaN unknown:
    :func:`precision_steps`) is given. The width cue compares each peak's width with
    the typical one of the map (the median of the clearly peaked pixels'); with
    ``memo`` a dict, a typical width it holds is used (and one computed is put in it),
    so that the bands of one grid are judged alike.

    The noise test: on a textureless pixel the focus curve is the
    sensor noise's focus measure, whose frame-to-frame spread relative to its mean falls
    as 1/√N with the N = window_px² pixels summed, so the peak-to-floor ratio A/b it can
    fake shrinks as 1/window_px. The ramp is on (A/b)·window_px/9: at the default 9-px
    window from A/b = 1.2 (0) to 2.2 (1); a 5-px window needs 1.8× more.
    ``noise_spread_gain`` (≥ 1 with a noise pre-filter: its correlated noise sums fewer
    independent responses, :func:`~smdinspect.sff._focus.noise_focus_spread`) divides
    the ratio alike. With alignment the ratio is in the units of the reference (the
    most magnified) frame, where the magnification correction scales the scene's focus
    down and leaves the noise's: the strictest frame's units. (Judging each peak in its
    own frame's units instead let wrong heights through wherever a noise-dominated sweep
    had been registered wrongly but consistently.)
    """
    r = np.nan_to_num(fit.reliability_db, nan=0.0)
    c_r = _ramp(r, R_LOW_DB, R_HIGH_DB)
    sigma = fit.sigma_mm
    good = fit.interior & (r >= 20.0) & np.isfinite(sigma)
    if memo is not None and "typical_sigma_mm" in memo:
        typical = memo["typical_sigma_mm"]
    else:
        typical = float(np.median(sigma[good])) if np.count_nonzero(good) > 16 else np.nan
        if memo is not None:
            memo["typical_sigma_mm"] = typical
    if np.isfinite(typical) and typical > 0:
        c_w = _ramp(np.nan_to_num(sigma / typical, nan=np.inf), WIDTH_BAD, WIDTH_OK)
    else:
        c_w = np.ones_like(c_r)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.nan_to_num(fit.f_best / fit.floor, nan=0.0, posinf=1e6) * (window_px / 9.0)
    if noise_spread_gain != 1.0:
        snr = snr / np.float32(noise_spread_gain)
    cues = {"reliability": c_r, "width": c_w,
            "ambiguity": _ramp(fit.ambiguity, AMBIG_BAD, AMBIG_OK),
            "second_mode": _ramp(fit.second_mode, SECOND_BAD, SECOND_OK),
            "noise": _ramp(snr, SNR_BAD, SNR_OK)}
    if precision is not None:  # unknown (NaN): not judged
        cues["precision"] = _ramp(np.nan_to_num(precision, nan=0.0), PRECISION_BAD, PRECISION_OK)
    return cues


def precision_steps(split_steps: np.ndarray, *, box_px: int) -> np.ndarray:
    """(H, W) float32: 1σ random error of the measured heights, in frame steps; NaN
    where it cannot be told (fewer than :data:`PRECISION_MIN_SHARE` of the square hold a
    split estimate: narrow curves, at steps coarse against the depth of field, where a
    half of the samples misses the peak).

    From the even/odd split of each focus curve (:attr:`PeakFit.split_steps`): the
    difference d of the two halves' peaks has the variance of both halves, each fitted
    from half the samples, i.e. about four times the full fit's: σ = √mean(d²)/2 over a
    ``box_px`` square. Only the random part: what every frame shares (a window mixing
    two depths, a halo, a wrong curve shape) cancels out of d and is the other cues'.
    """
    import cv2

    d = np.asarray(split_steps, np.float32)
    have = np.isfinite(d).astype(np.float32)
    d2 = np.where(have > 0, d * d, 0).astype(np.float32)
    size = (box_px, box_px)
    share = cv2.blur(have, size, borderType=cv2.BORDER_REFLECT)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = cv2.blur(d2, size, borderType=cv2.BORDER_REFLECT) / share
    sigma = np.sqrt(np.maximum(mean, 0)) * np.float32(0.5)
    sigma[~(share >= PRECISION_MIN_SHARE)] = np.nan
    return sigma.astype(np.float32)


def borrowed_mask(share: np.ndarray, ratio: np.ndarray, *, own_px: int,
                  noise_gain: float = 1.0) -> np.ndarray:
    """(H, W) bool: pixels whose focus peak was borrowed from a neighbour.

    The main window sums the focus response of window² pixels; next to a sharp edge
    (a body's rim, a termination's top) the edge's response outweighs the pixel's own
    weak texture and the window peaks where the edge is in focus. A small ``own_px``
    window centred on the pixel leaves the edge out: when its own curve is clearly
    peaked (its peak-to-floor ratio, scaled like the noise test to its window, at least
    ``SNR_OK``) but it has less than ``OWN_SHARE_MIN`` of that peak at the main
    window's peak frame (``share``, :meth:`PeakTracker.own_share`), the two windows
    see different depths and the main one's is not the pixel's. A noise-dominated small
    window proves nothing and vetoes nothing.
    """
    scaled = ratio * np.float32(own_px / 9.0 / noise_gain)
    return (share < OWN_SHARE_MIN) & (scaled >= SNR_OK)


def step_levels(height_mm: np.ndarray, reliable: np.ndarray, *, jump_mm: float,
                span_px: int) -> np.ndarray:
    """(H, W) float32: at each reliable pixel whose ``span_px`` square holds reliable
    heights more than ``jump_mm`` apart, the middle of their range (a height step's
    level); −inf elsewhere."""
    import cv2

    unmeasured = ~reliable
    buf = height_mm.astype(np.float32)   # a copy: filled in below
    square = np.ones((span_px, span_px), np.uint8)
    # replicated borders: OpenCV's constant border is ∓FLT_MAX, finite under every test
    buf[unmeasured] = -np.inf
    hi = cv2.dilate(buf, square, borderType=cv2.BORDER_REPLICATE)
    buf[unmeasured] = np.inf
    lo = cv2.erode(buf, square, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(invalid="ignore", over="ignore"):
        np.subtract(hi, lo, out=buf)
        flat = unmeasured | ~(buf > jump_mm)   # not at a step (NaN spans: no step)
        hi += lo
        hi *= 0.5
        hi[flat] = -np.inf
        return hi


def depth_edge_mask(height_mm: np.ndarray, reliable: np.ndarray, *, jump_mm: float,
                    radius_px: int, span_px: int = 5,
                    wide_span_px: int | tuple[int, ...] = 0,
                    gap_span_px: int = 0,
                    levels: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: pixels within ``radius_px`` of a height step, on its high side.

    A step is where the reliable heights inside a ``span_px`` square differ by more than
    ``jump_mm`` (a measured step is smeared over a few pixels, so neighbours alone miss
    it); its level is the middle of that range. Bleeding makes low pixels next to a step
    take the *high* side's height, so only pixels above the level of a step within
    ``radius_px`` (the highest such level) are flagged: the correctly measured low side,
    a fillet at the foot of a termination, stays.

    The pixels right at a step are often unreliable already (their curves mix the two
    depths), and a gap of unreliable pixels as wide as the square hides the step from
    it while the bled band beyond the gap stays reliable. With ``wide_span_px`` (one
    side or several) wider squares look across such gaps, each for a rise of more than
    ``jump_mm`` · wide/span (the same slope: a steep fillet is no more a step in the
    wide square than in the narrow one).

    ``gap_span_px`` looks across wider gaps (those the halo check leaves beside a tall
    step grow with the step): a square of that side over the pixels that border an
    unreliable one only, for a rise steeper than the step's slope (``jump_mm`` per
    ``span_px − 1`` px) over half the square, the most a gap can span from the
    square's centre. A continuous measured slope has no such pixels inside it, so a
    steep fillet is not taken for a step.

    ``levels``, when given, is ``step_levels(height_mm, reliable, jump_mm=jump_mm,
    span_px=span_px)`` already computed (one map judged at several radii); it is not
    modified.
    """
    h = height_mm.astype(np.float32, copy=False)
    if levels is None:
        level = step_levels(h, reliable, jump_mm=jump_mm, span_px=span_px)
    else:
        level = levels
    for wide in (wide_span_px,) if isinstance(wide_span_px, int) else wide_span_px:
        if wide > span_px:
            more = step_levels(h, reliable, jump_mm=jump_mm * wide / span_px, span_px=wide)
            level = np.maximum(level, more, out=more)
    flagged = _above_step(h, level, radius_px)
    if gap_span_px > span_px:
        import cv2

        unmeasured = (~reliable).view(np.uint8)
        border = reliable & (cv2.dilate(unmeasured, np.ones((3, 3), np.uint8)) > 0)
        across = step_levels(h, border, span_px=gap_span_px,
                             jump_mm=jump_mm * (gap_span_px - 1) / (2 * (span_px - 1)))
        # judged apart: a gap's level (the middle of a tall rise) must not raise the
        # level the pixels beside a nearer, lower step are judged by
        flagged |= _above_step(h, across, radius_px)
    return flagged


def hidden_step_mask(height_mm: np.ndarray, reliable: np.ndarray, measured: np.ndarray, *,
                     jump_mm: float, radius_px: int, side_px: int) -> np.ndarray:
    """(H, W) bool: reliable pixels on the high side of a step whose low side is all
    unreliable, read from the unreliable pixels' own peaks.

    Beside a tall body on weak texture the board's focus curves carry the body edge's
    defocused blur as a second mode, so the board there is unreliable; the band of
    board pixels within half a window of the body takes the body's height from the
    edge in its window and stays reliable, and :func:`depth_edge_mask` sees no step:
    no reliable height lies below. Each unreliable peak is untrusted alone, but most of
    them still read their own surface (randomised tuning boards: 71-82 % of the peaks
    called unreliable for their shape, a halo or a depth edge lie within 1 Δd). So a
    reliable pixel within ``radius_px`` of an unreliable ``measured`` one (in the field,
    a height read) is flagged where at least a quarter of its ``side_px`` square is
    such unreliable pixels and more than half of them read more than ``jump_mm`` below
    it: the majority of its unreliable neighbours see a lower surface (a quarter: a
    small unreliable island, whose peaks are as likely noise, tells nothing). Only the
    high side is flagged (only it bleeds).

    Counted per pixel through heights quantised by ``jump_mm``/2 (one box filter a
    level that holds a candidate; a reading counts as below when it lies more than
    ``jump_mm`` below, by up to ``jump_mm``/2 more).
    """
    import cv2

    h = height_mm.astype(np.float32, copy=False)
    un = measured & ~reliable & np.isfinite(h)
    out = np.zeros(h.shape, bool)
    if not un.any() or not reliable.any() or not jump_mm > 0:
        return out
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius_px + 1,) * 2)
    cand = reliable & (cv2.dilate(un.view(np.uint8), disc) > 0)
    if not cand.any():
        return out
    size = (side_px, side_px)

    def count(mask: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(mask.view(np.uint8), cv2.CV_32F, size, normalize=False,
                             borderType=cv2.BORDER_CONSTANT)

    n_un = count(un)
    cand &= n_un >= side_px * side_px // 4
    q = np.float32(jump_mm / 2.0)
    base = np.float32(h[un].min())
    level = np.floor((np.where(un, h, base) - base) / q).astype(np.int32)
    top = int(level[un].max()) + 1  # every reading lies below this level
    need = np.floor((np.where(cand, h, base) - np.float32(jump_mm) - base) / q)
    need = np.clip(need, 0, top).astype(np.int32)  # readings of lower levels count
    below = np.zeros(h.shape, np.float32)
    for k in np.unique(need[cand]):
        if k == 0:
            continue  # nothing lies below the lowest level
        sel = cand & (need == k)
        below[sel] = n_un[sel] if k >= top else count(un & (level < k))[sel]
    return cand & (below > 0.5 * n_un)


def _above_step(h: np.ndarray, level: np.ndarray, radius_px: int) -> np.ndarray:
    """Pixels above the highest step level (−inf: none) within ``radius_px``."""
    with np.errstate(invalid="ignore", over="ignore"):
        if not np.isfinite(level).any():
            return np.zeros(h.shape, bool)
        if radius_px > 0:
            level = dilate_disc(level, radius_px)
        return np.isfinite(level) & (h > level)


def dilate_disc(image: np.ndarray, radius_px: int) -> np.ndarray:
    """Grey dilation (max filter) of ``image`` by OpenCV's elliptic disc of ``radius_px``,
    with replicated borders (OpenCV's constant border for dilate is −FLT_MAX, a finite
    value under every pixel within the radius of the image's edge).

    A large disc is the union of the rectangles spanned by its rows of equal half-width;
    a rectangle's dilation is separable (O(1) per pixel at any size), so the max of those
    dilations is the disc's exactly, at 2× (r = 45 px) the speed of OpenCV's
    point-by-point pass over the disc.

    Pixels farther than the radius (in rows or columns) from every value above −inf
    stay −inf, so only the bounding box of those values, grown by the radius, is
    dilated: a map of step levels (:func:`step_levels`) is −inf but near its few steps
    (pcb-oblique: 19 of 3.1 Mpixel; r = 45 px took 0.3-0.5 s over the whole map). The
    grown box's own edges are −inf where they are not the image's, so its replicated
    border adds nothing the image does not hold. (An image holding NaN, which has no
    order under max, is dilated whole as before.)
    """
    rows = np.flatnonzero((image != -np.inf).any(axis=1))
    if rows.size == 0:
        return np.full_like(image, -np.inf)
    if np.isnan(image[rows[0]:rows[-1] + 1]).any():
        return _dilate_disc(image, radius_px)
    cols = np.flatnonzero((image[rows[0]:rows[-1] + 1] != -np.inf).any(axis=0))
    box = (slice(max(0, rows[0] - radius_px), rows[-1] + radius_px + 1),
           slice(max(0, cols[0] - radius_px), cols[-1] + radius_px + 1))
    if image[box].size == image.size:
        return _dilate_disc(image, radius_px)
    out = np.full_like(image, -np.inf)
    out[box] = _dilate_disc(image[box], radius_px)
    return out


def _dilate_disc(image: np.ndarray, radius_px: int) -> np.ndarray:
    """:func:`dilate_disc` over the whole of ``image``."""
    import cv2

    side = 2 * radius_px + 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))
    if radius_px < 16:
        return cv2.dilate(image, disk, borderType=cv2.BORDER_REPLICATE)
    rows: dict[int, int] = {}  # half-width -> the largest |dy| of a row that wide
    for dy in range(radius_px + 1):
        half = int(np.flatnonzero(disk[radius_px - dy]).max()) - radius_px
        rows[half] = max(rows.get(half, 0), dy)
    out = None
    for half, dy in rows.items():
        rect = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * half + 1, 2 * dy + 1))
        part = cv2.dilate(image, rect, borderType=cv2.BORDER_REPLICATE)
        out = part if out is None else np.maximum(out, part, out=out)
    return out


def halo_mask(amplitude: np.ndarray, frame_pos: np.ndarray, candidate: np.ndarray, *,
              radius_px: int, min_frames: float = 2.0, ratio: float = 4.0) -> np.ndarray:
    """(H, W) bool: peaks that a much stronger neighbour at another depth can explain.

    A bright, sharp edge at depth z_q spreads its contrast over a disc that grows with
    defocus; in the weak texture next to it the focus curve then peaks at a frame where
    the *edge* is out of focus: a second, wrong peak (a halo). Such a pixel's peak
    amplitude A_p is small against the edge's A_q. A pixel is flagged when some
    ``candidate`` neighbour q within ``radius_px`` has its peak at least ``min_frames``
    frames away and ``A_q > ratio · A_p``. Computed on a grid reduced so that the
    radius is about 4 cells, one max-filter per frame bin: cheap at any frame count.

    Parameters
    ----------
    amplitude : (H, W) float32
        Highest sampled focus above the curve's floor (``PeakFit.f_best``; the fitted
        amplitude of a sharp peak between two frames is too noisy for this).
    frame_pos : (H, W) float
        Peak position in frames (fractional).
    candidate : (H, W) bool
        Pixels that may explain others' peaks (those with a trustworthy own peak).
    """
    return _HaloGroups(amplitude, frame_pos, candidate).mask(
        radius_px=radius_px, min_frames=min_frames, ratio=ratio).reshape(amplitude.shape)


def halo_reach_px(radius_px: int) -> int:
    """Farthest a pixel :func:`halo_mask` flags can lie from the neighbour that explains
    it, at ``radius_px``: the radius plus what pooling into cells of ``radius_px // 4``
    px adds (up to a cell less one pixel)."""
    return radius_px + max(1, radius_px // 4) - 1


class _HaloGroups:
    """The pixels of :func:`halo_mask` sorted by peak frame bin, shared by every reach.

    The sort is by a 8- or 16-bit key (numpy's stable sort is then a radix sort), and
    each bin's pixels are then a contiguous slice, so the per-bin look-ups of the
    dilated cell maps walk memory in order; only the candidates carrying a nonzero
    amplitude are pooled into cells.
    """

    def __init__(self, amplitude: np.ndarray, frame_pos: np.ndarray,
                 candidate: np.ndarray) -> None:
        h, w = amplitude.shape
        self.shape = (h, w)
        bins = np.clip(np.round(np.nan_to_num(frame_pos, nan=0.0, posinf=0.0, neginf=0.0)), 0,
                       None).astype(np.int32)  # a non-finite position is bin 0
        flat = bins.ravel()
        self.nb = nb = int(flat.max()) + 1
        key = flat.astype(np.uint8 if nb <= 256 else np.int16) if nb <= 32767 else flat
        index = np.int32 if h * w < 2**31 else np.intp
        self.order = order = np.argsort(key, kind="stable").astype(index, copy=False)
        self.starts = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=nb))])
        self.amp = np.asarray(amplitude).ravel()[order]
        strong = np.where(candidate.ravel()[order], self.amp, 0).astype(np.float32)
        self.rows, self.cols = np.divmod(order, index(w))
        # pooling a zero changes nothing: only the nonzero candidates join the cells
        pos = np.flatnonzero(strong)
        self.strong = strong[pos]
        self.cand_rows, self.cand_cols = self.rows[pos], self.cols[pos]
        self.cand_starts = np.searchsorted(pos, self.starts)

    def mask(self, *, radius_px: int, min_frames: float, ratio: float) -> np.ndarray:
        """Flat (H·W,) bool halo mask for one reach (see :func:`halo_mask`)."""
        return self.unsort(self.mask_sorted(radius_px=radius_px, min_frames=min_frames,
                                            ratio=ratio))

    def unsort(self, flags_sorted: np.ndarray) -> np.ndarray:
        """Flat (H·W,) array of per-pixel flags given in bin order."""
        out = np.empty(flags_sorted.size, bool)
        out[self.order] = flags_sorted
        return out

    def mask_sorted(self, *, radius_px: int, min_frames: float, ratio: float) -> np.ndarray:
        """The halo mask in the pixels' bin order."""
        import cv2

        h, w = self.shape
        s = max(1, radius_px // 4)
        hs, ws = -(-h // s), -(-w // s)
        rs = max(1, radius_px // s)  # max-pooling into cells adds up to s - 1 px of reach
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rs + 1, 2 * rs + 1))
        nb, starts, cs = self.nb, self.starts, self.cand_starts
        gap = max(1, int(np.ceil(min_frames)))
        cells = self.rows // s
        cells *= ws
        cells += self.cols // s
        cand_cells = (self.cand_rows // s) * ws + self.cand_cols // s

        def spread(b: int) -> np.ndarray:
            """Bin b's candidate amplitudes, max-pooled to cells and dilated by the radius."""
            pooled = np.zeros(hs * ws, np.float32)
            np.maximum.at(pooled, cand_cells[cs[b]:cs[b + 1]], self.strong[cs[b]:cs[b + 1]])
            return cv2.dilate(pooled.reshape(hs, ws), disk).ravel()

        dom = np.zeros(h * w, np.float32)
        # one pass upwards (neighbours >= gap bins lower), one downwards; memory: gap arrays
        for bins_in_order in (range(nb), range(nb - 1, -1, -1)):
            running = None
            pending: list[np.ndarray | None] = []
            for b in bins_in_order:
                pending.append(spread(b) if cs[b + 1] > cs[b] else None)
                if len(pending) > gap:
                    done = pending.pop(0)
                    if done is not None:
                        running = done if running is None else np.maximum(running, done,
                                                                          out=running)
                if running is not None and starts[b + 1] > starts[b]:
                    m = dom[starts[b]:starts[b + 1]]
                    np.maximum(m, running[cells[starts[b]:starts[b + 1]]], out=m)
        return dom > ratio * self.amp


#: In-focus blur (σ, px) assumed for the sharpest edges of a stack: optics matched to
#: the sensor resolve about one pixel.
SIGMA0_PX = 1.0


def blur_px_per_frame(fit: PeakFit, reliable: np.ndarray, *, power: float) -> float:
    """Growth κ of the defocus blur σ (px) per frame step, from the sharpest peaks.

    A focus curve F ∝ (1 + Δ²/γ²)^(−p) has γ = σ0/κ frames for a blur
    σ_b = √(σ0² + κ²Δ²); the strongest 1 % of the reliable peaks (sharp edges, in focus
    at the resolution limit σ0 = ``SIGMA0_PX``) give γ from their fitted width σ_F =
    γ·√(e^(1/(2p)) − 1). Returns 0 when fewer than 100 peaks are reliable.

    Measured on rendered slanted planes (σ0 = 1 px): κ = 0.2 and 0.6 px/frame came out
    0.16–0.26 and 0.51–0.94; at 1.5 px/frame, where the peak is narrower than a frame
    and its width is not resolved, 3.6–5.9 (too high: the halo reach errs long).
    """
    step = None
    sig = fit.sigma_mm[reliable]
    amp = fit.f_peak[reliable]
    if sig.size < 100:
        return 0.0
    top = amp >= np.percentile(amp, 99)
    z = fit.coarse_mm  # frame z of each pixel: the step is the smallest nonzero spacing
    zs = np.unique(z[reliable])
    if zs.size > 1:
        step = float(np.min(np.diff(zs)))
    if not step:
        return 0.0
    width_frames = float(np.median(sig[top])) / step
    if not np.isfinite(width_frames) or width_frames <= 0:
        return 0.0
    gamma = width_frames / np.sqrt(np.expm1(0.5 / power))
    return SIGMA0_PX / gamma


def defocus_halo_mask(amplitude: np.ndarray, frame_pos: np.ndarray, candidate: np.ndarray, *,
                      base_radius_px: int, blur_px_per_frame: float, ratio: float,
                      n_frames: int, power: float = 2.0, cap_px: int | None = None) -> np.ndarray:
    """:func:`halo_mask` with a reach that grows with the depth gap.

    A sharp edge g frames from a pixel's peak is blurred there by σ_b ≈ κ·g px, and its
    blurred contrast reaches about 2σ_b: a neighbour at least g frames away explains a
    weak peak within ``max(base_radius_px, 2κg)`` px, if it is stronger by
    ``ratio·(g/2)^power`` (the blurred contrast, and so the halo it makes, weakens as
    the blur grows; ``power`` is the focus curve's p). Tested for gaps 2, 3, 5, 8, 13,
    … below ``n_frames`` (reach capped at ``cap_px``, by default a quarter of the image
    side).

    Measured: on pcb-oblique (κ ≈ 6 px/frame) the reliable heights standing above the
    barcode fell from 10 873 to 2 647 px; on a synthetic board (κ ≈ 0.7) 0.06 % of the
    reliable pixels were dropped, 2 % of them wrong (a constant ratio dropped 3.3 %).
    """
    h, w = amplitude.shape
    cap = max(base_radius_px, min(h, w) // 4 if cap_px is None else cap_px)
    out = np.zeros((h, w), bool)
    gaps, a, b = [], 2, 3
    while a < n_frames:
        gaps.append(a)
        a, b = b, a + b
    last_radius = -1
    groups = None
    for g in gaps:
        radius = int(min(cap, max(base_radius_px, round(2 * blur_px_per_frame * g))))
        if radius == last_radius and g != gaps[0]:
            continue  # same reach, a larger gap: implied by the smaller gap's test
        if groups is None:
            groups = _HaloGroups(amplitude, frame_pos, candidate)
            flagged = np.zeros(h * w, bool)
        flagged |= groups.mask_sorted(radius_px=radius, min_frames=g,
                                      ratio=ratio * (g / 2) ** power)
        last_radius = radius
    if groups is not None:
        out = groups.unsort(flagged).reshape(h, w)
    return out


def unsupported_mask(height_mm: np.ndarray, reliable: np.ndarray, *, distance_px: int,
                     tol_mm: float) -> np.ndarray:
    """(H, W) bool: reliable pixels that no independent neighbour corroborates.

    Two focus windows ``distance_px`` apart (the window side) share no pixel, so their
    noise is independent. A real surface is measured alike by the windows around a
    pixel, at least along its height contour; a peak that noise or a glint made is a
    blob one window wide that no window next to it repeats. A reliable pixel is kept
    when one of the 8 pixels ``distance_px`` away (rows, columns, diagonals) is reliable
    and within ``tol_mm`` of it; 16 directions, so that a thin band of real heights
    (a fillet's top along a pad edge) finds its continuation whatever its direction.
    """
    h, w = height_mm.shape
    d = int(distance_px)
    half = max(1, d // 2)
    supported = np.zeros((h, w), bool)
    hv = np.where(reliable, height_mm, np.nan).astype(np.float32)
    offsets = {(sy * a, sx * b) for a, b in ((d, 0), (0, d), (d, d), (d, half), (half, d))
               for sy in (-1, 1) for sx in (-1, 1)}
    diff = np.empty((h, w), np.float32)
    near = np.empty((h, w), bool)
    for dy, dx in sorted(offsets):
        if (dy, dx) < (0, 0):
            continue  # |a - b| = |b - a|: the opposite offset's test marks both ends
        # pixel (y, x) looks at (y + dy, x + dx), and (y + dy, x + dx) at (y, x)
        ys, yd = slice(max(0, -dy), h - max(0, dy)), slice(max(0, dy), h - max(0, -dy))
        xs, xd = slice(max(0, -dx), w - max(0, dx)), slice(max(0, dx), w - max(0, -dx))
        part = diff[: ys.stop - ys.start, : xs.stop - xs.start]
        ok = near[: ys.stop - ys.start, : xs.stop - xs.start]
        with np.errstate(invalid="ignore"):
            np.subtract(hv[ys, xs], hv[yd, xd], out=part)
            np.abs(part, out=part)
            np.less_equal(part, tol_mm, out=ok)
        supported[ys, xs] |= ok
        supported[yd, xd] |= ok
    return reliable & ~supported
