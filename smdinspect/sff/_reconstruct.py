"""From a focal stack to a :class:`Surface`, in one streaming pass over the frames."""

from __future__ import annotations

import collections
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import cv2
import numpy as np

from ..errors import InputError
from ..stack import FocalStack
from ._align import Alignment, estimate_alignment
from ._config import FitMethod, FocusConfig
from ._confidence import confidence_map, depth_edge_mask, halo_mask
from ._depth import PeakTracker, fit_peaks
from ._focus import FocusOperator, focus_measure, noise_focus
from ._surface import Surface

__all__ = ["reconstruct", "to_gray"]

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]
#: Every frame is scaled to this mean grey level before its focus measure.
MEAN_GREY = 128.0


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
    of frames (see :class:`smdinspect.sff.PeakTracker`).

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
    if config.align:
        alignment = estimate_alignment(lambda i: to_gray(stack.read_frame(i)), n)
        log.info("aligned %d frames onto frame %d (the most magnified); field %.1f %% of it",
                 n, alignment.reference, 100 * alignment.field.mean())
    first = stack.frames[0].path
    operator = FocusOperator(config.operator)

    def load(i: int):
        image = stack.read_frame(i)
        gray = to_gray(image)
        mean = float(gray.mean())
        # Same mean grey in every frame: exposure drift, flicker and auto-gain change the
        # focus measure, defocus does not change the mean (blur conserves light).
        norm = MEAN_GREY / mean if mean > 0 else 1.0
        if mean > 0:
            gray = gray * np.float32(norm)
        focus = focus_measure(gray, operator=config.operator, window_px=config.window_px,
                              threshold=config.threshold)
        if alignment is not None:
            if image.shape[:2] != alignment.shape:
                raise _mismatch(stack.frames[i].path, image.shape, first, alignment.shape)
            gain = alignment.scale(i) ** operator.magnification_exponent
            if gain != 1.0:
                # The same texture seen less magnified has steeper derivatives: scale the
                # scene's part of the focus, not the sensor noise's (which is per pixel).
                noise = noise_focus(operator.value, config.window_px, config.threshold) \
                    * (alignment.noise_sigma * norm) ** operator.curve_power
                focus -= np.float32(noise)
                focus *= np.float32(gain)
                focus += np.float32(noise)
            focus = alignment.warp(focus, i)
            image = alignment.warp(image, i)
        return image, focus

    tracker: PeakTracker | None = None
    aif = None
    ref_shape = None
    depth = config.workers + 2  # frames in flight; bounds memory
    with ThreadPoolExecutor(max_workers=config.workers, thread_name_prefix="sff") as pool:
        pending: collections.deque = collections.deque()
        next_i = 0
        for i in range(n):
            while next_i < n and len(pending) < depth:
                pending.append(pool.submit(load, next_i))
                next_i += 1
            image, focus = pending.popleft().result()
            if ref_shape is None:
                ref_shape = image.shape
                if min(image.shape[:2]) < config.window_px:
                    raise InputError(
                        f"window_px {config.window_px} is larger than the frames "
                        f"({image.shape[1]}x{image.shape[0]} px)")
                tracker = PeakTracker(image.shape[:2], n, half_width=config.fit_half_width)
                aif = np.zeros_like(image)
            elif image.shape != ref_shape:
                raise _mismatch(stack.frames[i].path, image.shape, first, ref_shape)
            better = tracker.update(i, focus)
            cv2.copyTo(image, better.view(np.uint8), aif)
            if progress is not None:
                progress(i + 1, n)
    t_stream = time.perf_counter() - t0

    tracker.finish()
    fit = fit_peaks(tracker, z_mm, method=config.fit, workers=config.workers,
                    power=operator.curve_power)
    confidence = confidence_map(fit, window_px=config.window_px)
    meta: dict = {}
    field = np.ones(tracker.shape, bool)
    if alignment is not None:
        field = alignment.field
        confidence[~field] = 0.0
        meta["alignment"] = alignment.summary()
    if config.halo_ratio > 0:
        frame_pos = np.interp(fit.height_mm, z_mm, np.arange(n, dtype=np.float64))
        halo = halo_mask(fit.f_best, frame_pos, confidence >= config.min_confidence,
                         radius_px=config.window_px + 2, ratio=config.halo_ratio)
        confidence[halo] = 0.0
    if config.edge_jump_steps > 0:
        edges = depth_edge_mask(fit.height_mm, confidence >= config.min_confidence,
                                jump_mm=config.edge_jump_steps * stack.step_mm,
                                radius_px=config.window_px // 2 + 1)
        confidence[edges] = 0.0
    reliable = confidence >= config.min_confidence
    if config.fit == FitMethod.ARGMAX:
        height = fit.coarse_mm
    else:
        height = fit.height_mm
    t_total = time.perf_counter() - t0
    h, w = tracker.shape
    meta.update({
        "frames": n,
        "image_size_px": [w, h],
        "channels": 1 if len(ref_shape) == 2 else ref_shape[2],
        "dtype": str(aif.dtype),
        "step_mm": stack.step_mm,
        "z_range_mm": [float(z_mm[0]), float(z_mm[-1])],
        "config": config.to_dict(),
        "seconds": {"stream": round(t_stream, 4), "total": round(t_total, 4)},
        "mpixel_per_s": round(n * h * w / 1e6 / t_total, 2),
    })
    log.info("reconstructed %d frames of %dx%d px in %.2f s (%.1f Mpixel/s), coverage %.1f%%",
             n, w, h, t_total, meta["mpixel_per_s"], 100 * reliable.mean())
    return Surface(
        height_mm=height,
        confidence=confidence,
        reliable=reliable,
        f_peak=fit.f_peak,
        sigma_mm=fit.sigma_mm,
        reliability_db=fit.reliability_db,
        aif=aif,
        pixel_size_mm=stack.pixel_size_mm,
        z_mm=z_mm,
        field=field,
        meta=meta,
    )


def _mismatch(path, shape, first, ref_shape) -> InputError:
    return InputError(f"frame {path.name} is {_describe(shape)} but {first.name} is "
                      f"{_describe(ref_shape)}; all frames must match")


def _describe(shape: tuple[int, ...]) -> str:
    ch = 1 if len(shape) == 2 else shape[2]
    return f"{shape[1]}x{shape[0]} px with {ch} channel{'s' if ch > 1 else ''}"
