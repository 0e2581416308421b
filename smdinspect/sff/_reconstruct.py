"""From a focal stack to a :class:`Surface`, in one streaming pass over the frames."""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable

import cv2
import numpy as np

from .._malloc import release_free_memory
from ..errors import InputError
from ..stack import FocalStack
from ._align import Alignment, estimate_alignment
from ._blur_order import FACTOR as ORDER_FACTOR
from ._blur_order import SIGMAS_PX, blur_order_suspect, reduce_frame
from ._config import FitMethod, FocusConfig
from ._confidence import (PRECISION_BOX_WINDOWS, blur_px_per_frame, borrowed_mask,
                          confidence_cues, confidence_map, defocus_halo_mask, depth_edge_mask,
                          halo_reach_px, hidden_step_mask, precision_steps, step_levels,
                          unsupported_mask)
from ._depth import (PeakTracker, centroid_correction, fit_peaks, local_plane,
                     masked_gradient, select_curve_power)
from ._focus import (FocusOperator, band_powers, focus_measure, focus_measure_moments,
                     magnification_exponent, noise_focus, noise_focus_spread, prefilter,
                     prefilter_sigma)
from ._surface import UNRELIABLE_REASONS, Surface, clipped_white, reason_shares

__all__ = ["reconstruct", "to_gray"]

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]
#: Every frame is scaled to this mean grey level before its focus measure.
MEAN_GREY = 128.0
#: reason name -> code of :data:`~smdinspect.sff._surface.UNRELIABLE_REASONS`
REASON = {name: code for code, (name, _) in UNRELIABLE_REASONS.items()}
#: A magnification growing by more than this towards higher z draws a warning (a
#: moving-camera rig shrinks the image as z goes up; see Alignment.magnification_trend).
MAGNIFICATION_TREND_WARN = 0.01
#: Decoded frames the alignment pre-pass may keep for the main pass (bytes).
FRAME_CACHE_BYTES = 256 * 2**20
#: Reduced grey frames the stream may keep for the blur-order check's pass (bytes).
ORDER_CACHE_BYTES = 64 * 2**20
#: A share of the field sharpest on the lowest or highest frame (the scene extends beyond
#: the sweep there) from which reconstruct() warns and names the end to extend.
BEYOND_SWEEP_WARN = 0.05
#: A share of the field clipped white in the all-in-focus image from which
#: reconstruct() warns (over-exposure: no height can be measured there).
CLIPPED_WARN = 0.01
#: ``summary.json`` → ``beyond_sweep`` keys, the end frame each counts and the side of the
#: swept range it lies on.
BEYOND_SWEEP_ENDS = (("below_fraction", "lowest", "below"), ("above_fraction", "highest", "above"))
#: Frames (evenly spaced) read before the main pass to choose the "auto" pre-filter
#: when there is no alignment pre-pass (kept in the frame cache).
PREFILTER_SAMPLE_FRAMES = 9
#: Rows measured beyond each side of a band's core (see :func:`_bands`): the reach of
#: the checks around a pixel (halo, edges, support, the coarse levels' footprints).
BAND_MARGIN_PX = 128
#: Band cores start on multiples of this (the largest coarse block, 4²).
BAND_ALIGN_PX = 16
#: Side of the square in which a height step is looked for (:func:`step_levels`; the
#: default of :func:`depth_edge_mask`).
EDGE_SPAN_PX = 5


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) float32 luminance of a grey or RGB frame, in the frame's own units."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return image.astype(np.float32, copy=False)


