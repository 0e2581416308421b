"""Pixel size and lens distortion from one image of a target of known pitch.

Targets: a checkerboard (OpenCV's ``findChessboardCornersSBWithMeta``, any board size) or a
grid of dots (OpenCV's blob detector, then a lattice fitted to the blobs so that any
part of the grid in view will do). The detected points ``p`` get integer grid indices
``(i, j)``; the model is

    p = c + (q − c)·(1 + k1·ρ²),   q = A·(i, j) + t,   ρ = |q − c| / R

with ``c`` the image centre, ``R`` the half diagonal, ``A`` (2 × 2) the grid step in
pixels and ``k1`` the radial distortion (``k1 < 0`` barrel, ``> 0`` pincushion;
``100·k1`` % is the displacement at the image corner). The pixel size is
``pitch_mm / sqrt(|det A|)``; the residual is what the model leaves.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from enum import Enum

import numpy as np

from ..errors import InputError

__all__ = ["PixelSizeResult", "TargetKind", "detect_target", "pixel_size_from_image"]

log = logging.getLogger(__name__)


class TargetKind(str, Enum):
    """Calibration target patterns."""

    AUTO = "auto"
    CHECKERBOARD = "checkerboard"
    DOTS = "dots"


@dataclass(frozen=True)
class PixelSizeResult:
    """Result of :func:`pixel_size_from_image`.

    Attributes
    ----------
    pixel_size_mm : float
        Object-side size of one pixel (geometric mean of the two grid axes), at the
        image centre.
    pixel_size_x_mm, pixel_size_y_mm : float
        Along the grid's two axes (a large difference means a tilted target or
        non-square pixels).
    grid_angle_deg : float
        Rotation of the grid's first axis from the image's x axis.
    n_points : int
        Detected grid points used.
    residual_rms_px, residual_max_px : float
        What the model with distortion leaves, pixels.
    residual_rms_um : float
        The same in µm on the object.
    affine_residual_rms_px : float
        Residual without the distortion term.
    k1 : float
        Radial distortion coefficient (see the module docstring).
    distortion_corner_px, distortion_corner_percent : float
        Radial displacement at the image corner.
    target : str
        ``"checkerboard"`` or ``"dots"``.
    pitch_mm : float
    image_shape : (int, int)
    """

    pixel_size_mm: float
    pixel_size_x_mm: float
    pixel_size_y_mm: float
    grid_angle_deg: float
    n_points: int
    residual_rms_px: float
    residual_max_px: float
    residual_rms_um: float
    affine_residual_rms_px: float
    k1: float
    distortion_corner_px: float
    distortion_corner_percent: float
    target: str
    pitch_mm: float
    image_shape: tuple[int, int]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["image_shape"] = list(self.image_shape)
        return d

    def summary(self) -> str:
        return (f"pixel size {self.pixel_size_mm * 1000:.3f} µm "
                f"(x {self.pixel_size_x_mm * 1000:.3f}, y {self.pixel_size_y_mm * 1000:.3f} µm) "
                f"from {self.n_points} {self.target} points; residual RMS "
                f"{self.residual_rms_px:.3f} px ({self.residual_rms_um:.2f} µm), "
                f"{self.affine_residual_rms_px:.3f} px without distortion; lens distortion "
                f"k1 {self.k1:+.2e} ({self.distortion_corner_percent:+.3f} % = "
                f"{self.distortion_corner_px:+.2f} px at the corner)")


def _to_u8(image: np.ndarray) -> np.ndarray:
    """Grey uint8 view for the detectors (uint16 and float are scaled to their range)."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY) if img.dtype == np.uint8 else \
            img[..., :3].mean(axis=2)
    if img.ndim != 2:
        raise InputError(f"image must be (H, W) or (H, W, 3); got shape {image.shape}")
    if img.dtype == np.uint8:
        return img
    f = img.astype(np.float64)
    lo, hi = np.percentile(f, [0.5, 99.5])
    if hi <= lo:
        raise InputError("the target image is uniform: no pattern to detect")
    return np.clip((f - lo) / (hi - lo) * 255.0, 0, 255).astype(np.uint8)


