"""Frame alignment for ordinary (non-telecentric) lenses.

Magnification changes with focus, and a real stage shifts a little: frames must be
brought onto one pixel grid before their focus measures are compared. Every frame is
registered to its predecessor with OpenCV's ECC (enhanced correlation coefficient)
maximisation under an affine motion (scale, rotation, shear, translation), computed on
a reduced copy for speed; the pairwise warps are chained so that every frame is
resampled onto the grid of the first (lowest-z) frame. Chaining neighbours rather than
matching every frame to one reference keeps the compared images similar in blur.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

__all__ = ["FrameAligner"]

log = logging.getLogger(__name__)

_MAX_SIDE = 640  # ECC runs on an image no larger than this (pixels)


class FrameAligner:
    """Streaming aligner: feed frames in stack order, get them back on frame 0's grid.

    Attributes
    ----------
    transforms : list of (3, 3) float64
        For frame n, the map from reference (frame 0) pixel coordinates (x=col, y=row)
        to frame n's pixel coordinates.
    failures : int
        Pairs where ECC did not converge (the previous warp increment was reused).
    """

    def __init__(self) -> None:
        self.transforms: list[np.ndarray] = []
        self.failures = 0
        self._prev_small: np.ndarray | None = None
        self._last_step = np.eye(3, dtype=np.float32)[:2]
        self._scale = 1.0

    def _small(self, gray: np.ndarray) -> np.ndarray:
        h, w = gray.shape
        self._scale = min(1.0, _MAX_SIDE / max(h, w))
        g = gray.astype(np.float32)
        if self._scale < 1.0:
            g = cv2.resize(g, (round(w * self._scale), round(h * self._scale)),
                           interpolation=cv2.INTER_AREA)
        # normalise contrast so ECC sees comparable images across focus
        return (g - g.mean()) / (g.std() + 1e-6)

    def add(self, gray: np.ndarray) -> np.ndarray:
        """Register ``gray`` (H, W) to the previous frame; return its (3, 3) transform."""
        small = self._small(gray)
        if self._prev_small is None:
            a = np.eye(3)
        else:
            warp = self._last_step.copy()
            criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
            try:
                _, warp = cv2.findTransformECC(self._prev_small, small, warp, cv2.MOTION_AFFINE,
                                               criteria, None, 5)
                self._last_step = warp
            except cv2.error as exc:
                self.failures += 1
                log.warning("frame %d: ECC alignment did not converge (%s); reusing the "
                            "previous step", len(self.transforms), str(exc).splitlines()[-1])
                warp = self._last_step
            s = np.diag([self._scale, self._scale, 1.0])
            step = np.linalg.inv(s) @ np.vstack([warp, [0, 0, 1]]).astype(np.float64) @ s
            a = step @ self.transforms[-1]
        self._prev_small = small
        self.transforms.append(a)
        return a

    @staticmethod
    def warp(image: np.ndarray, transform: np.ndarray) -> np.ndarray:
        """Resample ``image`` (frame n) onto the reference grid with ``transform``."""
        if np.allclose(transform, np.eye(3)):
            return image
        h, w = image.shape[:2]
        return cv2.warpAffine(image, transform[:2], (w, h),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REPLICATE)

    def valid_mask(self, shape: tuple[int, int]) -> np.ndarray:
        """(H, W) bool: reference pixels that every frame actually covered."""
        h, w = shape
        rows, cols = np.indices(shape, dtype=np.float64)
        ok = np.ones(shape, bool)
        for a in self.transforms:
            x = a[0, 0] * cols + a[0, 1] * rows + a[0, 2]
            y = a[1, 0] * cols + a[1, 1] * rows + a[1, 2]
            ok &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        return ok
