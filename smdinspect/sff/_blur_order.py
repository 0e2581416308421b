"""The blur-order check: a focus peak must be the sharpest picture of its neighbourhood.

Defocus only blurs. Where the surface is in focus at frame k, its neighbours k − 1 and
k + 1 are blurred copies of frame k there: each is explained as frame k convolved with
a Gaussian, and frame k is not explained as either of them blurred (blur cannot be
undone). A false peak is the other way round. In the wide bars of a barcode whose
sharp frame is the first, the focus rises in the bars' interiors as the bars blur (and
the camera's JPEG leaves its 8 × 8 block steps, strongest where the image is smooth),
and peaks 3–5 frames from the sharp end with amplitudes as large as the bars' own
edges — no amplitude ratio tells it from a surface. But there frame k *is* a blur of
frame k − 1.

For each adjacent pair (i − 1, i), on the grey frames reduced by :data:`FACTOR` (mean
grey normalised, as aligned), the residual energies over a square of ``box_px``

    a = min_σ box((g_i − G_σ ∗ g_{i−1})²)      frame i as a blur of frame i − 1
    c = min_σ box((g_{i−1} − G_σ ∗ g_i)²)      frame i − 1 as a blur of frame i

over σ in :data:`SIGMAS_PX`, and the pair's floor ν (the 10th percentile of min(a, c):
where both explain each other, the residual is the noise's). A pixel whose peak frame
is k is unreliable when frame k is explained as a blur of k − 1 or of k + 1 ``ratio``
times better than the reverse: (a + ν)·ratio < (c + ν) for the pair (k − 1, k), and
alike for (k, k + 1). The check is applied only where adjacent frames differ by at
least the smallest blur it tries (the stack's blur per frame κ, from its sharpest
peaks, ≥ ``SIGMAS_PX[0]``): below that the order is not read from defocus but from
whatever else blurs one frame more than the next (the alignment's resampling, the
JPEG) — on flat-target (κ 0.1 px/frame, 2× magnification change) it flagged 11 % of the
reliable heights, which fitted the flat plate no worse than the others.

Measured (2026-12-02; pcb-oblique, the barcode's isolated reliable heights standing
1–2.6 mm above it, 4 072 px): 79 % flagged at ratio 2 while 2.2 % of all its reliable
pixels are; metal-bore 3.4 % of the reliable pixels (the bore's outer rim, a depth
edge); rendered demo boards (telecentric and ordinary lenses, steps 1–2.5 depths of
field, normal and high noise) 0.2–0.8 % of the heights within 0.5 Δd of the truth.
A second pass over the frames, after the fit, and only where the check is judged: each
pixel's pairs are the ones around its final best frame, so nothing needs tracking while
the focus is streamed (where it is not judged — telecentric boards, fine steps — it
costs nothing; run in the stream, it cost 5–7 ms of the main thread per 1-Mpixel
frame whether judged or not). The pass takes each frame's reduced grey from the stream
when the stream kept it (:data:`~smdinspect.sff._reconstruct.ORDER_CACHE_BYTES`; a grid
measured whole), else decodes and aligns the frame again (in worker threads); it keeps
the reduced grey of one frame and its blurs; about 50 ms per 3-Mpixel frame besides the
decoding.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

__all__ = ["blur_order_suspect", "reduce_frame"]

#: The frames are compared on a grid reduced by this factor (the blur differences the
#: check needs are a pixel and more; finer ones are where it says nothing anyway).
FACTOR = 2
#: Blurs (σ, full-resolution px) tried to explain one frame by its neighbour.
SIGMAS_PX = (1.0, 2.0, 4.0, 8.0)
#: Grey level the reduced frames are scaled to (exposure, flicker).
MEAN_GREY = 128.0


def reduce_frame(image: np.ndarray) -> np.ndarray:
    """(H // FACTOR, W // FACTOR) float32 grey of an (aligned) frame, mean grey
    :data:`MEAN_GREY`."""
    from ._reconstruct import to_gray

    g = to_gray(image)
    h, w = g.shape
    g = cv2.resize(g, (max(1, w // FACTOR), max(1, h // FACTOR)), interpolation=cv2.INTER_AREA)
    mean = float(g.mean())
    if mean > 0:
        g *= np.float32(MEAN_GREY / mean)
    return g


def blur_order_suspect(read_reduced: Callable[[int], np.ndarray], n_frames: int,
                       best_idx: np.ndarray, *, box_px: int, ratio: float,
                       floors: dict | None = None) -> np.ndarray:
    """(H, W) bool: pixels whose best frame k is explained as a blur of frame k − 1 or
    k + 1 ``ratio`` times better than the reverse (see the module doc).

    ``read_reduced(i)`` gives frame i's :func:`reduce_frame` (asked in ascending order);
    ``best_idx`` (H, W) is every pixel's peak frame. ``floors`` (a dict by frame) keeps
    each pair's floor ν: one computed is put in it, one found there is used (the bands
    of one grid share their frames' floors).
    """
    h, w = best_idx.shape
    box = max(3, (int(box_px) // FACTOR) | 1)
    sigmas = [sg / FACTOR for sg in SIGMAS_PX]
    size = (box, box)
    out = np.zeros((h, w), np.uint8)
    prev = prev_blurs = None
    blurs: list[np.ndarray] = []
    d = r = a = c = flag = None
    up = np.empty((h, w), np.uint8)
    here = np.empty((h, w), bool)

    def residual(target, with_blurs, dst):
        """dst = min over the blurs of box((target − blur)²)."""
        for k, b in enumerate(with_blurs):
            cv2.subtract(target, b, dst=d)
            cv2.multiply(d, d, dst=d)
            if k == 0:
                cv2.blur(d, size, dst=dst, borderType=cv2.BORDER_REFLECT)
            else:
                cv2.blur(d, size, dst=r, borderType=cv2.BORDER_REFLECT)
                cv2.min(dst, r, dst=dst)

    def mark(frame: int, judged_flag: np.ndarray) -> None:
        """out |= the flag, upsampled, where the best frame is ``frame``."""
        cv2.resize(judged_flag, (w, h), dst=up, interpolation=cv2.INTER_NEAREST)
        np.equal(best_idx, frame, out=here)
        cv2.bitwise_or(out, up, dst=out, mask=here.view(np.uint8))

    for i in range(n_frames):
        reduced = read_reduced(i)
        if d is None:  # every plane allocated once
            d, r, a, c = (np.empty_like(reduced) for _ in range(4))
            flag = np.empty(reduced.shape, np.uint8)
            blurs = [np.empty_like(reduced) for _ in sigmas]
            prev_blurs = [np.empty_like(reduced) for _ in sigmas]
        judged = prev is not None and min(reduced.shape) >= box
        if judged:
            residual(reduced, prev_blurs, a)   # frame i as a blur of frame i − 1
        for sg, b in zip(sigmas, blurs):
            cv2.GaussianBlur(reduced, (0, 0), sg, dst=b, borderType=cv2.BORDER_REFLECT)
        if judged:
            residual(prev, blurs, c)           # frame i − 1 as a blur of frame i
            low = cv2.min(a, c, dst=d)
            nu = None if floors is None else floors.get(i)
            if nu is None:
                nu = max(float(np.percentile(low[::3, ::3], 10)), 1e-6)
                if floors is not None:
                    floors[i] = nu
            cv2.add(a, nu, dst=a)
            cv2.add(c, nu, dst=c)
            # peaks at frame i − 1: a blur of frame i when (c + ν)·ratio < (a + ν)
            cv2.multiply(c, ratio, dst=r)
            cv2.compare(r, a, cv2.CMP_LT, dst=flag)
            mark(i - 1, flag)
            # peaks at frame i: a blur of frame i − 1 when (a + ν)·ratio < (c + ν)
            cv2.multiply(a, ratio, dst=r)
            cv2.compare(r, c, cv2.CMP_LT, dst=flag)
            mark(i, flag)
        prev = reduced
        blurs, prev_blurs = prev_blurs, blurs
    return out > 0
