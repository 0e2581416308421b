"""Per-pixel focus-peak tracking in one pass, and the Gaussian fit of the peak.

Memory does not grow with the number of frames: the tracker keeps the running best
focus value and frame of every pixel, the last 2k+1 focus frames (a ring of
references), the focus curve over ±k frames around each pixel's current best (copied
out of the ring once the k frames after the best have been seen), and the strongest
focus value seen *away* from the peak (more than k frames from it), which reveals a
second peak (e.g. a defocused component edge bleeding over the board).

The focus curve around the peak is modelled as F(z) = F_peak·exp(−(z − z̄)²/(2σ_F²)),
i.e. a parabola in ln F. ``gauss3`` passes it through the peak and its two neighbours
(Nayar's 3-point Gaussian interpolation, generalised to uneven z spacing); ``lsq`` fits
it to the 2k+1 samples by least squares weighted by F² (so noisy low values count little).
Pertuz's reliability R = 20·log10(F_peak / mean|F − model|) over the 2k+1 samples (dB).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ._config import FitMethod

__all__ = ["PeakFit", "PeakTracker", "fit_peaks"]

_TINY = np.float32(1e-12)


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
    """

    def __init__(self, shape: tuple[int, int], n_frames: int, *, half_width: int) -> None:
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
        # window[j] holds F at frame best_idx - k + j (NaN where outside the stack)
        self.window = np.full((2 * k + 1, *shape), np.nan, np.float32)
        self.ring: list[np.ndarray | None] = [None] * (2 * k + 1)
        self._better = np.empty(shape, bool)
        self._far = np.empty(shape, bool)
        self._frame_no = np.empty(shape, np.int16)
        self._scratch = np.empty(shape, np.float32)
        self._zeros = np.zeros(shape, np.float32)
        self._nans = np.full(shape, np.nan, np.float32)

    def update(self, n: int, focus: np.ndarray) -> np.ndarray:
        """Take frame ``n``'s focus measure; return the (H, W) bool mask of new bests.

        The returned mask is reused by the next call: copy it to keep it.
        """
        k, size = self.k, 2 * self.k + 1
        better = np.greater(focus, self.best, out=self._better)
        mask = better.view(np.uint8)
        # cv2.copyTo with a mask is branch-free; numpy's where= is slow on noisy masks
        np.maximum(self.best, focus, out=self.best)
        self._frame_no.fill(n)
        cv2.copyTo(self._frame_no, mask, self.best_idx)
        far = np.less(self.best_idx, n - k, out=self._far)
        np.multiply(focus, far, out=self._scratch)
        np.maximum(self.after, self._scratch, out=self.after)
        cv2.copyTo(self._zeros, mask, self.after)
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
            src = self.ring[frame % size] if 0 <= frame <= upto else self._nans
            cv2.copyTo(src, mask, self.window[j])

    def finish(self) -> None:
        """Settle the pixels whose best lies in the last k frames."""
        last = self.n_frames - 1
        for m in range(max(0, last - self.k + 1), last + 1):
            self._settle(m, upto=last)

    @property
    def alternative(self) -> np.ndarray:
        """(H, W) float32: strongest focus more than k frames away from the peak."""
        return np.maximum(self.before, self.after)


@dataclass(frozen=True, eq=False)
class PeakFit:
    """Per-pixel result of the peak fit; all arrays ``(H, W)``."""

    height_mm: np.ndarray  # float32, interpolated peak position
    coarse_mm: np.ndarray  # float32, z of the frame of maximum focus
    f_peak: np.ndarray  # float32
    sigma_mm: np.ndarray  # float32, NaN where the fit is inverted
    reliability_db: np.ndarray  # float32
    ambiguity: np.ndarray  # float32 in [0, 1]: excess focus away from the peak / peak
    prominence: np.ndarray  # float32 in [0, 1]: 1 - (lowest focus within ±k frames) / peak
    interior: np.ndarray  # bool: peak not on the first/last frame and fit not inverted
    best_idx: np.ndarray  # int16


def fit_peaks(tracker: PeakTracker, z_mm: np.ndarray, *, method: FitMethod,
              workers: int = 1) -> PeakFit:
    """Fit the Gaussian focus-curve model to the tracked windows.

    Parameters
    ----------
    tracker : PeakTracker
        After :meth:`PeakTracker.finish`.
    z_mm : (n_frames,) float64
        Ascending focused-plane heights of the frames.
    method : FitMethod
    workers : int
        Threads; the rows are split into this many blocks (numpy releases the GIL).
    """
    h = tracker.shape[0]
    if workers <= 1 or h < 64:
        return _fit_block(tracker.best_idx, tracker.window, tracker.alternative, tracker.best,
                          z_mm, k=tracker.k, method=method)
    from concurrent.futures import ThreadPoolExecutor

    alternative = tracker.alternative
    edges = np.linspace(0, h, workers + 1).astype(int)
    # Each thread writes its rows straight into the full-size results (no concatenation
    # afterwards: that copy alone cost ~10 % of a 40-frame 1024² reconstruction).
    dtypes = {"interior": bool, "best_idx": np.int16}
    out = {f: np.empty(tracker.shape, dtypes.get(f, np.float32)) for f in PeakFit.__dataclass_fields__}

    def run(r0: int, r1: int) -> None:
        part = _fit_block(tracker.best_idx[r0:r1], tracker.window[:, r0:r1], alternative[r0:r1],
                          tracker.best[r0:r1], z_mm, k=tracker.k, method=method)
        for f, a in out.items():
            a[r0:r1] = getattr(part, f)

    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(run, edges[:-1], edges[1:]))
    return PeakFit(**out)


