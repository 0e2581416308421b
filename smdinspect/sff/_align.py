"""Frame alignment for ordinary (non-telecentric) lenses.

Magnification changes with focus, and a real stage shifts a little: the focus measures
of different frames must be brought onto one pixel grid before they are compared.

:func:`estimate_alignment` runs before the focus pass, on reduced grey copies: every
frame is registered to its predecessor with OpenCV's ECC (enhanced correlation
coefficient) maximisation under an affine motion, and the pairwise warps are chained
(neighbours look alike in blur, far frames do not). The reference grid is then the
**most magnified** frame's: every other frame sees more of the scene, so the field
every frame sees is nearly that whole frame (:attr:`Alignment.field`), and no frame is
stretched past its own resolution.

The focus measure of each frame is computed on the frame's own pixels and only then
resampled onto the reference grid. Resampling an image first would low-pass it by an
amount that depends on the sub-pixel shift (linear interpolation halves the Laplacian
energy at a half-pixel shift), so the unresampled reference frame would look sharpest
and the heights would pile up on it; the focus measure, a window sum, is smooth and
survives resampling.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from dataclasses import field as _field
from typing import Callable

import cv2
import numpy as np

from ._focus import noise_sigma

__all__ = ["Alignment", "estimate_alignment"]

log = logging.getLogger(__name__)

_MAX_SIDE = 640  # ECC runs on an image no larger than this (pixels)
#: A pair whose ECC correlation is below this is a failed registration.
MIN_CORRELATION = 0.3


@dataclass(frozen=True, eq=False)
class Alignment:
    """Where every frame lies on the reference grid.

    Attributes
    ----------
    transforms : list of (3, 3) float64
        For frame n, the map from reference-grid pixel coordinates (x = col, y = row)
        to frame n's pixel coordinates.
    reference : int
        Index of the frame whose grid is the output grid (the most magnified one).
    shape : (H, W)
        Size of the reference grid.
    field : (H, W) bool
        Reference pixels that every frame sees.
    correlation : list of float
        ECC correlation of each frame with its predecessor (1.0 for frame 0).
    failed : list of int
        Frames whose registration failed (ECC did not converge or correlated below
        ``MIN_CORRELATION``); their warp reuses the previous step.
    noise_sigma : float
        Sensor noise σ in the frames' grey units: the median of the per-frame estimates
        (:func:`~smdinspect.sff.noise_sigma`). Texture inflates an estimate and
        JPEG smoothing of defocused frames deflates it; too large is the safe side (the
        magnification correction of :func:`reconstruct` then leaves weak texture
        uncorrected instead of faking a peak in textureless pixels). 0 when unknown.
    """

    transforms: list[np.ndarray]
    reference: int
    shape: tuple[int, int]
    field: np.ndarray
    correlation: list[float] = _field(default_factory=list)
    failed: list[int] = _field(default_factory=list)
    noise_sigma: float = 0.0

    @property
    def ok(self) -> bool:
        return not self.failed

    def scale(self, n: int) -> float:
        """Linear size of a reference pixel in frame n's pixels (≤ 1 by construction)."""
        return float(np.sqrt(abs(np.linalg.det(self.transforms[n][:2, :2]))))

    def warp(self, image: np.ndarray, n: int, *, interpolation: int = cv2.INTER_LINEAR,
             border_value: float = 0.0) -> np.ndarray:
        """Resample frame n's ``image`` (its own grid) onto the reference grid."""
        a = self.transforms[n]
        h, w = self.shape
        if image.shape[:2] == (h, w) and np.allclose(a, np.eye(3), atol=1e-9):
            return image
        return cv2.warpAffine(image, a[:2], (w, h), flags=interpolation | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=border_value)

    def summary(self) -> dict:
        """JSON-able description (for ``summary.json``)."""
        return {
            "ok": self.ok,
            "reference_frame": self.reference,
            "failed_frames": list(self.failed),
            "min_correlation": round(min(self.correlation), 4) if self.correlation else None,
            "scale_range": [round(min(self.scale(n) for n in range(len(self.transforms))), 4),
                            round(max(self.scale(n) for n in range(len(self.transforms))), 4)],
            "field_fraction": round(float(self.field.mean()), 4),
            "magnification_trend": self.magnification_trend(),
            "transforms": [a.tolist() for a in self.transforms],
        }

    def magnification_trend(self) -> float:
        """Relative magnification change from the first frame to the last (frames in
        ascending z), from a least-squares line through the frames' scales: > 0 when
        the image grows with z. On a rig that moves the camera the image shrinks as the
        camera (and z) goes up, so a clear positive trend there means z runs the wrong
        way; a rig that focuses with the lens magnifies as it focuses nearer (up)."""
        scales = np.array([self.scale(n) for n in range(len(self.transforms))])
        if scales.size < 2:
            return 0.0
        slope, mid = np.polyfit(np.arange(scales.size), scales, 1)
        return round(float(slope * (scales.size - 1) / max(np.mean(scales), 1e-9)), 4)


