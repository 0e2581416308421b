"""A quick texture analysis of a focal stack: contrast, dominant frequency, noise.

The same measurement is made on every stack of the texture study and on the stack that
``--operator auto`` reconstructs, so the study's table is looked up in the space of what
can be *measured* on a stack, not of the renderer's nominal parameters.

Every sampled frame is scaled to mean 1 (as :func:`smdinspect.sff.reconstruct` scales
frames to one mean grey) and cut into ``block_px`` tiles. Per tile and frame: the grey
variance ``v`` and the mean squared central-difference gradient ``e``; the noise
variance ``σ_n²`` (below) is subtracted from both. Each tile keeps the frame where
``e`` is largest (the tile's sharpest view). Then

- **contrast** = median over tiles of ``√v`` (RMS contrast relative to the mean);
- **frequency** = median over textured tiles of ``√(e / v) / 2π`` cycles/px (for a
  sinusoid of frequency f, ``e / v ≈ (2πf)²``), measured through the in-focus blur;
- **noise** = sensor noise σ relative to the mean: Immerkær's estimate (as
  :func:`smdinspect.sff.noise_sigma`) per tile and frame, its median over the frames (a
  tile is sharp, and leaks texture into the estimate, in a few frames only), then over
  the tiles;
- **sparsity** = log10 of the 90th over the 50th percentile of the tiles' contrast
  (near 0 for a uniform texture, large for sparse marks on a blank background).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Iterable

import numpy as np

from ..errors import InputError

__all__ = ["TextureFeatures", "stack_features", "texture_features"]

#: Side (px) of the tiles the analysis is made in.
BLOCK_PX = 16
#: Frames the analysis samples at most, evenly spread over the stack.
MAX_FRAMES = 24
_FLOOR = 1e-6  # smallest contrast / noise reported (log scale stays finite)
_K_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_IMMERKAER_GAIN = math.sqrt(math.pi / 2.0) / 6.0


@dataclass(frozen=True)
class TextureFeatures:
    """What :func:`texture_features` measured on a stack (all relative to the mean grey).

    Attributes
    ----------
    contrast : float
        Median RMS contrast of the tiles at their sharpest frame (0.05 = 5 %).
    freq_cyc_px : float
        Median dominant spatial frequency of the textured tiles, cycles per pixel.
    noise : float
        Sensor noise σ as a fraction of the mean grey.
    sparsity : float
        log10(p90 / p50) of the tiles' contrast.
    frames : int
        Frames analysed.
    """

    contrast: float
    freq_cyc_px: float
    noise: float
    sparsity: float
    frames: int

    def vector(self) -> np.ndarray:
        """``(4,) float64``: log10 contrast, log10 frequency, log10 noise, sparsity."""
        return np.array([math.log10(max(self.contrast, _FLOOR)),
                         math.log10(max(self.freq_cyc_px, _FLOOR)),
                         math.log10(max(self.noise, _FLOOR)), self.sparsity])

    def to_dict(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()}

    def describe(self) -> str:
        return (f"contrast {100 * self.contrast:.2g} %, dominant frequency "
                f"{self.freq_cyc_px:.3g} cyc/px, noise {100 * self.noise:.2g} % of the mean grey, "
                f"sparsity {self.sparsity:.2f}")


def texture_features(frames: Iterable[np.ndarray], *, block_px: int = BLOCK_PX) -> TextureFeatures:
    """Measure contrast, dominant frequency and noise of a stack's frames.

    Parameters
    ----------
    frames : iterable of (H, W) or (H, W, 3) arrays
        Frames of one stack (any order), uint8, uint16 or float; colour is converted to
        luminance.
    block_px : int
        Tile side; frames smaller than two tiles a side are analysed as one tile.

    Returns
    -------
    TextureFeatures
    """
    import cv2

    from ..sff import to_gray

    if isinstance(block_px, bool) or not isinstance(block_px, int) or block_px < 4:
        raise InputError(f"block_px must be an integer >= 4; got {block_px!r}")
    best_e = best_v = None
    noise: list[np.ndarray] = []
    count = 0
    for frame in frames:
        g = to_gray(np.asarray(frame))
        if g.ndim != 2 or min(g.shape) < 8:
            raise InputError(f"frames must be images of at least 8x8 px; got shape {g.shape}")
        g = g.astype(np.float32)
        mean = float(g.mean())
        g *= np.float32(1.0 / mean) if mean > 0 else np.float32(1.0)
        b = block_px if min(g.shape) >= 2 * block_px else min(g.shape)
        hh, ww = (g.shape[0] // b) * b, (g.shape[1] // b) * b
        g = np.ascontiguousarray(g[:hh, :ww])
        small = (ww // b, hh // b)

        def tile_mean(a: np.ndarray) -> np.ndarray:
            return cv2.resize(a, small, interpolation=cv2.INTER_AREA).astype(np.float64)

        m = tile_mean(g)
        v = np.maximum(tile_mean(g * g) - m * m, 0.0)
        gx = cv2.filter2D(g, cv2.CV_32F, np.array([[-0.5, 0.0, 0.5]], np.float32),
                          borderType=cv2.BORDER_REFLECT)
        gy = cv2.filter2D(g, cv2.CV_32F, np.array([[-0.5], [0.0], [0.5]], np.float32),
                          borderType=cv2.BORDER_REFLECT)
        e = tile_mean(gx * gx + gy * gy)
        # Immerkær's estimator (smdinspect.sff.noise_sigma), per tile
        n = _IMMERKAER_GAIN * tile_mean(np.abs(cv2.filter2D(g, cv2.CV_32F, _K_IMMERKAER,
                                                           borderType=cv2.BORDER_REFLECT)))
        if best_e is None:
            best_e, best_v = e, v
        else:
            if e.shape != best_e.shape:
                raise InputError("frames must all have the same size")
            sharper = e > best_e
            best_e = np.where(sharper, e, best_e)
            best_v = np.where(sharper, v, best_v)
        noise.append(n)
        count += 1
    if count == 0:
        raise InputError("texture_features needs at least one frame")
    sigma = float(np.median(np.median(np.array(noise), axis=0)))
    # central differences pass white noise of σ² with variance σ²/2 per axis
    v = np.maximum(best_v - sigma * sigma, 0.0)
    e = np.maximum(best_e - sigma * sigma, 0.0)
    c = np.sqrt(v).ravel()
    textured = v.ravel() > (2.0 * sigma) ** 2 / block_px  # the variance beats its own noise
    ratio = e.ravel()[textured] / v.ravel()[textured] if textured.any() else np.zeros(1)
    freq = float(np.median(np.sqrt(ratio)) / (2.0 * math.pi)) if textured.any() else 0.0
    p50, p90 = np.percentile(c, [50, 90])
    sparsity = math.log10(max(p90, _FLOOR) / max(p50, _FLOOR))
    return TextureFeatures(contrast=max(float(np.median(c)), 0.0), freq_cyc_px=min(freq, 0.5),
                           noise=sigma, sparsity=float(sparsity), frames=count)


def stack_features(stack, *, max_frames: int = MAX_FRAMES) -> TextureFeatures:
    """:func:`texture_features` of up to ``max_frames`` frames evenly spread over a
    :class:`~smdinspect.stack.FocalStack` (or a sequence of frames)."""
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1:
        raise InputError(f"max_frames must be an integer >= 1; got {max_frames!r}")
    n = len(stack)
    picks = sorted({int(round(i)) for i in np.linspace(0, n - 1, min(n, max_frames))})
    read = stack.read_frame if hasattr(stack, "read_frame") else stack.__getitem__
    return texture_features(read(i) for i in picks)