def _fit_block(best_idx, window, alternative, best, z_mm, *, k: int, method: FitMethod) -> PeakFit:
    """:func:`fit_peaks` on one block of rows."""
    z_mm = np.asarray(z_mm, dtype=np.float64)
    n = len(z_mm)
    kb = best_idx
    z_pad = np.concatenate([np.full(k, np.nan), z_mm, np.full(k, np.nan)])
    z0 = z_mm[kb]
    coarse = z0.astype(np.float32)

    def u_at(j: int) -> np.ndarray:
        """(H, W) float32: z of window sample j relative to the best frame (NaN outside)."""
        return (np.take(z_pad, kb + j) - z0).astype(np.float32)

    w = window
    f0, fm, fp = w[k], w[k - 1], w[k + 1]
    um, up = u_at(k - 1), u_at(k + 1)
    on_edge = (kb == 0) | (kb == n - 1) | ~np.isfinite(fm) | ~np.isfinite(fp)

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if method == FitMethod.LSQ:
            u = np.stack([u_at(j) for j in range(2 * k + 1)])
            c, beta, l0 = _lsq_log_parabola(u, w)
            del u
        else:
            lm, l0, lp = (np.log(np.maximum(x, _TINY)) for x in (fm, f0, fp))
            c = ((lp - l0) / up - (l0 - lm) / (-um)) / (up - um)
            beta = (l0 - lm) / (-um) - c * um
        inverted = ~(c < 0)
        shift = -beta / (2 * c)
        sigma2 = -1.0 / (2 * c)
        log_peak = l0 - beta * beta / (4 * c)
        # A fitted peak outside the sampled neighbourhood is not trusted.
        wild = ~(np.abs(shift) <= np.maximum(np.abs(um), np.abs(up)))
        bad = on_edge | inverted | wild
        if method == FitMethod.ARGMAX:
            offset = np.zeros_like(coarse)
        else:
            offset = np.where(bad, 0.0, shift).astype(np.float32)
        height = (z0 + offset).astype(np.float32)
        sigma = np.where(inverted | on_edge, np.nan, np.sqrt(sigma2)).astype(np.float32)
        f_peak = np.where(bad, f0, np.exp(np.minimum(log_peak, 80.0))).astype(np.float32)
        # Pertuz's reliability R over the 2k+1 samples (NaN samples skipped), and the
        # lowest sample (for the prominence), one window row at a time.
        res_sum = np.zeros_like(f0)
        res_n = np.zeros_like(f0)
        low = np.full_like(f0, np.inf)
        inv_2s2 = (-0.5 / sigma2).astype(np.float32)
        for j in range(2 * k + 1):
            wj = w[j]
            model = f_peak * np.exp((u_at(j) - offset) ** 2 * inv_2s2)
            r = np.abs(wj - model)
            ok = np.isfinite(r)
            res_sum += np.where(ok, r, 0)
            res_n += ok
            np.fmin(low, wj, out=low)
        mean_res = res_sum / np.maximum(res_n, 1)
        rel = 20.0 * np.log10(f_peak / np.maximum(mean_res, 1e-12 * np.maximum(f_peak, _TINY)))
        rel = np.where(bad, 0.0, rel).astype(np.float32)
        # The strongest focus more than k frames from the peak, less what the fitted peak
        # itself predicts k+½ frames out (the tail of a wide peak is not a second peak).
        step = float(np.median(np.diff(z_mm))) if n > 1 else 1.0
        tail = np.where(inverted | on_edge, 0.0, np.exp(-((k + 0.5) * step) ** 2 / (2 * sigma2)))
        ambiguity = np.clip(alternative / np.maximum(best, _TINY) - tail,
                            0, 1).astype(np.float32)
        prominence = np.clip(1.0 - low / np.maximum(f0, _TINY), 0, 1).astype(np.float32)
    return PeakFit(
        height_mm=height,
        coarse_mm=coarse,
        f_peak=f_peak,
        sigma_mm=sigma,
        reliability_db=rel,
        ambiguity=ambiguity,
        prominence=prominence,
        interior=~bad,
        best_idx=best_idx,
    )


def _lsq_log_parabola(u: np.ndarray, w: np.ndarray):
    """Least-squares ln F = l0 + β·u + c·u² over the window, weights F² (Caruana/Guo).

    Returns ``(c, beta, l0)`` per pixel.
    """
    valid = np.isfinite(w) & np.isfinite(u) & (w > 0)
    f = np.where(valid, w, 0.0).astype(np.float64)
    uu = np.where(valid, u, 0.0).astype(np.float64)
    lg = np.where(valid, np.log(np.maximum(f, 1e-30)), 0.0)
    wt = f * f
    s = [np.sum(wt * uu**p, axis=0) for p in range(5)]
    t = [np.sum(wt * uu**p * lg, axis=0) for p in range(3)]
    # normal equations [[s0 s1 s2][s1 s2 s3][s2 s3 s4]] · [l0 β c] = [t0 t1 t2]
    a = np.stack([np.stack([s[0], s[1], s[2]], -1),
                  np.stack([s[1], s[2], s[3]], -1),
                  np.stack([s[2], s[3], s[4]], -1)], -2)
    b = np.stack(t, -1)[..., None]
    ok = valid.sum(0) >= 3
    det = np.linalg.det(a)
    ok &= np.abs(det) > 1e-300
    a[~ok] = np.eye(3)
    b[~ok] = 0
    sol = np.linalg.solve(a, b)[..., 0]
    l0, beta, c = sol[..., 0], sol[..., 1], sol[..., 2]
    c = np.where(ok, c, np.nan)
    return c.astype(np.float32), beta.astype(np.float32), l0.astype(np.float32)