def _small(gray: np.ndarray, scale: float) -> np.ndarray:
    g = gray.astype(np.float32)
    if scale < 1.0:
        h, w = g.shape
        g = cv2.resize(g, (max(8, round(w * scale)), max(8, round(h * scale))),
                       interpolation=cv2.INTER_AREA)
    # normalise contrast so ECC sees comparable images across focus
    return (g - g.mean()) / (g.std() + 1e-6)


def estimate_alignment(read_gray: Callable[[int], np.ndarray], n_frames: int, *,
                       progress: Callable[[int, int], None] | None = None) -> Alignment:
    """Register every frame to its neighbour and choose the reference grid.

    Parameters
    ----------
    read_gray : callable(index) -> (H, W) array
        Returns frame ``index``'s grey image at full size.
    n_frames : int

    Returns
    -------
    Alignment
    """
    steps = [np.eye(3)]  # frame n-1 coords -> frame n coords, full resolution
    correlation = [1.0]
    failed: list[int] = []
    sigmas: list[float] = []
    prev = None
    last = np.eye(3, dtype=np.float32)[:2]
    shape = None
    for n in range(n_frames):
        gray = read_gray(n)
        if shape is None:
            shape = gray.shape[:2]
            scale = min(1.0, _MAX_SIDE / max(shape))
        sigmas.append(noise_sigma(gray))
        small = _small(gray, scale)
        if prev is not None:
            warp = last.copy()
            criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
            try:
                cc, warp = cv2.findTransformECC(prev, small, warp, cv2.MOTION_AFFINE,
                                                criteria, None, 5)
            except cv2.error as exc:
                cc, warp = 0.0, last
                log.debug("frame %d: ECC failed: %s", n, str(exc).splitlines()[-1])
            if cc < MIN_CORRELATION:
                failed.append(n)
                log.warning("frame %d: alignment to frame %d failed (correlation %.2f); "
                            "reusing the previous step", n, n - 1, cc)
                warp = last
            last = warp
            correlation.append(float(cc))
            s = np.diag([scale, scale, 1.0])
            steps.append(np.linalg.inv(s) @ np.vstack([warp, [0, 0, 1]]).astype(np.float64) @ s)
        prev = small
        if progress is not None:
            progress(n + 1, n_frames)
    # chain: frame 0 coords -> frame n coords
    to_frame = [steps[0]]
    for st in steps[1:]:
        to_frame.append(st @ to_frame[-1])
    scales = [np.sqrt(abs(np.linalg.det(a[:2, :2]))) for a in to_frame]
    ref = int(np.argmax(scales))  # the frame in which one frame-0 pixel is largest
    inv_ref = np.linalg.inv(to_frame[ref])
    transforms = [a @ inv_ref for a in to_frame]
    return Alignment(transforms=transforms, reference=ref, shape=shape,
                     field=_field(transforms, shape), correlation=correlation, failed=failed,
                     noise_sigma=float(np.median(sigmas)) if sigmas else 0.0)


def _field(transforms: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: reference pixels that land inside every frame (one row at a time
    would be a loop; a frame's footprint is a convex quadrilateral, drawn with OpenCV)."""
    h, w = shape
    ok = np.ones(shape, np.uint8)
    corners = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
    for a in transforms:
        # frame n's corners in reference coordinates
        inv = np.linalg.inv(a)
        pts = corners @ inv[:2, :2].T + inv[:2, 2]
        poly = np.zeros(shape, np.uint8)
        cv2.fillConvexPoly(poly, np.round(pts * 16).astype(np.int32), 1, lineType=cv2.LINE_8,
                           shift=4)
        ok &= poly
    # stay half a pixel inside the footprints (no interpolation against the border)
    ok = cv2.erode(ok, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return ok.astype(bool)