def reconstruct(
    stack: FocalStack,
    config: FocusConfig | None = None,
    *,
    progress: Progress | None = None,
) -> Surface:
    """Measure the height of every pixel of a focal stack by shape from focus.

    Frames are decoded and their focus measures computed in ``config.workers`` threads;
    the per-pixel peak state is updated in frame order. Memory is constant in the number
    of frames (see :class:`smdinspect.sff.PeakTracker`). Frames larger than
    :attr:`FocusConfig.band_mpixels` are measured in bands of rows, one after the other
    (:func:`_bands`; the choices made from the data are made once and shared, and
    ``summary.json`` → ``bands`` lists the bands): memory follows the band.

    Parameters
    ----------
    stack : FocalStack
    config : FocusConfig, optional
    progress : callable(done, total), optional

    Returns
    -------
    Surface

    Raises
    ------
    InputError
        A frame is unreadable, or differs in size or channel count from the first.

    Examples
    --------
    >>> from smdinspect.sff import FocusConfig, reconstruct      # doctest: +SKIP
    >>> surface = reconstruct(FocalStack.open("stacks/cone"), FocusConfig())  # doctest: +SKIP
    """
    if not isinstance(stack, FocalStack):
        raise InputError(f"stack must be a FocalStack; got {type(stack).__name__}")
    config = config or FocusConfig()
    t0 = time.perf_counter()
    n = len(stack)
    z_mm = stack.z_mm
    alignment: Alignment | None = None
    # frames decoded by the alignment pre-pass, kept (up to FRAME_CACHE_BYTES) for the
    # main pass instead of being decoded twice; only the decoded image (its grey is
    # remade from it: cheaper than keeping a float32 copy)
    cache: dict[int, np.ndarray] = {}
    # power spectra of tiles of the frames read before the main pass (for prefilter "auto")
    powers: dict[int, np.ndarray | None] = {}
    auto = config.prefilter_px == "auto"
    pool = ThreadPoolExecutor(max_workers=config.workers, thread_name_prefix="sff")
    cached = [0]
    # mean grey of every whole frame (each band's focus is normalised by its frame's)
    means: dict[int, float] = {}

    def read(i: int) -> np.ndarray:
        image = stack.read_frame(i)
        gray = to_gray(image)
        means[i] = mean = float(gray.mean())
        if auto:
            powers[i] = band_powers(gray, gain=MEAN_GREY / mean if mean > 0 else 1.0)
        if cached[0] + image.nbytes <= FRAME_CACHE_BYTES:
            cache[i] = image
            cached[0] += image.nbytes
        return gray

    if config.align:
        reads = _prefetch(read, n, pool, depth=config.workers + 1)
        try:
            alignment = estimate_alignment(reads, n, z_mm=z_mm)
        except BaseException:
            pool.shutdown(cancel_futures=True)
            raise
        log.info("aligned %d frames onto frame %d (the most magnified); field %.1f %% of it",
                 n, alignment.reference, 100 * alignment.field.mean())
        trend = alignment.magnification_trend()
        if trend > MAGNIFICATION_TREND_WARN:
            log.warning(
                "the image grows by %.1f %% from the lowest to the highest z: on a rig that "
                "moves the camera this means z runs the wrong way (check the sign of "
                "--step-mm or the stack's z_mm: every height would be flipped); on a rig "
                "that focuses with the lens it is expected", 100 * trend)
    elif auto:
        sample = np.unique(np.linspace(0, n - 1, min(n, PREFILTER_SAMPLE_FRAMES)).round())
        try:
            list(pool.map(read, sample.astype(int).tolist()))
        except BaseException:
            pool.shutdown(cancel_futures=True)
            raise
    if auto:
        sigma, modulation = prefilter_sigma(
            [powers[i] for i in sorted(powers)], config.operator,
            scales=None if alignment is None else [alignment.scale(i) for i in sorted(powers)])
        # ±3σ within the window: the pre-filter must not widen the footprint the halo,
        # edge and support checks are sized for
        sigma = min(sigma, config.window_px / 6.0)
        log.info("focus pre-filter σ %.2f px (band modulation %s)", sigma, modulation)
    else:
        sigma, modulation = float(config.prefilter_px), None
    # the focus's change with magnification for this sweep's texture (aligned sweeps)
    mag_k = (None if alignment is None else
             magnification_exponent(config.operator, [powers.get(i) for i in range(n)],
                                    [alignment.scale(i) for i in range(n)], sigma))
    try:
        frame0 = cache.get(0)
        if frame0 is None:  # decoded here once, for its size; the first band takes it
            frame0 = cache[0] = stack.read_frame(0)
    except BaseException:
        pool.shutdown(cancel_futures=True)
        raise
    shape = alignment.shape if alignment is not None else frame0.shape[:2]
    if min(shape) < config.window_px:  # as focus_measure says it
        pool.shutdown(cancel_futures=True)
        raise InputError(f"window_px must be <= the frame's smaller side ({min(shape)} px for "
                         f"a {shape[0]}x{shape[1]} frame); got {config.window_px}")
    bands = _bands(shape, config)
    run = _Run(stack=stack, config=config, pool=pool, alignment=alignment, sigma=sigma,
               magnification_k=mag_k,
               cache=cache, means=means, shape=shape, frame_shape=frame0.shape,
               # what every band must share: the coarse levels and the choices made
               # from the data, taken from the first band measured (the middle one)
               decided={"coarse_factors": _coarse_factors(config, shape),
                        "halo_cap_px": min(shape) // 4})
    del frame0
    if len(bands) > 1:
        log.info("%dx%d px measured in %d bands of rows (at most %.1f Mpixel each, "
                 "%d px margins)", shape[1], shape[0], len(bands), config.band_mpixels,
                 BAND_MARGIN_PX)
    out: dict = {}
    stats: dict = collections.defaultdict(float)
    with pool:
        for k, band in enumerate(sorted(bands, key=lambda b: abs(b[2] + b[3] - shape[0]))):
            def sub(done: int, total: int, k=k) -> None:
                progress(k * total + done, len(bands) * total)

            part = _measure(run, band, progress=None if progress is None else sub)
            lo, hi, core_lo, core_hi = band
            keep = slice(core_lo - lo, core_hi - lo)
            for key, plane in part.pop("planes").items():
                if plane is None:
                    out[key] = None
                    continue
                if key not in out:
                    out[key] = np.empty((shape[0], *plane.shape[1:]), plane.dtype)
                out[key][core_lo:core_hi] = plane[keep]
            for key, value in part.items():
                stats[key] += value
            del part
            release_free_memory()  # the band's planes, before the next band allocates
    return _finish(run, out, stats, bands, t0=t0, modulation=modulation)


def _measure(run: "_Run", band: tuple[int, int, int, int], *,
             progress: Progress | None) -> dict:
    """Measure one band of rows ``band = (lo, hi, core_lo, core_hi)`` of the output grid
    (the whole grid when the frames fit one band): stream its frames, fit and judge its
    peaks. Returns the band's planes (``"planes"``, rows ``lo .. hi``) and its counts
    for the summary (see :func:`reconstruct`)."""
    stack, config, alignment, sigma = run.stack, run.config, run.alignment, run.sigma
    cache, means, decided = run.cache, run.means, run.decided
    n = len(stack)
    z_mm = stack.z_mm
    lo, hi, core_lo, core_hi = band
    rows = None if (lo, hi) == (0, run.shape[0]) else (lo, hi)
    first = stack.frames[0].path
    operator = FocusOperator(config.operator)
    own_px = (config.own_window_px
              if operator.uses_threshold and config.own_window_px < config.window_px else 0)
    moments_wanted = ((config.centroid_correction or own_px) and operator.uses_threshold
                      and config.fit != FitMethod.ARGMAX)

    # Σ Mx and Σ My of the frames (for the centroid correction), summed in the workers
    moment_sums = _FrameOrderSums(n) if moments_wanted else None
    # The blur-order check's pass after the fit wants every frame aligned and reduced
    # (reduce_frame): the workers make it from the frame they have just aligned, for the
    # first frames that fit ORDER_CACHE_BYTES (a 2048x1536 frame: 3 MiB), instead of the
    # pass decoding and aligning the frame again (pcb-oblique: 33 of its 42 ms a frame).
    # When the check is not judged they cost the reduction (9 ms). One band only: a
    # band's frames are aligned from other crops of them here than in the pass.
    reduced: dict[int, np.ndarray] = {}
    keep_reduced = 0
    if config.blur_order_ratio > 0 and rows is None:
        h2, w2 = run.shape[0] // ORDER_FACTOR, run.shape[1] // ORDER_FACTOR
        keep_reduced = ORDER_CACHE_BYTES // max(1, h2 * w2 * np.dtype(np.float32).itemsize)

    def load(i: int):
        moments = None  # stays None when the frame fails: the next frames must not wait
        try:
            image, focus, small, own, moments = _load(i)
            return image, focus, small, own
        finally:
            if moment_sums is not None:
                moment_sums.add(i, moments)

    def _load(i: int):
        image = cache.pop(i, None)
        if image is None:
            image = stack.read_frame(i)
        if image.shape != run.frame_shape:
            raise _mismatch(stack.frames[i].path, image.shape, first, run.frame_shape)
        gray = None
        mean = means.get(i)
        if mean is None:
            gray = to_gray(image)
            means[i] = mean = float(gray.mean())
        src = 0  # the first frame row of the band's crop
        if rows is not None:
            src, end = rows
            if alignment is not None:  # the frame rows the band is resampled from
                src, end = alignment.source_rows(
                    i, rows, pad=config.window_px + int(np.ceil(4 * sigma)) + 4)
            image = image[src:end].copy()  # the whole frame is let go
            gray = None if gray is None else gray[src:end]
        if gray is None:
            gray = to_gray(image)
        # Same mean grey in every frame: exposure drift, flicker and auto-gain change the
        # focus measure, defocus does not change the mean (blur conserves light).
        norm = MEAN_GREY / mean if mean > 0 else 1.0
        if mean > 0:
            if np.may_share_memory(gray, image):  # a float32 grey frame is its own grey
                gray = gray * np.float32(norm)
            else:  # a grey made here: scaled in place (no second frame-sized plane)
                gray *= np.float32(norm)
        # σ is in reference pixels; frame i's pixels are larger by 1/scale
        sigma_i = round(sigma * (alignment.scale(i) if alignment is not None else 1.0), 3)
        gray = prefilter(gray, sigma_i)
        own = None
        if moments_wanted:
            focus, mx, my, *rest = focus_measure_moments(
                gray, operator=config.operator, window_px=config.window_px,
                threshold=config.threshold, own_px=own_px)
            own = rest[0] if rest else None
        else:
            focus = focus_measure(gray, operator=config.operator, window_px=config.window_px,
                                  threshold=config.threshold)
            mx = my = None
        del gray
        if alignment is not None:
            def warp(plane: np.ndarray) -> np.ndarray:
                return alignment.warp(plane, i, rows=rows, src_row=src)

            gain = alignment.scale(i) ** run.magnification_k
            if gain != 1.0 or sigma_i != sigma:
                # The same texture seen less magnified has steeper derivatives: scale the
                # scene's part of the focus, not the sensor noise's (which is per pixel).
                # The noise part becomes the reference frame's: with a pre-filter (in
                # reference pixels) a frame's own noise floor differs, and a floor that
                # changes over the sweep pulls every peak towards its higher end.
                level = (alignment.noise_sigma * norm) ** operator.curve_power
                for plane, side in ((focus, config.window_px), (own, own_px)):
                    if plane is None:
                        continue
                    mine = noise_focus(operator.value, side, config.threshold, sigma_i) * level
                    ref = noise_focus(operator.value, side, config.threshold,
                                      round(sigma, 3)) * level
                    plane -= np.float32(mine)
                    plane *= np.float32(gain)
                    plane += np.float32(ref)
                if mx is not None:  # the noise's centroid is the window centre
                    mx *= np.float32(gain)
                    my *= np.float32(gain)
            if mx is not None:
                # offsets in frame i's pixels -> the reference grid's
                inv = np.linalg.inv(alignment.transforms[i][:2, :2]).astype(np.float32)
                if abs(inv[0, 1]) + abs(inv[1, 0]) < 1e-6 * (abs(inv[0, 0]) + abs(inv[1, 1])):
                    mx *= inv[0, 0]  # no rotation (the usual focus zoom): in place
                    my *= inv[1, 1]
                else:
                    mx, my = (cv2.addWeighted(mx, float(inv[0, 0]), my, float(inv[0, 1]), 0.0),
                              cv2.addWeighted(mx, float(inv[1, 0]), my, float(inv[1, 1]), 0.0))
                mx, my = warp(mx), warp(my)
            focus = warp(focus)
            if own is not None:
                own = warp(own)
            image = warp(image)
        if i < keep_reduced:
            reduced[i] = reduce_frame(image)
        small = [_CoarseLevel.reduce(focus, f)  # in the worker
                 for f in decided["coarse_factors"]]
        return image, focus, small, own, (None if mx is None else (mx, my))

    tracker: PeakTracker | None = None
    coarse: list[_CoarseLevel] = []
    aif = None
    depth = config.workers + 2  # frames in flight; bounds memory
    pool = run.pool
    t0 = time.perf_counter()
    try:
        pending: collections.deque = collections.deque()
        next_i = 0
        for i in range(n):
            while next_i < n and len(pending) < depth:
                pending.append(pool.submit(load, next_i))
                next_i += 1
            image, focus, small, own = pending.popleft().result()
            if tracker is None:
                tracker = PeakTracker(image.shape[:2], n, half_width=config.fit_half_width,
                                      sum_focus=moments_wanted)
                coarse = [_CoarseLevel(image.shape[:2], n, config, f)
                          for f in decided["coarse_factors"]]
                aif = np.zeros_like(image)
            better = tracker.update(i, focus, own=own)
            for level, plane in zip(coarse, small):
                level.tracker.update(i, plane)
            cv2.copyTo(image, better.view(np.uint8), aif)
            if progress is not None:
                progress(i + 1, n)
        del image, focus, small, own, better  # the last frame's planes
    except BaseException:
        for future in pending:
            future.cancel()
        raise
    t_stream = time.perf_counter() - t0
    release_free_memory()  # the workers' freed frames, before the fit allocates afresh
    centroid = None
    if config.centroid_correction and moment_sums is not None and moment_sums.sums is not None:
        centroid = tracker.centroid_px(*moment_sums.sums, window_px=config.window_px)
    moment_sums = None
    energy = tracker.texture_energy if coarse else None
    tracker.focus_sum = None  # summed into the centroid and the energy

    noise_gain = _noise_gain(config, sigma)
    order_out: dict = {}
    order = None
    if config.blur_order_ratio > 0:
        def order(best_idx: np.ndarray) -> np.ndarray:
            """The blur-order check's second pass over the (aligned) frames."""
            def read_reduced(i: int) -> np.ndarray:
                kept = reduced.pop(i, None)
                if kept is not None:
                    return kept
                image = stack.read_frame(i)
                if alignment is not None:
                    src = 0
                    if rows is not None:
                        src, end = alignment.source_rows(i, rows, 2)
                        image = image[src:end]
                    return reduce_frame(alignment.warp(image, i, rows=rows, src_row=src))
                return reduce_frame(image if rows is None else image[lo:hi])

            with ThreadPoolExecutor(max_workers=config.workers,
                                    thread_name_prefix="sff-order") as again:
                return blur_order_suspect(_prefetch(read_reduced, n, again, depth=config.workers),
                                          n, best_idx, box_px=config.window_px + 6,
                                          ratio=config.blur_order_ratio,
                                          floors=decided.setdefault("order_floors", {}))
    halo_px = config.window_px + 2   # the halo test's base reach
    fit, confidence, halo, beyond, precision, failed = _level(
        tracker, z_mm, config, window_px=config.window_px, halo_radius_px=halo_px,
        noise_gain=noise_gain, own_px=own_px, decided=decided, grid_rows=(lo, run.shape[0]),
        order=order, order_out=order_out)
    reduced.clear()  # what the check did not take (it was not judged)
    field = np.ones(tracker.shape, bool)
    if alignment is not None:
        field = alignment.field if rows is None else alignment.field[lo:hi]
    confidence[~field] = 0.0
    height = fit.coarse_mm if config.fit == FitMethod.ARGMAX else fit.height_mm
    if centroid is not None:
        height = centroid_correction(height, confidence >= config.min_confidence,
                                     centroid, window_px=config.window_px,
                                     max_mm=abs(stack.step_mm),
                                     width_steps=fit.sigma_mm / np.float32(abs(stack.step_mm)))
    # coarse levels fill, finest first, what the finer ones left unreliable
    filled: list[np.ndarray] = []
    for level in coarse:
        before_h, before_c, before_p = height, confidence, precision
        height, confidence, use, precision = level.merge(
            height, confidence, halo, field, z_mm, config, noise_gain=noise_gain,
            energy=energy, precision=precision, decided=decided)
        if filled and use.any() and config.edge_jump_steps > 0:
            # a second coarse level's window spans whole parts: where its fills meet a
            # height step, the fill is the suspect, not the finer level's pixels
            near = _near_step(height, confidence >= config.min_confidence,
                              jump_mm=config.edge_jump_steps * abs(stack.step_mm),
                              radius_px=level.window_px // 2) & use
            height = np.where(near, before_h, height)
            confidence = np.where(near, before_c, confidence)
            if precision is not None:
                precision = np.where(near, before_p, precision)
            use &= ~near
        filled.append(use)
    del energy
    core = slice(core_lo - lo, core_hi - lo)
    stats = {f"coarse/{lv.factor}": float(np.count_nonzero(u[core]))
             for lv, u in zip(coarse, filled)}
    misaligned = None
    if alignment is not None and not alignment.trusted:
        # a wrong registration puts a frame's focus on the wrong pixels: a height is only
        # as good as the alignment of the frames around its peak
        # (the warnings: _finish)
        if alignment.checks and not alignment.verified_spans:
            confidence[:] = 0.0
            beyond[:] = 0
            misaligned = np.ones(height.shape, bool)
        else:
            pos = np.interp(height, z_mm, np.arange(n, dtype=np.float64))
            k = config.fit_half_width
            bad = np.zeros(height.shape, bool)
            for i, j in alignment.inconsistent:
                bad |= (pos >= i - k) & (pos <= j + k)
            stats["misaligned"] = float(np.count_nonzero(
                (bad & (confidence >= config.min_confidence))[core]))
            confidence[bad] = 0.0
            misaligned = bad
    edges = lonely = None
    if config.edge_jump_steps > 0:
        jump = config.edge_jump_steps * stack.step_mm
        # The gap of unreliable pixels beside a step is mostly the halo test's: it drops
        # the weak texture within its base reach of the step's strong edge, leaving the
        # band bled to the high side beyond it. A square reaching one pixel further than
        # that each way, from the first pixel past such a gap, sees the other side.
        gap = halo_reach_px(halo_px)
        wide = (halo_px, 2 * (gap + 1) + 1) if config.edge_gap_check else 0
        # the halo check's reach grows with the depth gap (2κg px): beside a tall step
        # its gap is up to twice as wide, read over the gap's borders alone (53 px for
        # a 9-px window; on the tuning boards a 105-px square added nothing and a 27-px
        # one dropped good pixels)
        across = 2 * (2 * gap + 2) + 1 if config.edge_gap_check else 0
        reliable = confidence >= config.min_confidence
        # the steps are found once; each level judges them at its own radius
        levels = step_levels(height, reliable, jump_mm=jump, span_px=EDGE_SPAN_PX)
        edges = depth_edge_mask(height, reliable, jump_mm=jump, span_px=EDGE_SPAN_PX,
                                radius_px=config.window_px // 2 + 1, wide_span_px=wide,
                                gap_span_px=across, levels=levels)
        for level, use in zip(coarse, filled):
            if use.any():  # a coarse window bleeds the higher side over half its width
                edges |= use & depth_edge_mask(
                    height, reliable, jump_mm=jump, span_px=EDGE_SPAN_PX,
                    radius_px=level.window_px // 2 + 1, levels=levels)
        del levels
        if config.edge_gap_check:
            # a step whose low side is all unreliable, told by those pixels' own peaks
            # (textured ones: a peak that fails the noise test is noise, anywhere)
            textured = field & (failed != REASON["weak_texture"])
            edges |= hidden_step_mask(height, reliable, textured, jump_mm=abs(jump),
                                      radius_px=config.window_px // 2 + 1,
                                      side_px=config.window_px + 4)
        confidence[edges] = 0.0
    reliable = confidence >= config.min_confidence
    if config.support_steps > 0:
        # independent windows must corroborate a height (kills isolated noise peaks)
        tol = config.support_steps * stack.step_mm
        lonely = unsupported_mask(height, reliable, distance_px=config.window_px, tol_mm=tol)
        for level, use in zip(coarse, filled):
            lonely = (lonely & ~use) | (use & unsupported_mask(
                height, reliable, distance_px=level.window_px, tol_mm=tol))
        confidence[lonely] = 0.0
        reliable &= ~lonely
    if config.plane_px >= 3:
        # the heights' random error averaged after the peak (precision: the reading's
        # before it, which the plane does not raise: neighbouring windows overlap and
        # their errors are largely shared, so how much it lowers them is not known here)
        height, used = local_plane(height, reliable, side_px=config.plane_px)
        stats["plane"] = float(np.count_nonzero(used[core]))
    # Why each pixel is unreliable: the first test it failed, in the order they are
    # made (later assignments win): the field and the sweep's ends, the alignment, the
    # confidence cues (failed), the halo checks, the depth edges, the support. (Where a
    # coarse level filled it, the fine level's reasons stand. Over-exposure and the
    # parallax's hidden pixels: _finish.)
    reason = np.full(height.shape, REASON["peak_shape"], np.uint8)
    for name, mask in (("unsupported", lonely), ("depth_edge", edges), ("halo", halo)):
        if mask is not None:
            reason[mask] = REASON[name]
    np.copyto(reason, failed, where=failed > 0)
    for name, mask in (("misaligned", misaligned), ("above_sweep", beyond > 0),
                       ("below_sweep", beyond < 0), ("outside_field", ~field)):
        if mask is not None:
            reason[mask] = REASON[name]
    reason[reliable] = 0
    del failed
    for key in ("flagged", "judged"):  # counted over the band's margins too
        if f"_{key}" in order_out:
            stats[f"order/{key}"] = order_out[f"_{key}"]
    if "order" not in decided and order_out:
        decided["order"] = {k: v for k, v in order_out.items() if not k.startswith("_")}
    stats["t_stream"] = t_stream
    stats["planes"] = {
        "height": height, "confidence": confidence, "reliable": reliable, "f_peak": fit.f_peak,
        "sigma_mm": fit.sigma_mm, "reliability_db": fit.reliability_db, "aif": aif,
        "beyond": beyond, "precision": precision, "reason": reason}
    return stats


def _noise_gain(config: FocusConfig, sigma: float) -> float:
    """A pre-filtered noise is correlated: the noise test must ask for a larger peak
    (the ratio of the noise focus spreads with and without the pre-filter, ≥ 1)."""
    if sigma <= 0:
        return 1.0
    op = FocusOperator(config.operator).value
    return max(1.0, noise_focus_spread(op, config.window_px, config.threshold, round(sigma, 3))
               / noise_focus_spread(op, config.window_px, config.threshold))


def _finish(run: "_Run", planes: dict, stats: dict, bands: list, *, t0: float,
            modulation) -> Surface:
    """The whole grid's measurement from its bands' planes: the alignment's parallax
    correction, the field beyond the sweep, the summary; the :class:`Surface`."""
    stack, config, alignment, sigma = run.stack, run.config, run.alignment, run.sigma
    n, z_mm = len(stack), stack.z_mm
    (height, confidence, reliable, f_peak, sigma_mm, reliability_db, aif, beyond, precision,
     reason) = (planes[key] for key in ("height", "confidence", "reliable", "f_peak",
                                        "sigma_mm", "reliability_db", "aif", "beyond",
                                        "precision", "reason"))
    decided = run.decided
    meta: dict = {}
    if "curve" in decided:
        meta["curve_power"] = decided["curve"]
    if "order" in decided:
        order = dict(decided["order"])
        if "order/judged" in stats:
            order["flagged_of_reliable"] = round(
                stats["order/flagged"] / max(stats["order/judged"], 1.0), 5)
        meta["blur_order"] = order
    field = np.ones(run.shape, bool)
    if alignment is not None:
        field = alignment.field
        meta["alignment"] = alignment.summary()
        if not alignment.trusted:
            if alignment.checks and not alignment.verified_spans:
                log.warning("the frames' alignment could not be verified (no span of the "
                            "sweep registered directly): every height is marked unreliable")
            else:
                log.warning("the frames' alignment disagrees with direct registrations over "
                            "frames %s: the %.1f %% of heights that peak there are marked "
                            "unreliable",
                            ", ".join(f"{i}-{j}" for i, j in alignment.inconsistent),
                            100 * stats["misaligned"] / height.size)
    factors = decided["coarse_factors"]
    if factors:
        meta["coarse_fraction"] = round(sum(stats[f"coarse/{f}"] for f in factors)
                                        / height.size, 4)
        meta["coarse_fractions"] = {str(f): round(stats[f"coarse/{f}"] / height.size, 4)
                                    for f in factors}
    if len(bands) > 1:
        meta["bands"] = {"rows": [[b[2], b[3]] for b in bands], "margin_px": BAND_MARGIN_PX}
    if config.plane_px >= 3:
        meta["plane"] = {"side_px": config.plane_px, "fraction_of_reliable": round(
            stats["plane"] / max(float(np.count_nonzero(reliable)), 1.0), 4)}
    pixel_size = stack.pixel_size_mm
    if alignment is not None:
        sources, info = alignment.parallax_sources(z_mm, height, reliable)
        meta["alignment"]["parallax"] = info
        if sources is not None:
            if pixel_size is not None:
                pixel_size *= info["pixel_scale"]
            hidden = sources < 0
            take = np.where(hidden, np.arange(sources.size).reshape(sources.shape), sources)
            height, confidence, f_peak, sigma_mm, reliability_db, aif, beyond, reason = (
                a.reshape(-1, *a.shape[2:])[take] for a in (
                    height, confidence, f_peak, sigma_mm, reliability_db, aif, beyond,
                    reason))
            if precision is not None:
                precision = precision.reshape(-1)[take]
            reliable = reliable.reshape(-1)[take] & ~hidden
            confidence[hidden] = 0.0
            reason[hidden] = REASON["outside_field"]  # not seen by every frame
    beyond = np.where(field & ~reliable, beyond, 0).astype(np.int8)
    meta["beyond_sweep"] = _beyond_sweep(beyond, field, z_mm)
    white = clipped_white(aif)
    if white is not None:
        meta["clipped_white"] = _clipped(white, field, reliable)
        reason[white & (reason > REASON["over_exposed"])] = REASON["over_exposed"]
    shares = reason_shares(reason)
    meta["unreliable_reasons"] = {name: round(share, 4) for name, share in shares.items()}
    if shares:
        log.info("unreliable %.1f %% of the image: %s", 100 * sum(shares.values()),
                 ", ".join(f"{name.replace('_', ' ')} {100 * share:.1f} %"
                           for name, share in shares.items()))
    t_total = time.perf_counter() - t0
    h, w = run.shape
    meta.update({
        "frames": n,
        "image_size_px": [w, h],
        "channels": 1 if len(run.frame_shape) == 2 else run.frame_shape[2],
        "dtype": str(aif.dtype),
        "step_mm": stack.step_mm,
        "z_range_mm": [float(z_mm[0]), float(z_mm[-1])],
        "config": config.to_dict(),
        "prefilter": {"sigma_px": round(sigma, 3), "band_modulation": modulation,
                      "noise_test_gain": round(_noise_gain(config, sigma), 3)},
        "magnification_exponent": (None if run.magnification_k is None
                                   else round(run.magnification_k, 3)),
        "seconds": {"stream": round(stats["t_stream"], 4), "total": round(t_total, 4)},
        "mpixel_per_s": round(n * h * w / 1e6 / t_total, 2),
    })
    log.info("reconstructed %d frames of %dx%d px in %.2f s (%.1f Mpixel/s), coverage %.1f%%",
             n, w, h, t_total, meta["mpixel_per_s"], 100 * reliable.mean())
    return Surface(
        height_mm=height,
        confidence=confidence,
        reliable=reliable,
        f_peak=f_peak,
        sigma_mm=sigma_mm,
        reliability_db=reliability_db,
        aif=aif,
        pixel_size_mm=pixel_size,
        z_mm=z_mm,
        field=field,
        beyond=beyond,
        precision_mm=None if precision is None else precision * np.float32(abs(stack.step_mm)),
        meta=meta,
        reason=reason,
    )


@dataclasses.dataclass
class _Run:
    """What every band of one :func:`reconstruct` shares."""

    stack: FocalStack
    config: FocusConfig
    pool: ThreadPoolExecutor
    alignment: Alignment | None
    sigma: float  # the pre-filter's σ (reference pixels)
    magnification_k: float | None  # the focus's exponent of magnification (aligned sweeps)
    cache: dict  # frames decoded before the main pass, taken by the first band
    means: dict  # every whole frame's mean grey
    shape: tuple[int, int]  # the output grid
    frame_shape: tuple[int, ...]  # the first frame's (every frame's) array shape
    decided: dict  # choices made once from the data (see reconstruct)


def _bands(shape: tuple[int, int], config: FocusConfig) -> list[tuple[int, int, int, int]]:
    """Bands of rows ``(lo, hi, core_lo, core_hi)`` covering a grid of ``shape``: each
    band measures rows ``lo .. hi`` (its core and :data:`BAND_MARGIN_PX` either side)
    and keeps ``core_lo .. core_hi``, at most :attr:`FocusConfig.band_mpixels` a band.
    Cores start on multiples of :data:`BAND_ALIGN_PX` (the coarse levels' blocks line up
    with the whole grid's). One band, the whole grid, when it fits."""
    h, w = shape
    limit = config.band_mpixels * 1e6
    if not limit or h * w <= limit:
        return [(0, h, 0, h)]
    rows = int(limit // w) - 2 * BAND_MARGIN_PX
    rows = max(BAND_MARGIN_PX, rows // BAND_ALIGN_PX * BAND_ALIGN_PX)
    count = -(-h // rows)
    rows = -(-h // count // BAND_ALIGN_PX) * BAND_ALIGN_PX  # even bands
    out = []
    for core_lo in range(0, h, rows):
        core_hi = min(h, core_lo + rows)
        out.append((max(0, core_lo - BAND_MARGIN_PX), min(h, core_hi + BAND_MARGIN_PX),
                    core_lo, core_hi))
    return out


def _beyond_sweep(beyond: np.ndarray, field: np.ndarray, z_mm: np.ndarray) -> dict:
    """Shares of the field sharpest on the lowest / highest frame (``Surface.beyond``:
    clearly peaked there, so the surface lies at or beyond that end of the sweep and is
    not measured), for ``summary.json`` (the ends' z are its ``z_range_mm``); a warning
    names the end to extend when a share reaches :data:`BEYOND_SWEEP_WARN`."""
    n_field = max(int(np.count_nonzero(field)), 1)
    out = {}
    for (key, frame, side), sign, z in zip(BEYOND_SWEEP_ENDS, (-1, 1), (z_mm[0], z_mm[-1])):
        share = np.count_nonzero(beyond == sign) / n_field
        out[key] = round(share, 4)
        if share >= BEYOND_SWEEP_WARN:
            log.warning("%.0f %% of the field is sharpest on the sweep's %s frame (z = %.3f mm): "
                        "that part of the scene lies %s the swept range and is not measured; "
                        "extend the sweep %s z = %.3f mm to measure it", 100 * share, frame,
                        float(z), side, side, float(z))
    return out


def _clipped(mask: np.ndarray, field: np.ndarray, reliable: np.ndarray) -> dict:
    """Shares of the field, and of its unreliable part, clipped white in the all-in-focus
    image (``mask``: :func:`~smdinspect.sff._surface.clipped_white`), for
    ``summary.json``; a warning when the share of the field reaches :data:`CLIPPED_WARN`."""
    in_field = mask & field
    n_field = max(int(np.count_nonzero(field)), 1)
    n_unrel = max(int(np.count_nonzero(field & ~reliable)), 1)
    share = np.count_nonzero(in_field) / n_field
    if share >= CLIPPED_WARN:
        log.warning("%.1f %% of the field is clipped white in its sharpest frame (over-exposed: "
                    "no texture, so no height there); lower the exposure or the lighting",
                    100 * share)
    return {"fraction_of_field": round(float(share), 4),
            "fraction_of_unreliable": round(float(np.count_nonzero(in_field & ~reliable) / n_unrel), 4)}


class _FrameOrderSums:
    """Per-pixel sums over the frames of planes made in the worker threads, added by the
    workers in frame order: the float32 sums are the same whichever thread finishes
    first, and no frame's planes wait in the queue for the main thread.

    Every frame index must pass through :meth:`add` once (with None when its frame
    failed) so that the next frame does not wait for it for ever.
    """

    def __init__(self, n: int) -> None:
        self._done = [threading.Event() for _ in range(n)]
        self.sums: list[np.ndarray] | None = None

    def add(self, i: int, planes: tuple[np.ndarray, ...] | None) -> None:
        try:
            if i > 0:
                self._done[i - 1].wait()
            if planes is not None:
                if self.sums is None:
                    self.sums = [p.copy() for p in planes]
                elif planes[0].shape == self.sums[0].shape:  # else the main thread raises
                    for acc, p in zip(self.sums, planes):
                        np.add(acc, p, out=acc)
        finally:
            self._done[i].set()


def _prefetch(read: Callable[[int], np.ndarray], n: int, pool: ThreadPoolExecutor, *,
              depth: int) -> Callable[[int], np.ndarray]:
    """``read`` for indices asked in ascending order, with the next ``depth`` frames
    already being decoded in ``pool``."""
    futures: dict[int, Future] = {}

    def get(i: int) -> np.ndarray:
        for j in range(i, min(n, i + depth + 1)):
            if j not in futures:
                futures[j] = pool.submit(read, j)
        return futures.pop(i).result()

    return get


def _level(tracker: PeakTracker, z_mm: np.ndarray, config: FocusConfig, *, window_px: int,
           halo_radius_px: int, noise_gain: float = 1.0, own_px: int = 0,
           decided: dict | None = None, grid_factor: int = 1,
           grid_rows: tuple[int, int] | None = None,
           order: Callable[[np.ndarray], np.ndarray] | None = None,
           order_out: dict | None = None):
    """Fit one level's peaks and judge them: (fit, confidence, halo mask, beyond,
    precision in steps or None (see :func:`precision_steps`), failed: uint8, where an
    interior peak fails the confidence cues the reason's code (weak texture: the noise
    test, else peak shape; on an end frame weak texture only), 0 elsewhere).

    ``beyond`` (int8) is −1 / +1 where the curve is sharpest on the first / last frame
    and passes the noise and second-mode tests (clearly textured, falling away from the
    end): the surface is at or beyond that end of the sweep. The halo mask includes the
    heights borrowed from a neighbour (:func:`borrowed_mask`, when the tracker has the
    ``own_px`` window's focus) and, with ``order`` (best frames → suspect mask, a pass
    over the frames), the peaks on a frame that is a blur of its neighbour's
    (:func:`~smdinspect.sff._blur_order.blur_order_suspect`; run only where the blur per frame κ
    reaches the smallest blur the check tries; ``order_out`` gets the figures). The
    fine level's (``grid_factor`` 1) heights use :attr:`FocusConfig.fit_power`
    (:func:`select_curve_power` for "auto").

    ``decided`` holds what is chosen from the data once for every band of a grid
    measured in bands (:func:`_bands`): the first band to need a choice makes it (the
    curve power, each level's blur per frame κ and typical peak width), the others
    take it; without it every choice is this call's own. ``grid_rows`` (first, height):
    the tracker holds rows ``first ..`` of a grid ``height`` rows high (fine level).
    """
    decided = {} if decided is None else decided
    tracker.finish()
    power = FocusOperator(config.operator).curve_power
    fit = fit_peaks(tracker, z_mm, method=config.fit, workers=config.workers, power=power)
    if grid_factor == 1 and config.fit == FitMethod.POWER and config.fit_power is not None:
        # the heights from the curve shape of this sweep; the confidence cues stay on the
        # operator's model, which their thresholds were set on
        if "curve" not in decided:
            if config.fit_power == "auto":
                chosen, scores = select_curve_power(tracker, z_mm, power=power,
                                                    grid_rows=grid_rows)
                decided["curve"] = {
                    "power": round(chosen, 3),
                    "scores": {str(round(q, 3)): round(v, 4) for q, v in scores.items()}}
            else:
                chosen = float(config.fit_power)
                decided["curve"] = {"power": chosen}
            decided["power"] = chosen
        chosen = decided["power"]
        if abs(chosen / power - 1) > 0.05:
            height, interior = fit_peaks(tracker, z_mm, method=config.fit,
                                         workers=config.workers, power=chosen,
                                         heights_only=True)
            np.copyto(fit.height_mm, height, where=fit.interior & interior)
            del height, interior
    tracker.release_curves()  # the fit holds what is needed from here on
    # the random error from the even/odd split, averaged over 3 × 3 windows (of this
    # level's grid): a cue of its own, and the precision reported with the heights
    precision = None
    if fit.split_steps is not None:
        box = max(3, int(round(PRECISION_BOX_WINDOWS * window_px / grid_factor)) | 1)
        precision = precision_steps(fit.split_steps, box_px=box)
    cues = confidence_cues(fit, window_px=window_px, noise_spread_gain=noise_gain,
                           precision=precision if config.precision_check else None,
                           memo=decided.setdefault(f"cues/{grid_factor}", {}))
    confidence = confidence_map(fit, window_px=window_px, cues=cues)
    cues = {key: cues[key] for key in ("noise", "second_mode")}  # the others are spent
    first, last = fit.best_idx == 0, fit.best_idx == len(z_mm) - 1
    halo = np.zeros(tracker.shape, bool)
    kappa = 0.0
    if config.halo_ratio > 0 or order is not None:
        key = f"kappa/{grid_factor}"
        if key not in decided:
            decided[key] = blur_px_per_frame(fit, confidence >= config.min_confidence,
                                             power=power)
        kappa = decided[key]
    if config.halo_ratio > 0:
        frame_pos = np.interp(fit.height_mm, z_mm, np.arange(len(z_mm), dtype=np.float64))
        # a sharp edge whose peak lies on the first or last frame (beyond the sweep)
        # spreads its blur like any other: it may explain its neighbours' peaks
        halo = defocus_halo_mask(fit.f_best, frame_pos,
                                 (confidence >= config.min_confidence) | first | last,
                                 base_radius_px=halo_radius_px, blur_px_per_frame=kappa,
                                 ratio=config.halo_ratio, n_frames=len(z_mm), power=power,
                                 cap_px=decided.get("halo_cap_px", 0) // grid_factor or None)
    own = tracker.own_share()
    if own is not None and own_px:
        # also where the fine peak is unreliable anyway: the coarse level's wider
        # window would borrow the same edge's height for it
        borrowed = borrowed_mask(*own, own_px=own_px, noise_gain=noise_gain)
        tracker.own = None
        halo |= borrowed
    if order is not None:
        # Adjacent frames must differ by at least the smallest blur the check tries for
        # their order to be read (below it, resampling by the alignment and the JPEG
        # blur them as much: flat-target, κ 0.1 px/frame, lost 11 % of its reliable
        # heights, no worse than the rest, to the check).
        judged = kappa >= SIGMAS_PX[0]
        flagged = 0.0
        if judged:
            late = order(fit.best_idx) & fit.interior & ~halo
            was = (confidence >= config.min_confidence) & ~halo
            n_was = int(np.count_nonzero(was))
            n_late = int(np.count_nonzero(late & was))
            flagged = n_late / max(n_was, 1)
            if order_out is not None:
                order_out.update(_flagged=n_late, _judged=n_was)
            log.info("blur-order check: %.2f %% of the reliable peaks lie on a frame that "
                     "is a blur of its neighbour's: unreliable", 100 * flagged)
            halo |= late
        if order_out is not None:
            order_out.update(ratio=config.blur_order_ratio, judged=bool(judged),
                             blur_px_per_frame=round(float(kappa), 3),
                             flagged_of_reliable=round(flagged, 5))
    weak = cues["noise"] < 0.5
    # the confidence cues' verdict, before the halo checks: why a peak failed them
    # (a textured peak on an end frame fails as not interior: its reason is the sweep's
    # end where it is clear (beyond, below), else a halo or its shape)
    failed = np.select([confidence >= config.min_confidence, weak, first | last],
                       [0, REASON["weak_texture"], 0], REASON["peak_shape"]).astype(np.uint8)
    confidence[halo] = 0.0
    clear = ~weak & (cues["second_mode"] >= 0.5) & ~halo
    beyond = (np.where(first & clear, -1, 0) + np.where(last & clear, 1, 0)).astype(np.int8)
    return fit, confidence, halo, beyond, precision, failed


def _coarse_factors(config: FocusConfig, shape) -> list[int]:
    """Block factors of the coarse levels (:attr:`FocusConfig.coarse_factor` to the powers
    1 .. ``coarse_levels``) that fit the frame (at least 8 blocks on its shorter side)."""
    f = config.coarse_factor
    if f <= 1:
        return []
    return [f ** k for k in range(1, config.coarse_levels + 1) if min(shape) >= 8 * f ** k]


#: Largest bias (frame steps) a coarse fill may carry from the slope under its window.
COARSE_BIAS_STEPS = 0.5
#: Share of a second (or further) coarse level's footprint the finer map must have
#: measured before that level may fill the pixel (see ``_CoarseLevel.merge``).
FOOTPRINT_MIN_SHARE = 0.5


class _CoarseLevel:
    """A coarse focus level (:attr:`FocusConfig.coarse_factor`): every frame's focus
    block-averaged by the factor and box-filtered 5 × 5 on the reduced grid, its peaks
    tracked there (1/factor² of the fine level's memory and time)."""

    BOX = 5

    def __init__(self, shape: tuple[int, int], n_frames: int, config: FocusConfig,
                 factor: int) -> None:
        f = self.factor = factor
        self.shape = shape
        self.small = (shape[0] // f, shape[1] // f)
        #: side of the full-resolution footprint one coarse focus value sums over
        self.window_px = config.window_px + self.BOX * f - 1
        self.tracker = PeakTracker(self.small, n_frames, half_width=config.fit_half_width)

    @classmethod
    def reduce(cls, focus: np.ndarray, factor: int) -> np.ndarray:
        """One frame's focus on the reduced grid (block mean, then a BOX × BOX box)."""
        h, w = focus.shape
        small = cv2.resize(focus, (w // factor, h // factor), interpolation=cv2.INTER_AREA)
        return cv2.blur(small, (cls.BOX, cls.BOX), borderType=cv2.BORDER_REFLECT)

    def merge(self, height: np.ndarray, confidence: np.ndarray, halo: np.ndarray,
              field: np.ndarray, z_mm: np.ndarray, config: FocusConfig, *,
              noise_gain: float = 1.0, energy: np.ndarray | None = None,
              precision: np.ndarray | None = None, decided: dict | None = None):
        """Fill the finer levels' unreliable pixels inside ``field`` (except the fine
        level's ``halo`` pixels) from reliable coarse ones; returns (height, confidence,
        the mask of the pixels filled, ``precision`` (steps) with the filled pixels'
        taken from this level).

        With the fine level's ``energy`` (:attr:`PeakTracker.texture_energy`) a pixel is
        filled only where the texture of its coarse footprint is not all to one side:
        the footprint's energy centroid must lie within a quarter of the footprint of
        the pixel. A coarse window reads the height where its texture is; a pixel whose
        footprint has texture only on one side (a textureless region next to a textured
        one) would take the textured side's height, which is not a measurement of it.
        """
        # the noise test scales with the footprint; the halo radius is the footprint's
        fit, conf, _, _, prec, _ = _level(self.tracker, z_mm, config, window_px=self.window_px,
                                          halo_radius_px=-(-(self.window_px + 2) // self.factor),
                                          noise_gain=noise_gain, grid_factor=self.factor,
                                          decided=decided)
        inside = cv2.resize(field.astype(np.float32), self.small[::-1],
                            interpolation=cv2.INTER_AREA) > 0.999
        ok = (conf >= config.min_confidence) & inside
        h_small = fit.coarse_mm if config.fit == FitMethod.ARGMAX else fit.height_mm
        size = self.shape[::-1]
        # bilinear upsampling normalised over the reliable coarse pixels; a
        # full-resolution pixel needs half its interpolation weight on reliable ones
        weight = ok.astype(np.float32)
        support = cv2.resize(weight, size, interpolation=cv2.INTER_LINEAR)
        with np.errstate(divide="ignore", invalid="ignore"):
            h_up = cv2.resize(np.where(ok, h_small, 0).astype(np.float32), size,
                              interpolation=cv2.INTER_LINEAR) / support
            c_up = cv2.resize(np.where(ok, conf, 0).astype(np.float32), size,
                              interpolation=cv2.INTER_LINEAR) / support
        use = (confidence < config.min_confidence) & ~halo & field & (support >= 0.5)
        if energy is not None:
            # a coarse window reads the height under its energy centroid: a footprint
            # whose texture is all to one side reads that side's height
            dx, dy = _energy_offset_px(energy, self.window_px)
            use &= np.hypot(dx, dy) <= self.window_px / 4.0
        # A coarse window reads the energy-weighted mean height of its footprint; with
        # the energy centroid up to a quarter footprint off the pixel, a surface sloping
        # by |∇h| steps per px can be read |∇h|·window/4 off. Fill only where that bound
        # is at most COARSE_BIAS_STEPS (the slope from the reliable coarse heights; where
        # too few coarse neighbours are reliable there is no slope: not filled).
        step = float(np.median(np.abs(np.diff(z_mm)))) if len(z_mm) > 1 else 1.0
        gx, gy, dense = masked_gradient(h_small / np.float32(step * self.factor), ok,
                                        sigma_px=1.0, min_weight=0.3)
        slope = np.where(dense, np.hypot(gx, gy), np.inf).astype(np.float32)
        slope = cv2.resize(slope, size, interpolation=cv2.INTER_NEAREST)
        use &= slope * np.float32(self.window_px / 4.0) <= COARSE_BIAS_STEPS
        if self.factor > config.coarse_factor:
            use &= _footprint_agrees(height, confidence >= config.min_confidence, h_up,
                                     step=step, window_px=self.window_px)
        height = np.where(use, h_up, height).astype(np.float32)
        confidence = np.where(use, c_up, confidence).astype(np.float32)
        if precision is not None and prec is not None:
            p_up = cv2.resize(prec, size, interpolation=cv2.INTER_NEAREST)
            precision = np.where(use, p_up, precision).astype(np.float32)
        return height, confidence, use, precision


def _footprint_agrees(height: np.ndarray, reliable: np.ndarray, coarse: np.ndarray, *,
                      step: float, window_px: int) -> np.ndarray:
    """(H, W) bool: where a coarse level's reading ``coarse`` (mm) is borne out by the
    finer map's ``reliable`` heights over its ``window_px`` footprint.

    A second coarse level's footprint (~88 px) spans whole parts, and its own heights,
    averaged over that footprint, show no curvature within it: under a sphere cap
    narrower than the footprint they read flat, so a slope bound from them passes
    everything while the cap's flanks are filled with the base's height (a randomised
    case: 3 249 pixels off by 1.4–13.5 steps). The finer map (fine level and the
    coarser levels before) resolves the footprint, so a pixel is filled only where at
    least :data:`FOOTPRINT_MIN_SHARE` of the footprint is measured there, those heights
    spread by at most :data:`COARSE_BIAS_STEPS` (σ; a plane sloping under the window by
    the slope bound's limit spreads by about as much) and the reading lies within twice
    that of their mean (a footprint reading another depth than the one measured in it).
    """
    k = (window_px, window_px)
    ok = reliable.astype(np.float32)
    base = float(np.median(height[reliable])) if reliable.any() else 0.0
    h = np.where(reliable, (height - np.float32(base)) / np.float32(step), 0).astype(np.float32)
    share = cv2.boxFilter(ok, -1, k, borderType=cv2.BORDER_REFLECT)
    m1 = cv2.boxFilter(h, -1, k, borderType=cv2.BORDER_REFLECT)
    np.multiply(h, h, out=h)
    m2 = cv2.boxFilter(h, -1, k, borderType=cv2.BORDER_REFLECT)
    del h
    known = share >= FOOTPRINT_MIN_SHARE
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = m1 / share
        spread = np.sqrt(np.maximum(m2 / share - mean * mean, 0))
        reading = (coarse - np.float32(base)) / np.float32(step)
        return known & (spread <= COARSE_BIAS_STEPS) & (
            np.abs(reading - mean) <= 2 * COARSE_BIAS_STEPS)


def _energy_offset_px(energy: np.ndarray, window_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) float32: offset (px) of the ``energy`` centroid over each pixel's
    ``window_px`` square from the pixel (the window's side where it has no energy)."""
    e = energy.astype(np.float64)
    h, w = e.shape
    size = (window_px, window_px)
    box = cv2.boxFilter(e, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    xs = np.arange(w, dtype=np.float64)[None, :]
    ys = np.arange(h, dtype=np.float64)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = cv2.boxFilter(e * xs, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT) / box - xs
        dy = cv2.boxFilter(e * ys, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT) / box - ys
    none = ~(box > 0)
    dx[none] = window_px
    dy[none] = window_px
    return dx.astype(np.float32), dy.astype(np.float32)


def _near_step(height, reliable, *, jump_mm: float, radius_px: int) -> np.ndarray:
    """Pixels within ``radius_px`` of a height step, either side (:func:`step_levels`)."""
    step = np.isfinite(step_levels(height, reliable, jump_mm=jump_mm, span_px=EDGE_SPAN_PX))
    if not step.any():
        return step
    # Euclidean distance to the nearest step pixel (a dilation by a disc, in O(1) a
    # pixel), over the steps' bounding box grown by the radius: a pixel beyond it is
    # farther than the radius from every step, and inside it every step is in the box
    rows, cols = np.flatnonzero(step.any(axis=1)), np.flatnonzero(step.any(axis=0))
    box = (slice(max(0, rows[0] - radius_px), rows[-1] + radius_px + 1),
           slice(max(0, cols[0] - radius_px), cols[-1] + radius_px + 1))
    dist = cv2.distanceTransform((~step[box]).view(np.uint8), cv2.DIST_L2,
                                 cv2.DIST_MASK_PRECISE)
    near = np.zeros_like(step)
    near[box] = dist <= radius_px
    return near


def _mismatch(path, shape, first, ref_shape) -> InputError:
    return InputError(f"frame {path.name} is {_describe(shape)} but {first.name} is "
                      f"{_describe(ref_shape)}; all frames must match")


def _describe(shape: tuple[int, ...]) -> str:
    ch = 1 if len(shape) == 2 else shape[2]
    return f"{shape[1]}x{shape[0]} px with {ch} channel{'s' if ch > 1 else ''}"
