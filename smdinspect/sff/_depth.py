"""Per-pixel focus-peak tracking in one pass, and the Gaussian fit of the peak.

Memory does not grow with the number of frames: the tracker keeps the running best
focus value and frame of every pixel, the last 2k+1 focus frames (a ring of
references), the focus curve over ±k frames around each pixel's current best (copied
out of the ring once the k frames after the best have been seen), and the strongest
focus value seen *away* from the peak (more than k frames from it), which reveals a
second peak (e.g. a defocused component edge bleeding over the board).

The tracker also keeps each pixel's floor, its lowest focus over the stack (defocused
texture plus noise); :func:`fit_peaks` fits the peak to F − floor, by default as the
power-law peak A/(1 + (z − z̄)²/γ²)^p of a defocus-blurred natural texture, or as a
Gaussian (``lsq``, Nayar's ``gauss3``). Pertuz's reliability R = 20·log10(A / mean|F −
model|) is taken over the samples the fit used (dB).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ._config import FitMethod

__all__ = ["PeakFit", "PeakTracker", "centroid_correction", "fit_peaks", "local_plane"]

_TINY = np.float32(1e-12)
#: Samples beyond ±1 frame join the fit while above this fraction of the peak.
SUPPORT_FRACTION = 0.2
#: Pixels fitted at once per thread by :func:`fit_peaks` (bounds its memory). The fit
#: makes some 40 temporaries per block: at 2^15 pixels they stay in a core's L2 cache
#: (pcb-oblique's 3.1 Mpixel fit: 2^18 pixels 1.07 s, 2^15 0.60 s on 2 threads).
FIT_BLOCK_PX = 1 << 15
#: Narrowest focus curve (σ_F in frame steps) whose frame sum is its integral to 1 %
#: (2·exp(−2π²w²) = 0.01): below it :func:`centroid_correction` leaves a height alone.
CENTROID_MIN_WIDTH_STEPS = 0.52
#: Reliability (dB) reported for a peak fitted exactly through its 3 samples.
R_EXACT_DB = 60.0


class PeakTracker:
    """Streaming state of the per-pixel focus curves.

    Feed ``update(n, focus)`` once per frame in ascending frame order, then call
    :meth:`finish` once.

    Parameters
    ----------
    shape : (H, W)
    n_frames : int
    half_width : int
        k; the curve is kept over ±k frames around the peak.
    sum_focus : bool
        Also sum the focus over the frames (:attr:`texture_energy`, :meth:`centroid_px`).
    """

    def __init__(self, shape: tuple[int, int], n_frames: int, *, half_width: int,
                 sum_focus: bool = False) -> None:
        self.shape = shape
        self.n_frames = n_frames
        self.k = k = half_width
        self.best = np.full(shape, -1.0, np.float32)
        self.best_idx = np.zeros(shape, np.int16)
        # strongest focus more than k frames after the current best ...
        self.after = np.zeros(shape, np.float32)
        # ... and more than k frames before it (captured when the best settles)
        self.before = np.zeros(shape, np.float32)
        # max of F over frames <= n - 2k - 1 (the frames that have left the ring)
        self.lagmax = np.zeros(shape, np.float32)
        # lowest focus over all frames: the curve's floor (defocused texture + noise)
        self.floor = np.full(shape, np.inf, np.float32)
        # window[j] holds F at frame best_idx - k + j (NaN where outside the stack, and
        # for a pixel that never has a best frame)
        self.window = np.full((2 * k + 1, *shape), np.nan, np.float32)
        self.ring: list[np.ndarray | None] = [None] * (2 * k + 1)
        self._better = np.empty(shape, bool)
        self._far = np.empty(shape, bool)
        self._frame_no = np.empty(shape, np.int16)
        self._scratch = np.empty(shape, np.float32)
        self._finished = False
        #: Σ F over the frames (with ``sum_focus``)
        self.focus_sum = np.zeros(shape, np.float32) if sum_focus else None
        #: the small window's focus: (max, min over the frames, value at the best frame),
        #: when update() was given ``own``
        self.own: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def update(self, n: int, focus: np.ndarray, own=None) -> np.ndarray:
        """Take frame ``n``'s focus measure; return the (H, W) bool mask of new bests.

        ``own``, the same frame's focus over a smaller window, is tracked for
        :meth:`own_share`. The returned mask is reused by the next call: copy it to keep it.
        """
        k, size = self.k, 2 * self.k + 1
        better = np.greater(focus, self.best, out=self._better)
        mask = better.view(np.uint8)
        # cv2.copyTo with a mask is branch-free; numpy's where= is slow on noisy masks
        np.maximum(self.best, focus, out=self.best)
        np.minimum(self.floor, focus, out=self.floor)
        self._frame_no.fill(n)
        cv2.copyTo(self._frame_no, mask, self.best_idx)
        if self.focus_sum is not None:
            np.add(self.focus_sum, focus, out=self.focus_sum)
        if own is not None:
            if self.own is None:
                self.own = (np.full(self.shape, -np.inf, np.float32),
                            np.full(self.shape, np.inf, np.float32), np.zeros(self.shape, np.float32))
            np.maximum(self.own[0], own, out=self.own[0])
            np.minimum(self.own[1], own, out=self.own[1])
            cv2.copyTo(own, mask, self.own[2])
        far = np.less(self.best_idx, n - k, out=self._far)
        np.multiply(focus, far, out=self._scratch)
        np.maximum(self.after, self._scratch, out=self.after)
        # zero where masked (x ^ x): no constant plane of zeros to keep
        cv2.bitwise_xor(self.after, self.after, dst=self.after, mask=mask)
        leaving = self.ring[n % size]  # frame n - 2k - 1
        if leaving is not None:
            np.maximum(self.lagmax, leaving, out=self.lagmax)
        self.ring[n % size] = focus  # references, no copies
        # pixels whose best is exactly k frames old now have their full window in the ring
        self._settle(n - k, upto=n)
        return better

    def _settle(self, m: int, *, upto: int) -> None:
        """Copy the ±k window for pixels whose best frame is ``m`` (frames ≤ ``upto`` seen)."""
        if m < 0:
            return
        mask = np.equal(self.best_idx, m, out=self._far).view(np.uint8)
        k, size = self.k, 2 * self.k + 1
        before = self.lagmax
        # frames between the ring's oldest and m - k - 1 (only at the end of the stack)
        for frame in range(max(0, upto - 2 * k), m - k):
            before = np.maximum(before, self.ring[frame % size])
        cv2.copyTo(before, mask, self.before)
        for j in range(size):
            frame = m - k + j
            if 0 <= frame <= upto:
                cv2.copyTo(self.ring[frame % size], mask, self.window[j])
            else:  # outside the stack: NaN (x + NaN), no constant plane of NaNs to keep
                cv2.add(self.window[j], np.nan, dst=self.window[j], mask=mask)

    def finish(self) -> None:
        """Settle the pixels whose best lies in the last k frames.

        Then the ring of focus frames and the scratch planes are let go (the tracker
        takes no more frames): :func:`fit_peaks` needs only the settled state.
        """
        if self._finished:
            return
        last = self.n_frames - 1
        for m in range(max(0, last - self.k + 1), last + 1):
            self._settle(m, upto=last)
        self._finished = True
        self.ring = [None] * len(self.ring)
        self.lagmax = self._better = self._far = self._frame_no = self._scratch = None

    def release_curves(self) -> None:
        """Let go of the per-pixel curves (window, best, before/after) once
        :func:`fit_peaks` has run; :attr:`focus_sum` and :attr:`shape` stay."""
        self.finish()
        self.window = self.best = self.before = self.after = None

    def own_share(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(share, ratio) float32 of the small window (``update(own=...)``), or None.

        share: the small window's focus at the main curve's best frame above its floor,
        over its own peak above the floor (1 where both windows peak together);
        ratio: its peak above the floor over the floor (its noise test's A/b).
        """
        if self.own is None:
            return None
        top, low, at = self.own
        span = top - low
        with np.errstate(divide="ignore", invalid="ignore"):
            share = np.where(span > 0, (at - low) / span, 1.0).astype(np.float32)
            ratio = np.where(low > 0, span / low, 0.0).astype(np.float32)
        return share, ratio

    @property
    def texture_energy(self) -> np.ndarray | None:
        """(H, W) float32: each window's focus summed over the frames above its floor
        (the texture the window holds, whatever its defocus), or None without
        ``sum_focus``."""
        if self.focus_sum is None:
            return None
        return np.maximum(self.focus_sum - np.float32(self.n_frames) * self.floor, 0)

    def centroid_px(self, mx: np.ndarray, my: np.ndarray, *,
                    window_px: int) -> tuple[np.ndarray, np.ndarray]:
        """(dx, dy) float32: offset (px) of the centroid of each window's focus energy from
        its centre, from Σ Mx and Σ My over the frames
        (:func:`~smdinspect.sff.focus_measure_moments`; needs ``sum_focus``).

        The energy is summed over all frames above the curve's floor, so it weighs each
        pixel of the window by its texture, not by how defocused it is in one frame (at
        a coarse step the best frame favours the pixels nearest that frame's height).
        The noise's centroid is the window's centre; offsets are clipped to the window.
        """
        den = self.focus_sum - np.float32(self.n_frames) * self.floor
        np.maximum(den, np.float32(1e-30), out=den)
        half = np.float32(window_px // 2)
        return (np.clip(mx / den, -half, half), np.clip(my / den, -half, half))

    @property
    def alternative(self) -> np.ndarray:
        """(H, W) float32: strongest focus more than k frames away from the peak."""
        return np.maximum(self.before, self.after)


@dataclass(frozen=True, eq=False)
class PeakFit:
    """Per-pixel result of the peak fit; all arrays ``(H, W)``."""

    height_mm: np.ndarray  # float32, interpolated peak position
    coarse_mm: np.ndarray  # float32, z of the frame of maximum focus
    f_peak: np.ndarray  # float32, fitted peak height above the floor (the amplitude A)
    floor: np.ndarray  # float32, lowest focus of the curve (defocused texture + noise)
    f_best: np.ndarray  # float32, highest sampled focus above the floor
    sigma_mm: np.ndarray  # float32, fitted width σ_F; NaN where the fit is inverted
    reliability_db: np.ndarray  # float32, Pertuz's R of the fit over ±k frames
    ambiguity: np.ndarray  # float32 in [0, 1]: excess focus away from the peak / A
    second_mode: np.ndarray  # float32 in [0, 1]: largest rise after a dip within ±k / A
    interior: np.ndarray  # bool: peak not on the first/last frame and fit not inverted
    best_idx: np.ndarray  # int16
    #: float32 (steps): even-frame peak − odd-frame peak (_split_difference); NaN where
    #: a half has too few samples on the peak (narrow curves: coarse steps)
    split_steps: np.ndarray | None = None


#: Candidate shape exponents of the ``power`` model, as multiples of the operator's own p.
POWER_CANDIDATES = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
#: Pixels (the clearest peaks) :func:`select_curve_power` judges the candidates on.
POWER_SAMPLE_PX = 40000


def select_curve_power(tracker: PeakTracker, z_mm: np.ndarray, *, power: float,
                       grid_rows: tuple[int, int] | None = None) -> tuple[float, dict]:
    """The ``power`` model's exponent p under which the surface has no terraces.

    The shape of a focus curve is the sweep's, not the pixel's: it follows from the
    texture's spectrum and the lens's blur (a broadband 1/ω² texture gives the power law
    of :attr:`FocusOperator.curve_power`, a narrow-band one a Gaussian: p → ∞). At a
    coarse step the fit uses the peak and its two neighbours, which any p fits exactly,
    so no single curve tells the shape; a wrong one biases every sub-frame position by
    a function of its fractional part, and a smooth surface then rises in terraces: its
    slope varies with the fractional frame position. Each candidate p·
    :data:`POWER_CANDIDATES` is fitted over a central crop (at most
    :data:`POWER_SAMPLE_PX` pixels) and scored by how much the median slope magnitude of
    the clear, smooth pixels varies over 8 bins of the fractional position (relative
    spread of the bins' medians); the lowest score wins. Returns ``(p, {p: score})``;
    the operator's own p when the crop has too few sloped pixels to judge. With
    ``grid_rows = (first, height)``, the tracker holds the rows ``first ..`` of a grid
    ``height`` rows high (a band, :func:`~smdinspect.sff.reconstruct`): the crop is the
    whole grid's central one.
    """
    k = tracker.k
    if tracker.window is None or len(z_mm) < 4:
        return power, {}
    h, w = tracker.shape
    side = int(np.sqrt(POWER_SAMPLE_PX))
    first, rows = (0, h) if grid_rows is None else grid_rows
    r0, c0 = max(0, max(0, (rows - side) // 2) - first), max(0, (w - side) // 2)
    rs, cs = slice(r0, r0 + side), slice(c0, c0 + side)
    args = (tracker.best_idx[rs, cs], tracker.window[:, rs, cs], tracker.alternative[rs, cs],
            tracker.best[rs, cs], tracker.floor[rs, cs])
    with np.errstate(invalid="ignore", divide="ignore"):
        clear = args[3] > 3.0 * np.where(np.isfinite(args[4]), args[4], np.inf)
    scores = {}
    for m in POWER_CANDIDATES:
        pw = power * m
        height, interior = _fit_block(*args, z_mm, k=k, method=FitMethod.POWER, power=pw,
                                      heights_only=True)
        pos = np.interp(height, z_mm, np.arange(len(z_mm), dtype=np.float64)).astype(np.float32)
        good = (interior & clear).astype(np.uint8)
        good = cv2.erode(good, np.ones((3, 3), np.uint8)).view(bool)
        gx = cv2.Sobel(pos, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(pos, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        g = np.hypot(gx, gy)
        # sloped but smooth: at least 1/50 frame per pixel, at most half a frame
        sel = good & (g > 0.02) & (g < 0.5)
        if sel.sum() < 2000:
            return power, {}
        frac = pos[sel] % 1.0
        bins = np.minimum((frac * 8).astype(int), 7)
        med = [np.median(g[sel][bins == b]) for b in range(8) if np.sum(bins == b) >= 50]
        if len(med) < 6:
            return power, {}
        scores[pw] = float(np.std(med) / np.mean(med))
    ps = sorted(scores)
    i = ps.index(min(scores, key=scores.get))
    if 0 < i < len(ps) - 1:  # the parabola through the best and its neighbours, in ln p
        x = np.log(ps[i - 1:i + 2])
        y = np.array([scores[q] for q in ps[i - 1:i + 2]])
        c2, c1, _ = np.polyfit(x, y, 2)
        if c2 > 0:
            return float(np.exp(np.clip(-c1 / (2 * c2), x[0], x[2]))), scores
    return ps[i], scores


def fit_peaks(tracker: PeakTracker, z_mm: np.ndarray, *, method: FitMethod,
              power: float = 2.0, workers: int = 1, heights_only: bool = False):
    """Fit the focus-curve peak of every pixel above the curve's floor.

    The floor b is the focus measure of fully defocused texture plus noise, tracked as
    the lowest focus over all frames; every model is fitted to F − b. Without b the
    tails of a narrow peak sink into the floor, the fit pulls every peak towards its
    frame and heights terrace at whole frames whenever the step is coarse against the
    depth of field.

    Parameters
    ----------
    tracker : PeakTracker
        After :meth:`PeakTracker.finish`.
    z_mm : (n_frames,) float64
        Ascending focused-plane heights of the frames.
    method : FitMethod
        ``power``: F − b = A/(1 + (u − μ)²/γ²)^p, i.e. (F − b)^(−1/p) a parabola in u,
        by least squares weighted by (F − b)^(2+2/p) over the peak's support.
        ``lsq``: ln(F − b) a parabola, weighted by (F − b)² (Guo's weighting), over the
        same support. ``gauss3``: ln(F − b) through the peak and its two neighbours
        (Nayar's 3-point Gaussian interpolation). ``argmax``: the peak frame only.
    power : float
        p of the ``power`` model (:attr:`FocusOperator.curve_power`).
    workers : int
        Threads fitting blocks of rows of about ``FIT_BLOCK_PX`` pixels (numpy releases
        the GIL; the blocks bound the memory of the temporaries).
    heights_only : bool
        Return only ``(height_mm, interior)`` (two planes, no confidence cues): the
        heights of a second curve shape cost a fraction of a full fit's time and memory.
    """
    h, w = tracker.shape
    alternative = tracker.alternative
    args = (tracker.best_idx, tracker.window, alternative, tracker.best, tracker.floor)
    rows = max(1, FIT_BLOCK_PX // max(w, 1))
    opts = dict(k=tracker.k, method=method, power=power, heights_only=heights_only)
    if h <= rows:
        return _fit_block(*args, z_mm, **opts)
    from concurrent.futures import ThreadPoolExecutor

    # blocks of rows bound the fit's temporaries (some 40 arrays of the block's size)
    edges = np.append(np.arange(0, h, rows), h)
    # Each thread writes its rows straight into the full-size results (no concatenation).
    dtypes = {"interior": bool, "best_idx": np.int16}
    fields = ("height_mm", "interior") if heights_only else PeakFit.__dataclass_fields__
    out = {f: np.empty(tracker.shape, dtypes.get(f, np.float32)) for f in fields}

    def run(r0: int, r1: int) -> None:
        part = _fit_block(*(a[:, r0:r1] if a.ndim == 3 else a[r0:r1] for a in args), z_mm,
                          **opts)
        for i, (f, a) in enumerate(out.items()):
            a[r0:r1] = part[i] if heights_only else getattr(part, f)

    with ThreadPoolExecutor(max(1, workers)) as pool:
        list(pool.map(run, edges[:-1], edges[1:]))
    return (out["height_mm"], out["interior"]) if heights_only else PeakFit(**out)


def _fit_block(best_idx, window, alternative, best, floor, z_mm, *, k: int,
               method: FitMethod, power: float, heights_only: bool = False):
    """:func:`fit_peaks` on one block of rows."""
    z_mm = np.asarray(z_mm, dtype=np.float64)
    n = len(z_mm)
    step = float(np.median(np.diff(z_mm))) if n > 1 else 1.0
    kb = best_idx
    # sample positions relative to the peak frame, in units of the median step
    z_pad = np.concatenate([np.full(k, np.nan), z_mm, np.full(k, np.nan)]) / step
    z0 = z_mm[kb]
    frames = np.arange(n)

    u_cache: dict[int, np.ndarray] = {}

    def u_at(j: int) -> np.ndarray:
        if j not in u_cache:
            # a function of the peak frame alone: made once a frame, then looked up
            u_cache[j] = np.take((z_pad[frames + j] - z_mm / step).astype(np.float32), kb)
        return u_cache[j]

    floor = np.where(np.isfinite(floor), floor, 0).astype(np.float32)
    y = [np.maximum(window[j] - floor, 0) for j in range(2 * k + 1)]  # NaN stays NaN
    y0 = y[k]
    on_edge = (kb == 0) | (kb == n - 1) | ~np.isfinite(y[k - 1]) | ~np.isfinite(y[k + 1])
    gauss = method in (FitMethod.GAUSS3, FitMethod.LSQ)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        tiny = np.maximum(y0 * 1e-4, _TINY)
        if gauss:  # q = −ln y is a parabola for a Gaussian peak
            to_q = lambda v: -np.log(np.maximum(v, tiny))  # noqa: E731
        else:  # q = y^(−1/p) is a parabola for A / (1 + (u − μ)²/γ²)^p
            to_q = lambda v: _pow(np.maximum(v, tiny), -1.0 / power)  # noqa: E731
        # The peak's support: the samples, contiguous with the peak, above
        # SUPPORT_FRACTION of it (always ±1 frame). A real focus curve is a narrow peak
        # on a broad pedestal (coarse texture defocuses slowly): samples on the pedestal
        # would pull the fit, and at coarse steps only ±1 frame is on the peak.
        support = [None] * (2 * k + 1)
        support[k] = np.isfinite(y0)
        for j in list(range(k - 1, -1, -1)) + list(range(k + 1, 2 * k + 1)):
            inner = support[j + 1] if j < k else support[j - 1]
            support[j] = inner & ((y[j] > SUPPORT_FRACTION * y0) | (abs(j - k) == 1))
        u = [u_at(j) for j in range(2 * k + 1)]
        q = None  # the linearised samples, for the weighted fit and the even/odd split
        if method == FitMethod.GAUSS3:
            for j in range(2 * k + 1):
                if abs(j - k) > 1:
                    support[j] = np.zeros_like(support[k])
            um, up = u_at(k - 1), u_at(k + 1)
            qm, q0, qp = to_q(y[k - 1]), to_q(y0), to_q(y[k + 1])
            c = ((qp - q0) / up - (q0 - qm) / (-um)) / (up - um)
            b = (q0 - qm) / (-um) - c * um
            a = q0
        else:
            # weights ∝ 1 / var(q) for a constant noise on y: y² (Gaussian), y^(2+2/p)
            expo = 2.0 if gauss else 2.0 + 2.0 / power
            q = [to_q(v) for v in y]
            c, b, a = _weighted_parabola(u, q,
                                         [np.where(m, _pow(v, expo), 0) for m, v in zip(support, y)])
        shift = -b / (2 * c)  # steps
        q_min = a - b * b / (4 * c)
        if gauss:
            inverted = ~(c > 0)
            log_amp = -q_min
            half2 = 0.5 / c  # σ² at e^(−½), steps²
        else:
            inverted = ~((c > 0) & (q_min > 0))
            log_amp = -power * np.log(q_min)
            half2 = (np.expm1(0.5 / power) * q_min / c)
        # A fitted peak more than one frame from the sampled maximum is not trusted.
        wild = ~(np.abs(shift) <= 1.0)
        bad = on_edge | inverted | wild
        offset = np.zeros_like(y0) if method == FitMethod.ARGMAX else np.where(bad, 0.0, shift)
        offset = offset.astype(np.float32)
        height = (z0 + offset * step).astype(np.float32)
        if heights_only:
            return height, ~bad
        split = np.full(y0.shape, np.nan, np.float32)
        if method in (FitMethod.POWER, FitMethod.LSQ):
            split = _split_difference(u, q, y, support, k=k)
            split[bad] = np.nan
        sigma = np.where(inverted | on_edge, np.nan, np.sqrt(half2) * abs(step)).astype(np.float32)
        amp = np.where(bad, y0, np.exp(np.minimum(log_amp, 80.0))).astype(np.float32)
        # curvature of q relative to its minimum: model d² = (u − μ)²·cq
        cq = np.where(bad, 1.0, c if gauss else c / q_min).astype(np.float32)

        def model(u: np.ndarray) -> np.ndarray:
            """Fitted curve above the floor at offset u (steps) from the peak frame."""
            d2 = (u - offset) ** 2 * cq
            return amp * (np.exp(-d2) if gauss else _pow(1.0 + d2, -power))

        # Pertuz's reliability R over the peak's support (the samples the fit used); a
        # support of 3 samples is fitted exactly and says nothing: R = R_EXACT_DB.
        def reliability(model, amp, ys, us, sups):
            res_sum = np.zeros_like(amp)
            res_n = np.zeros_like(amp)
            for yj, uj, sj in zip(ys, us, sups):
                r = np.abs(yj - model(uj))
                ok = np.isfinite(r) & sj
                res_sum += np.where(ok, r, 0)
                res_n += ok
            mean_res = res_sum / np.maximum(res_n, 1)
            rel = 20.0 * np.log10(amp / np.maximum(mean_res, 1e-6 * np.maximum(amp, _TINY)))
            return np.where(res_n <= 3, R_EXACT_DB, np.minimum(rel, R_EXACT_DB)), res_n

        rel, res_n = reliability(model, amp, y, u, support)
        wide = (res_n > 3) & ~bad
        if q is not None and not gauss and wide.any():
            # R judges the noise on the curve, not the operator's nominal shape: a
            # narrow-band texture or a disc-like PSF gives a clean peak closer to a
            # Gaussian, whose misfit to the power law is no error of the height. Where
            # R is judged (more than 3 samples of support) it is the better of the two
            # shapes' over the same support; a mixed or noisy curve fits neither.
            ys, us, sups = ([a[wide] for a in arrs] for arrs in (y, u, support))
            cg, bg, ag = _weighted_parabola(
                us, [-np.log(np.maximum(v, tiny[wide])) for v in ys],
                [np.where(m, v * v, 0) for m, v in zip(sups, ys)])
            sg = -bg / (2 * cg)
            amp_g = np.exp(np.minimum(bg * bg / (4 * cg) - ag, 80.0))
            good_g = (cg > 0) & (np.abs(sg) <= 1.0)
            cg, sg = np.where(good_g, cg, 1.0), np.where(good_g, sg, 0.0)
            rel_g, _ = reliability(lambda v: amp_g * np.exp(-((v - sg) ** 2) * cg), amp_g,
                                   ys, us, sups)
            rel[wide] = np.where(good_g, np.fmax(rel[wide], rel_g), rel[wide])
        rel = np.where(bad, 0.0, rel).astype(np.float32)
        # The strongest focus more than k frames from the peak, above the floor, less what
        # the fitted peak itself predicts k+½ frames out (the tail of a wide peak).
        tail = np.where(inverted | on_edge, 0.0, model(np.float32(k + 0.5) + offset) / amp)
        ambiguity = np.clip((alternative - floor) / np.maximum(amp, _TINY) - tail,
                            0, 1).astype(np.float32)
        # A second mode within ±k: the largest rise after a dip on either side of the
        # peak, over A (one surface point has a unimodal curve; in a short stack ±k may
        # be the whole curve, and beyond it there is nothing for ``ambiguity``).
        second = np.zeros_like(y0)
        for side in (range(k - 1, -1, -1), range(k + 1, 2 * k + 1)):
            low = y0.copy()
            for j in side:
                second = np.fmax(second, y[j] - low)
                low = np.fmin(low, y[j])
        second = np.clip(second / np.maximum(amp, _TINY), 0, 1).astype(np.float32)
    return PeakFit(
        height_mm=height,
        coarse_mm=z0.astype(np.float32),
        f_peak=amp,
        floor=floor,
        f_best=np.where(np.isfinite(y0), y0, 0).astype(np.float32),
        sigma_mm=sigma,
        reliability_db=rel,
        ambiguity=ambiguity,
        second_mode=second,
        interior=~bad,
        best_idx=best_idx,
        split_steps=split,
    )


def _pow(x: np.ndarray, e: float) -> np.ndarray:
    """``x ** e`` (float32), by products, a square root or a reciprocal for the exponents
    the default curve shape (p = 2) gives: a float32 power costs ~8x as much."""
    if e == 3.0:
        return x * x * x
    if e == 2.0:
        return np.square(x)
    if e == -0.5:
        return np.float32(1.0) / np.sqrt(x)
    if e == -2.0:
        return np.float32(1.0) / np.square(x)
    return x ** np.float32(e)


def _split_difference(u, q, y, support, *, k: int) -> np.ndarray:
    """Peak position from even samples less that from odd ones, in frame steps; NaN
    where a half lacks 3 supported samples around the peak.

    The even half is the peak frame and the frames ±2 from it; the odd half is the
    frames ±1 and the one 3 frames out on the side of the larger neighbour (both halves
    then hold the samples nearest the true peak). Each is fitted exactly by a parabola
    in the model's linearised q (as the full fit). The halves come from different
    frames, whose noise is independent: their difference is a draw of the fit's random
    error, whatever the noise is made of (read, shot, JPEG, flicker), while what both
    share (a window mixing two depths, a halo) cancels out. Its spread over a window is
    the measured height's precision (:func:`smdinspect.sff._confidence.precision_steps`).
    """
    if k < 3:
        return np.full(q[k].shape, np.nan, np.float32)
    right = np.nan_to_num(y[k + 1], nan=-1.0) >= np.nan_to_num(y[k - 1], nan=-1.0)

    def pick(j_right: int, j_left: int):
        return tuple(np.where(right, a[j_right], a[j_left]) for a in (u, q, support))

    even = tuple((u[j], q[j], support[j]) for j in (k - 2, k, k + 2))
    odd = (pick(k - 1, k - 3), pick(k + 1, k - 1), pick(k + 3, k + 1))
    shifts = []
    for (u1, q1, s1), (u2, q2, s2), (u3, q3, s3) in (even, odd):
        d12, d13, d23 = u1 - u2, u1 - u3, u2 - u3
        den = d12 * d13 * d23
        a = (u3 * (q2 - q1) + u2 * (q1 - q3) + u1 * (q3 - q2)) / den
        b = (u3 * u3 * (q1 - q2) + u2 * u2 * (q3 - q1) + u1 * u1 * (q2 - q3)) / den
        shift = -b / (2 * a)
        # a half samples the peak at twice the step: its vertex stays within ±2 frames
        ok = s1 & s2 & s3 & (a > 0) & (np.abs(shift) <= 2.0)
        shifts.append(np.where(ok, shift, np.nan))
    return (shifts[0] - shifts[1]).astype(np.float32)


def _weighted_parabola(u: list[np.ndarray], q: list[np.ndarray], wt: list[np.ndarray]):
    """Per-pixel weighted least squares q = a + b·u + c·u².

    ``u``, ``q``, ``wt`` are lists of (H, W) float32 samples (NaN where missing; weights
    below 1e-8 of the largest count as missing). The weights are scaled by each pixel's
    largest, q by its value at the largest weight, and u is in frame steps (|u| <= k),
    so the moments stay O(1) and float32 suffices; the 3 × 3 normal equations are
    solved by Cramer's rule in float64. Returns ``(c, b, a)`` as float32; NaN where
    fewer than 3 samples carry weight.
    """
    shape = u[0].shape
    f32 = np.float32
    s = [np.zeros(shape, f32) for _ in range(5)]
    t = [np.zeros(shape, f32) for _ in range(3)]
    count = np.zeros(shape, np.int16)
    top = np.fmax.reduce(wt)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_top = np.where(top > 0, 1.0 / top, 0).astype(f32)
        # q at the sample of largest weight (the peak): q / q_ref is O(1)
        q_ref = np.zeros(shape, f32)
        for qj, wj in zip(q, wt):
            np.copyto(q_ref, qj, where=(wj == top) & np.isfinite(qj))
        q_ref = np.where((q_ref != 0) & np.isfinite(q_ref), q_ref, 1).astype(f32)
    for uj, qj, wj in zip(u, q, wt):
        p = wj * inv_top
        ok = np.isfinite(uj) & np.isfinite(qj) & (p > 1e-8)
        p = np.where(ok, p, f32(0))
        uu = np.where(ok, uj, f32(0))
        qq = np.where(ok, qj / q_ref, f32(0))
        count += ok
        t[0] += p * qq
        for m in range(5):
            s[m] += p
            if m == 4:
                break
            p *= uu
            if m < 2:
                t[m + 1] += p * qq
    s0, s1, s2, s3, s4 = (a.astype(np.float64) for a in s)
    t0, t1, t2 = (a.astype(np.float64) for a in t)
    # Cramer's rule on [[s0 s1 s2][s1 s2 s3][s2 s3 s4]]·[a b c] = [t0 t1 t2]
    m00 = s2 * s4 - s3 * s3
    m01 = s1 * s4 - s2 * s3
    m02 = s1 * s3 - s2 * s2
    det = s0 * m00 - s1 * m01 + s2 * m02
    s0c = np.maximum(s0, 1e-300)
    ok = (count >= 3) & (np.abs(det) > 1e-9 * (s0c * s0c * s0c))  # a product, not a pow
    det = np.where(ok, det, 1.0)
    scale = q_ref.astype(np.float64) / det
    a = (t0 * m00 - s1 * (t1 * s4 - s3 * t2) + s2 * (t1 * s3 - s2 * t2)) * scale
    b = (s0 * (t1 * s4 - s3 * t2) - t0 * m01 + s2 * (s1 * t2 - t1 * s2)) * scale
    c = (s0 * (s2 * t2 - t1 * s3) - s1 * (s1 * t2 - t1 * s2) + t0 * m02) * scale
    c = np.where(ok, c, np.nan)
    return c.astype(np.float32), b.astype(np.float32), a.astype(np.float32)


def masked_gradient(height: np.ndarray, ok: np.ndarray, *, sigma_px: float,
                    min_weight: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gradient (per px) of the ``ok`` heights: normalised Gaussian convolution of σ
    ``sigma_px``, then central differences. Returns ``(gx, gy, dense)`` float32 and bool,
    ``dense`` where every pixel of the 3 × 3 stencil has at least ``min_weight`` of its
    smoothing weight on ``ok`` pixels (elsewhere the gradient means nothing)."""
    w = ok.astype(np.float32)
    h = np.where(ok, height, 0).astype(np.float32)
    den = cv2.GaussianBlur(w, (0, 0), sigma_px)
    smooth = cv2.GaussianBlur(h, (0, 0), sigma_px) / np.maximum(den, np.float32(1e-6))
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    dense = cv2.erode((den >= min_weight).astype(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    return gx, gy, dense


def level_gradient(height: np.ndarray, ok: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                   dense: np.ndarray, *, sigma_px: float, gap_mm: np.ndarray,
                   chunk: int = 4096) -> None:
    """Gradients of :func:`masked_gradient` redone, in place, from the pixel's own level,
    at the pixels of ``dense`` (cleared there where no plane can be fitted).

    A window's focus curve sums its pixels' curves. Heights that run on without a gap
    (a slope, however steep) sum to one peak; two groups of heights farther apart than
    twice the curve's width do not (two equal Gaussians farther apart than 2σ make two
    peaks), and the far group does not pull the tracked peak. Next to a step (a body
    on the board) the smoothing of :func:`masked_gradient` reaches the other level
    all the same, and the smoothed step's tail reads as a slope on flat ground.

    So where the footprint (3σ + 1 px) holds ``ok`` heights farther than ``gap_mm``
    from the pixel's own, its level is grown in height from the pixel's own: every
    footprint height within ``gap_mm`` of the level joins it, until none does. The
    gradient is then the weighted least-squares plane (Gaussian weights of σ) through
    the level's heights; where they cannot hold a plane (under a quarter of the
    Gaussian's weight, or nearly on a line) the pixel is cleared from ``dense``.
    """
    r = int(np.ceil(3.0 * sigma_px)) + 1
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    h = np.asarray(height, np.float32)
    hi = cv2.dilate(np.where(ok, h, -np.inf).astype(np.float32), k)
    lo = cv2.erode(np.where(ok, h, np.inf).astype(np.float32), k)
    gap = np.broadcast_to(np.asarray(gap_mm, np.float32), h.shape)
    ys, xs = np.nonzero(dense & ((hi - h > gap) | (h - lo > gap)))
    oy, ox = (a.ravel() for a in np.mgrid[-r:r + 1, -r:r + 1])
    g = np.exp(-(ox * ox + oy * oy) / (2.0 * sigma_px ** 2)).astype(np.float32)
    hp = np.pad(np.where(ok, h, np.nan), r, constant_values=np.nan)
    moments = np.stack([np.ones_like(g), ox, oy, ox * ox, ox * oy, oy * oy]).T * g[:, None]
    for i in range(0, ys.size, chunk):
        y, x = ys[i:i + chunk], xs[i:i + chunk]
        q = hp[(y + r)[:, None] + oy, (x + r)[:, None] + ox] - h[y, x][:, None]  # (n, K)
        t = gap[y, x]
        low, high = -t, t
        for _ in range(4 * r):  # a level can grow across the footprint at most this often
            inside = (q >= low[:, None]) & (q <= high[:, None])
            new_low = np.min(np.where(inside, q, 0.0), axis=1) - t
            new_high = np.max(np.where(inside, q, 0.0), axis=1) + t
            if np.array_equal(new_low, low) and np.array_equal(new_high, high):
                break
            low, high = new_low, new_high
        w = inside.astype(np.float32)
        n, sx, sy, sxx, sxy, syy = (w @ moments).T
        wq = w * np.nan_to_num(q) * g
        sh, sxh, syh = wq.sum(axis=1), wq @ ox, wq @ oy
        nn = np.maximum(n, 1e-12)
        cxx, cxy, cyy = sxx - sx * sx / nn, sxy - sx * sy / nn, syy - sy * sy / nn
        bx, by = sxh - sx * sh / nn, syh - sy * sh / nn
        det = cxx * cyy - cxy * cxy
        fine = (n >= 0.25 * g.sum()) & (det > (0.25 * sigma_px ** 2 * nn) ** 2)
        det = np.where(fine, det, 1.0)
        gx[y, x] = np.where(fine, (cyy * bx - cxy * by) / det, 0.0)
        gy[y, x] = np.where(fine, (cxx * by - cxy * bx) / det, 0.0)
        dense[y, x] &= fine


def centroid_correction(height_mm: np.ndarray, ok: np.ndarray, offset_px, *, window_px: int,
                        max_mm: float, width_steps: np.ndarray | None = None) -> np.ndarray:
    """Heights moved from under the window's focus-energy centroid to under its centre.

    A window's focus curve is the sum of its pixels' curves, each weighted by its texture
    energy; on a locally planar surface h(q) = h(p) + ∇h·(q − p) its peak lies at the
    energy-weighted mean height, h(p) + ∇h·c with c the energy centroid's offset from
    the window centre (:meth:`PeakTracker.centroid_px`). So h(p) = ĥ − ∇h·c, with ∇h
    estimated from the ``ok`` heights themselves (normalised Gaussian convolution at a
    quarter window, then central differences). Only ``ok`` pixels with enough ``ok``
    neighbours move, by at most ``max_mm`` (a step edge is not a plane).

    The centroid weighs each pixel by its focus summed over the frames; that sum is the
    curve's integral, independent of where the pixel's height falls between frames, only
    if the curve is sampled finely enough: for a Gaussian of width w steps the sum
    varies by 2·exp(−2π²w²) with the fractional position (Poisson summation). Pixels
    whose fitted width ``width_steps`` is below :data:`CENTROID_MIN_WIDTH_STEPS` (1 %)
    are left as they are: at such coarse steps the weights favour the pixels nearest a
    frame and the correction would pull heights away from the frames.
    Returns a new float32 array.
    """
    dx, dy = offset_px
    sigma = max(window_px / 4.0, 1.0)
    gx, gy, dense = masked_gradient(height_mm, ok, sigma_px=sigma, min_weight=0.5)
    move = ok & dense
    if width_steps is not None:
        width = np.nan_to_num(width_steps, nan=0.0)
        move &= width >= CENTROID_MIN_WIDTH_STEPS
        level_gradient(height_mm, ok, gx, gy, move, sigma_px=sigma,
                       gap_mm=2.0 * width * max_mm)  # twice the curve's width, in mm
    corr = gx * dx + gy * dy
    np.clip(corr, -max_mm, max_mm, out=corr)
    corr[~move] = 0.0
    return height_mm.astype(np.float32) - corr


#: Share of a :func:`local_plane` square that must hold reliable heights for a plane.
PLANE_MIN_SHARE = 0.6


def local_plane(height_mm: np.ndarray, ok: np.ndarray, *, side_px: int,
                rows_per_chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Each ``ok`` height replaced by the least-squares plane through the ``ok`` heights
    of the ``side_px`` square around it, evaluated at its centre; ``(heights, used)``.

    A height comes from the peak of a window's focus curve: a nonlinear reading, each
    with its own random error (noise moves the peak). Averaging heights, after the
    peak, lowers that error without the bias a larger focus window has on a slope (a
    wider window mixes depths before the peak, and its peak favours the strongest
    texture's): a plane through heights on a plane is the plane, whatever its slope.
    What a plane cannot follow is curvature, a bias of about h''·(side² − 1)/12 per
    axis (a 5-px square: h''·2 px², 0.03 Δd on a solder fillet at 20 µm/px). Only
    pixels whose square is at least :data:`PLANE_MIN_SHARE` reliable move (a height
    beside a gap keeps its reading). Computed in row chunks (bounded memory), float32
    about the median height (no cancellation on a sweep far from z = 0).
    """
    h = np.asarray(height_mm, np.float32)
    out = h.copy()
    used = np.zeros(h.shape, bool)
    if side_px < 3 or not ok.any():
        return out, used
    r = side_px // 2
    ref = np.float32(np.median(h[ok]))
    d = np.arange(-r, r + 1, dtype=np.float32)
    one = np.ones_like(d)
    need = PLANE_MIN_SHARE * side_px * side_px

    def corr(src, kx, ky):  # Σ over the square of src(p + o)·kx(ox)·ky(oy)
        return cv2.sepFilter2D(src, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_CONSTANT)

    for top in range(0, h.shape[0], rows_per_chunk):
        lo, hi = max(top - r, 0), min(top + rows_per_chunk + r, h.shape[0])
        w = ok[lo:hi].astype(np.float32)
        wh = np.where(ok[lo:hi], h[lo:hi] - ref, 0).astype(np.float32)
        s0, sx, sy = corr(w, one, one), corr(w, d, one), corr(w, one, d)
        sxx, syy, sxy = corr(w, d * d, one), corr(w, one, d * d), corr(w, d, d)
        t0, tx, ty = corr(wh, one, one), corr(wh, d, one), corr(wh, one, d)
        # the intercept of the normal equations, by cofactors of the 3 × 3 moment matrix
        c0 = sxx * syy - sxy * sxy
        c1 = sxy * sy - sx * syy
        c2 = sx * sxy - sxx * sy
        det = s0 * c0 + sx * c1 + sy * c2
        a = t0 * c0 + tx * c1 + ty * c2
        k0, k1 = top - lo, min(top + rows_per_chunk, h.shape[0]) - lo
        core = slice(k0, k1)
        fine = ok[lo:hi][core] & (s0[core] >= need) & (det[core] > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            plane = a[core] / det[core] + ref
        rows = slice(top, top + (k1 - k0))
        np.copyto(out[rows], plane, where=fine)
        used[rows] = fine
    return out, used
