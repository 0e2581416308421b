"""2D rigid transforms and polygon rasterisation shared by the inspection modules.

Frames: BOARD (mm, origin at the board's lower-left corner, y up), WORLD (mm, the
Surface frame: ``x = col·p``, ``y = (H−1−row)·p``) and image pixels (row, col).
A placement is the 3x3 homogeneous matrix ``T`` with ``WORLD = T · BOARD``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "apply2d",
    "decompose2d",
    "pixel_to_world",
    "polygon_mask",
    "rigid2d",
    "world_to_pixel",
]

_SHIFT = 8  # fixed-point bits of cv2.fillPoly (1/256 px)


def rigid2d(angle_deg: float, tx_mm: float, ty_mm: float) -> np.ndarray:
    """``(3, 3) float64`` rotation by ``angle_deg`` (counter-clockwise, y up) then translation."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, tx_mm], [s, c, ty_mm], [0.0, 0.0, 1.0]], dtype=np.float64)


def decompose2d(T: np.ndarray) -> tuple[float, float, float]:
    """``(angle_deg, tx_mm, ty_mm)`` of a 2D rigid ``(3, 3)`` matrix."""
    T = np.asarray(T, dtype=np.float64)
    return math.degrees(math.atan2(T[1, 0], T[0, 0])), float(T[0, 2]), float(T[1, 2])


def apply2d(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Apply ``(3, 3)`` ``T`` to ``(N, 2)`` points; returns ``(N, 2) float64``."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return xy @ T[:2, :2].T + T[:2, 2]


def world_to_pixel(xy_mm: np.ndarray, *, shape: tuple[int, int], pixel_size_mm: float) -> np.ndarray:
    """World ``(N, 2)`` mm → fractional ``(N, 2)`` (col, row) pixel coordinates (OpenCV order)."""
    xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([xy[:, 0] / pixel_size_mm, shape[0] - 1 - xy[:, 1] / pixel_size_mm])


def pixel_to_world(colrow: np.ndarray, *, shape: tuple[int, int], pixel_size_mm: float) -> np.ndarray:
    """Fractional ``(N, 2)`` (col, row) → world ``(N, 2)`` mm."""
    cr = np.asarray(colrow, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([cr[:, 0] * pixel_size_mm, (shape[0] - 1 - cr[:, 1]) * pixel_size_mm])


def polygon_mask(polygons_px, shape: tuple[int, int]) -> np.ndarray:
    """Boolean ``(H, W)`` mask of pixels whose centres lie inside any of the polygons.

    Parameters
    ----------
    polygons_px : (N, 2) array or list of them
        Vertices as fractional (col, row).
    """
    import cv2

    if isinstance(polygons_px, np.ndarray) and polygons_px.ndim == 2:
        polygons_px = [polygons_px]
    mask = np.zeros(shape, np.uint8)
    h, w = shape
    pts = []
    for p in polygons_px:
        p = np.asarray(p, np.float64).reshape(-1, 2)
        # a polygon wholly outside the image (a part beyond the field) adds nothing, and
        # its far coordinates would overflow OpenCV's fixed point
        if (len(p) < 3 or not np.isfinite(p).all() or p[:, 0].max() < -1 or p[:, 1].max() < -1
                or p[:, 0].min() > w or p[:, 1].min() > h):
            continue
        pts.append(np.round(p * (1 << _SHIFT)).astype(np.int32))
    if pts:
        cv2.fillPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=_SHIFT)
    return mask.astype(bool)


def polygon_area(poly: np.ndarray) -> float:
    """Unsigned area of a simple polygon ``(N, 2)``."""
    p = np.asarray(poly, dtype=np.float64)
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def rect_polygon(cx: float, cy: float, length: float, width: float, angle_deg: float) -> np.ndarray:
    """``(4, 2)`` corners (counter-clockwise) of a rectangle of ``length`` along its local x."""
    a = math.radians(angle_deg)
    ux, uy = math.cos(a), math.sin(a)
    vx, vy = -uy, ux
    hl, hw = length / 2.0, width / 2.0
    return np.array([
        [cx - hl * ux - hw * vx, cy - hl * uy - hw * vy],
        [cx + hl * ux - hw * vx, cy + hl * uy - hw * vy],
        [cx + hl * ux + hw * vx, cy + hl * uy + hw * vy],
        [cx - hl * ux + hw * vx, cy - hl * uy + hw * vy],
    ])


def arc_fillet(s, F: float, L: float, k: float) -> np.ndarray:
    """Height of a concave fillet of constant curvature at ``s`` (0 at the termination's
    end face, 1 at the toe, ``L`` mm away), rising to ``F`` at the face.

    Molten solder at these sizes is shaped by surface tension alone (its capillary
    length, about 2.6 mm, is ten times a chip fillet), so its free surface has constant
    mean curvature: across a chip's fillet, a circular arc from the toe (L, 0) to the
    face (0, F). ``k`` in [0, 1] is its curvature as a share of the largest one that
    meets both the pad and the face at a contact angle of 0 or more (the arc tangent to
    the pad when F < L, to the face when F > L): 0 is a straight wedge, 1 that most
    curved arc.
    """
    s = np.clip(np.asarray(s, np.float64), 0.0, 1.0)
    F, L, k = float(F), float(L), min(max(float(k), 0.0), 1.0)
    if F <= 0.0 or L <= 0.0:
        return np.zeros_like(s)
    if k < 1e-6:
        return F * (1.0 - s)
    c2 = L * L + F * F
    R = c2 / (2.0 * min(F, L)) / k
    h = math.sqrt(max(R * R - c2 / 4.0, 0.0))
    c = math.sqrt(c2)
    cx, cz = L / 2.0 + F / c * h, F / 2.0 + L / c * h   # centre, over the free side
    return np.clip(cz - np.sqrt(np.maximum(R * R - (s * L - cx) ** 2, 0.0)), 0.0, F)

