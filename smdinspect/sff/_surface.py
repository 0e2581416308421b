"""The reconstructed surface: heights, confidence and the all-in-focus image."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as _field
from functools import cached_property
from typing import Any

import numpy as np

__all__ = ["UNRELIABLE_REASONS", "Surface", "clipped_white", "pixel_to_xy_mm",
           "reason_shares", "xy_mm_to_pixel"]

#: Why a pixel is unreliable: :attr:`Surface.reason` holds the code (0: reliable), the
#: first that applies in this order; name and what it means (and what to do about it).
UNRELIABLE_REASONS: dict[int, tuple[str, str]] = {
    1: ("outside_field", "not seen by every frame (the aligned frames' common field)"),
    2: ("below_sweep", "sharpest on the sweep's lowest frame: the surface lies at or "
                       "below the swept range (extend the sweep)"),
    3: ("above_sweep", "sharpest on the sweep's highest frame: the surface lies at or "
                       "above the swept range (extend the sweep)"),
    4: ("over_exposed", "clipped white in its sharpest frame: no texture (lower the "
                        "exposure or the lighting)"),
    5: ("misaligned", "its peak lies on frames whose alignment disagrees with a direct "
                      "registration"),
    6: ("halo", "its focus peak is a defocused neighbour's blurred edge (a halo), a "
                "height borrowed from a neighbour in its window, or a frame that is a blur "
                "of the next"),
    7: ("depth_edge", "next to a height step: its window mixes the step's two depths"),
    8: ("unsupported", "no window around it corroborates its height (an isolated peak)"),
    9: ("weak_texture", "too little texture: its focus curve does not stand above the "
                        "sensor noise's"),
    10: ("peak_shape", "its focus peak is too wide, ambiguous, doubled or badly fitted"),
}


def reason_shares(reason: np.ndarray) -> dict[str, float]:
    """Share of the image (0..1) unreliable for each reason of :data:`UNRELIABLE_REASONS`
    in a plane of their codes: only those that occur, largest first."""
    counts = np.bincount(reason.ravel(), minlength=len(UNRELIABLE_REASONS) + 1)
    shares = {UNRELIABLE_REASONS[code][0]: float(counts[code]) / reason.size
              for code in UNRELIABLE_REASONS if counts[code]}
    return dict(sorted(shares.items(), key=lambda kv: -kv[1]))


def clipped_white(aif: np.ndarray) -> np.ndarray | None:
    """(H, W) bool: pixels clipped at the sensor's white level in every channel of the
    all-in-focus image (over-exposed: a glint or a bright finish flat at full scale has
    no texture, so no focus curve and no height). The AIF takes each pixel from its
    sharpest frame, where a glint is brightest. None for float images (no known white).
    """
    a = np.asarray(aif)
    if not np.issubdtype(a.dtype, np.integer):
        return None
    white = np.iinfo(a.dtype).max
    # one level below full scale: JPEG ringing and the alignment's resampling of a flat
    # white area leave it a level short here and there
    top = a >= white - 1
    return top.all(axis=2) if top.ndim == 3 else top


def pixel_to_xy_mm(rows, cols, *, shape, pixel_size_mm):
    """Image (row, col) → world (x_mm, y_mm).

    World frame: x to the right, y up the image, z (height) towards the camera, so the
    frame is right-handed and a cloud seen from +z looks like the image.
    ``x_mm = col * pixel_size_mm``, ``y_mm = (H - 1 - row) * pixel_size_mm``.
    """
    h = shape[0]
    p = 1.0 if pixel_size_mm is None else float(pixel_size_mm)
    return np.asarray(cols, dtype=np.float64) * p, (h - 1 - np.asarray(rows, dtype=np.float64)) * p


def xy_mm_to_pixel(x_mm, y_mm, *, shape, pixel_size_mm):
    """World (x_mm, y_mm) → fractional image (row, col); inverse of :func:`pixel_to_xy_mm`."""
    h = shape[0]
    p = 1.0 if pixel_size_mm is None else float(pixel_size_mm)
    return h - 1 - np.asarray(y_mm, dtype=np.float64) / p, np.asarray(x_mm, dtype=np.float64) / p


@dataclass(frozen=True, eq=False)
class Surface:
    """Result of :func:`smdinspect.sff.reconstruct`; every array is ``(H, W)``.

    Attributes
    ----------
    height_mm : (H, W) float32
        Height of every pixel above the board (base) plane, in the stack's z frame.
        Defined everywhere; unreliable pixels keep their best guess (see ``reliable``).
    confidence : (H, W) float32
        In [0, 1]; 1 is a strong, narrow, well-fitted focus peak.
    reliable : (H, W) bool
        ``confidence >= threshold`` and the peak was interior and not inverted.
    f_peak : (H, W) float32
        Fitted peak focus value F_peak.
    sigma_mm : (H, W) float32
        Fitted width σ_F of the focus curve in mm (NaN where the fit is inverted).
    reliability_db : (H, W) float32
        Pertuz's reliability R in dB (R < 20 dB: unreliable).
    aif : (H, W) or (H, W, 3), dtype of the frames
        All-in-focus image (RGB for colour stacks).
    pixel_size_mm : float or None
        Object-side pixel size; ``None`` when unknown (x, y then in pixels).
    z_mm : (n_frames,) float64
        Focused-plane heights of the frames used.
    field : (H, W) bool, optional
        Pixels every frame sees (after alignment); all True without alignment.
        Pixels outside it are unreliable.
    beyond : (H, W) int8, optional
        −1 / +1 where the focus curve is clearly textured and sharpest on the first /
        last frame: the surface lies at or beyond that end of the sweep (unreliable as a
        height, a bound for the dense surface); 0 elsewhere. None when unknown.
    reason : (H, W) uint8, optional
        Why each pixel is unreliable, a code of :data:`UNRELIABLE_REASONS` (0 where
        reliable). None when unknown.
    precision_mm : (H, W) float32, optional
        1σ random error of each height from the frames' noise (the even/odd split of its
        focus curve, :func:`smdinspect.sff.precision_steps`); NaN where the curve is too
        narrow to split (steps coarse against the depth of field). None when unknown.
    meta : dict
        Settings and timings, written to ``summary.json``.
    """

    height_mm: np.ndarray
    confidence: np.ndarray
    reliable: np.ndarray
    f_peak: np.ndarray
    sigma_mm: np.ndarray
    reliability_db: np.ndarray
    aif: np.ndarray
    pixel_size_mm: float | None
    z_mm: np.ndarray
    field: np.ndarray | None = None
    beyond: np.ndarray | None = None
    precision_mm: np.ndarray | None = None
    meta: dict[str, Any] = _field(default_factory=dict)
    reason: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.field is None:
            object.__setattr__(self, "field", np.ones(self.height_mm.shape, bool))

    @property
    def shape(self) -> tuple[int, int]:
        return self.height_mm.shape  # type: ignore[return-value]

    @cached_property
    def dense(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The dense surface ``(height_mm, filled, sigma_mm)``, each (H, W).

        Measured heights where reliable; elsewhere (inside :attr:`field`) an edge-aware
        fill guided by the all-in-focus image, with ``filled`` True and its own
        uncertainty ``sigma_mm`` (see :func:`smdinspect.sff._fill.fill_surface`);
        :attr:`beyond` pixels are drawn at their end of the sweep.
        Pixels outside the field are filled too and flagged. Never judged by inspection.
        """
        from ._fill import fill_surface

        step = float(np.median(np.abs(np.diff(self.z_mm)))) if len(self.z_mm) > 1 else 1.0
        return fill_surface(self.height_mm, self.reliable, self.aif,
                            confidence=self.confidence, step_mm=step, beyond=self.beyond,
                            z_range_mm=(float(np.min(self.z_mm)), float(np.max(self.z_mm))))

    def unreliable_reasons(self) -> dict[str, float] | None:
        """:func:`reason_shares` of :attr:`reason`; None when the reasons are unknown."""
        return None if self.reason is None else reason_shares(self.reason)

    @property
    def coverage(self) -> float:
        """Fraction of pixels that are reliable."""
        return float(np.mean(self.reliable))

    def xy_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """``(H, W)`` float64 grids of world x_mm and y_mm for every pixel."""
        rows, cols = np.indices(self.shape)
        return pixel_to_xy_mm(rows, cols, shape=self.shape, pixel_size_mm=self.pixel_size_mm)

    def points(self, *, keep_unreliable: bool = False):
        """World points of the surface.

        Returns
        -------
        xyz : (N, 3) float64
            x_mm, y_mm, z_mm (height).
        rgb : (N, 3) float32
            Colour from the all-in-focus image in [0, 1].
        confidence : (N,) float32
        index : (N, 2) int64
            (row, col) of each point.
        """
        mask = np.ones(self.shape, bool) if keep_unreliable else self.reliable
        rows, cols = np.nonzero(mask)
        x, y = pixel_to_xy_mm(rows, cols, shape=self.shape, pixel_size_mm=self.pixel_size_mm)
        xyz = np.column_stack([x, y, self.height_mm[rows, cols].astype(np.float64)])
        rgb = _unit_rgb(self.aif)[rows, cols]
        return xyz, rgb, self.confidence[rows, cols], np.column_stack([rows, cols])


def _unit_rgb(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        img = img.astype(np.float32) / 65535.0
    else:
        img = np.clip(img.astype(np.float32), 0.0, 1.0)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return img