def _checkerboard(img: np.ndarray):
    import cv2

    flags = cv2.CALIB_CB_LARGER | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    ok, corners, meta = cv2.findChessboardCornersSBWithMeta(img, (3, 3), flags)
    if not ok or corners is None or meta is None:
        return None
    rows, cols = meta.shape[:2]
    pts = corners.reshape(-1, 2).astype(np.float64)
    if len(pts) != rows * cols:
        return None
    k = np.arange(len(pts))
    idx = np.column_stack([k % cols, k // cols]).astype(np.float64)
    return pts, idx


def _dots(img: np.ndarray):
    import cv2

    best = None
    for color in (0, 255):
        params = cv2.SimpleBlobDetector_Params()
        params.filterByColor = True
        params.blobColor = color
        params.filterByArea = True
        params.minArea = 6.0
        params.maxArea = 0.25 * img.size
        params.filterByCircularity = True
        params.minCircularity = 0.85
        params.filterByConvexity = False
        params.filterByInertia = True
        params.minInertiaRatio = 0.4
        kps = cv2.SimpleBlobDetector_create(params).detect(img)
        if best is None or len(kps) > len(best):
            best = kps
    if best is None or len(best) < 9:
        return None
    pts = np.array([k.pt for k in best], dtype=np.float64)
    idx = _lattice(pts)
    if idx is None:
        return None
    return pts, idx


def _lattice(pts: np.ndarray) -> np.ndarray | None:
    """Integer grid indices of points on a (rotated, scaled) square lattice."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    dist, nn = tree.query(pts, k=5)
    d0 = float(np.median(dist[:, 1]))
    vecs = (pts[nn[:, 1:]] - pts[:, None, :]).reshape(-1, 2)
    lens = np.linalg.norm(vecs, axis=1)
    vecs = vecs[(lens > 0.75 * d0) & (lens < 1.25 * d0)]
    if len(vecs) < 8:
        return None
    ang = np.arctan2(vecs[:, 1], vecs[:, 0])
    theta = math.atan2(np.sin(4 * ang).mean(), np.cos(4 * ang).mean()) / 4.0
    A = d0 * np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    p0 = pts[np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1))]
    # Grow outward from the centre: local fits follow a distorted lattice.
    for radius in (3.0, 6.0, 12.0, 1e9):
        idx = np.round((pts - p0) @ np.linalg.inv(A).T)
        near = np.abs(idx).max(axis=1) <= radius
        if near.sum() < 6:
            continue
        X = np.column_stack([idx[near], np.ones(near.sum())])
        sol, *_ = np.linalg.lstsq(X, pts[near], rcond=None)
        A, p0 = sol[:2].T, sol[2]
    idx = np.round((pts - p0) @ np.linalg.inv(A).T)
    off = (pts - p0) @ np.linalg.inv(A).T - idx
    good = np.abs(off).max(axis=1) < 0.3
    if good.sum() < 9:
        return None
    keys = [tuple(v) for v in idx[good]]
    if len(set(keys)) != len(keys):
        return None
    out = np.full_like(idx, np.nan)
    out[good] = idx[good]
    return out


def _square(pts: np.ndarray, idx: np.ndarray) -> bool:
    """Whether the points form a square lattice (a dot grid read as a checkerboard, or
    squares read as dots, give skewed or unequal axes)."""
    X = np.column_stack([idx, np.ones(len(idx))])
    sol, *_ = np.linalg.lstsq(X, pts, rcond=None)
    a1, a2 = sol[0], sol[1]
    n1, n2 = np.linalg.norm(a1), np.linalg.norm(a2)
    if min(n1, n2) < 3.0:
        return False
    cos = abs(float(np.dot(a1, a2))) / (n1 * n2)
    return abs(n1 / n2 - 1.0) < 0.05 and cos < 0.05


def detect_target(image: np.ndarray, *, target: TargetKind | str = TargetKind.AUTO):
    """Grid points of a calibration target.

    Returns
    -------
    (points, indices, kind)
        ``points`` (N, 2) float64 image (x, y) = (col, row) pixels; ``indices`` (N, 2)
        integer grid coordinates as float64; ``kind`` the target found.

    Raises
    ------
    InputError
        When no grid of at least 9 points is found.
    """
    try:
        kind = TargetKind(target)
    except ValueError:
        raise InputError(f"target must be one of {', '.join(t.value for t in TargetKind)}; "
                         f"got {target!r}") from None
    img = _to_u8(image)
    tries = [TargetKind.CHECKERBOARD, TargetKind.DOTS] if kind is TargetKind.AUTO else [kind]
    for t in tries:
        found = _checkerboard(img) if t is TargetKind.CHECKERBOARD else _dots(img)
        if found is not None:
            pts, idx = found
            ok = np.isfinite(idx).all(axis=1)
            if ok.sum() >= 9 and _square(pts[ok], idx[ok]):
                return pts[ok], idx[ok], t.value
    raise InputError(f"no {'checkerboard or dot grid' if kind is TargetKind.AUTO else kind.value} "
                     f"target found in the image ({img.shape[1]}x{img.shape[0]} px): need at "
                     f"least 3 x 3 grid points in focus")


def _model(params: np.ndarray, idx: np.ndarray, c: np.ndarray, R: float) -> np.ndarray:
    A = params[:4].reshape(2, 2)
    t = params[4:6]
    k1 = params[6] if len(params) > 6 else 0.0
    q = idx @ A.T + t
    rho2 = np.sum((q - c) ** 2, axis=1) / (R * R)
    return c + (q - c) * (1.0 + k1 * rho2)[:, None]


def pixel_size_from_image(image: np.ndarray, *, pitch_mm: float,
                          target: TargetKind | str = TargetKind.AUTO,
                          distortion: bool = True) -> PixelSizeResult:
    """Measure the object-side pixel size (and lens distortion) from a target image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float
        The target, in focus, filling as much of the field as possible.
    pitch_mm : float
        Centre-to-centre distance of the dots, or the checkerboard's square size.
    target : {"auto", "checkerboard", "dots"}
    distortion : bool
        Fit the radial term ``k1`` (else an affine grid only).

    Returns
    -------
    PixelSizeResult

    Examples
    --------
    >>> import numpy as np
    >>> yy, xx = np.mgrid[0:240, 0:320]
    >>> img = np.where(((xx - 10) // 20 + (yy - 10) // 20) % 2 == 0, 220, 30).astype(np.uint8)
    >>> res = pixel_size_from_image(img, pitch_mm=0.5, target="checkerboard")
    >>> round(res.pixel_size_mm, 4)
    0.025
    """
    from scipy.optimize import least_squares

    if not (isinstance(pitch_mm, (int, float)) and math.isfinite(pitch_mm) and pitch_mm > 0):
        raise InputError(f"pitch_mm must be > 0; got {pitch_mm!r}")
    img = np.asarray(image)
    pts, idx, kind = detect_target(img, target=target)
    h, w = img.shape[:2]
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    R = math.hypot(w / 2.0, h / 2.0)
    X = np.column_stack([idx, np.ones(len(idx))])
    sol, *_ = np.linalg.lstsq(X, pts, rcond=None)
    p_aff = np.r_[sol[:2].T.ravel(), sol[2]]
    res_aff = pts - _model(p_aff, idx, c, R)
    aff_rms = float(np.sqrt(np.mean(np.sum(res_aff ** 2, axis=1))))
    params = p_aff
    if distortion and len(pts) >= 12:
        fit = least_squares(lambda q: (_model(q, idx, c, R) - pts).ravel(), np.r_[p_aff, 0.0],
                            x_scale="jac")
        params = fit.x
    res = pts - _model(params, idx, c, R)
    rr = np.sqrt(np.sum(res ** 2, axis=1))
    A = params[:4].reshape(2, 2)
    k1 = float(params[6]) if len(params) > 6 else 0.0
    sx, sy = float(np.linalg.norm(A[:, 0])), float(np.linalg.norm(A[:, 1]))
    step_px = math.sqrt(abs(float(np.linalg.det(A))))
    pixel = pitch_mm / step_px
    rms = float(np.sqrt(np.mean(rr ** 2)))
    return PixelSizeResult(
        pixel_size_mm=pixel, pixel_size_x_mm=pitch_mm / sx, pixel_size_y_mm=pitch_mm / sy,
        grid_angle_deg=math.degrees(math.atan2(A[1, 0], A[0, 0])), n_points=len(pts),
        residual_rms_px=rms, residual_max_px=float(rr.max()), residual_rms_um=rms * pixel * 1e3,
        affine_residual_rms_px=aff_rms, k1=k1, distortion_corner_px=k1 * R,
        distortion_corner_percent=100.0 * k1, target=kind, pitch_mm=float(pitch_mm),
        image_shape=(h, w))
