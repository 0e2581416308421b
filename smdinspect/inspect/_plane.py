"""The board plane: a robust (RANSAC) plane through the reliable points of the bare board.

Heights in the inspection are measured above this plane (and, per joint, above a local
correction of it), so a tilted board or a stage that is not square to the optical axis
does not show up as solder.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError, RegistrationError

__all__ = ["BoardPlane", "fit_board_plane"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BoardPlane:
    """The plane ``z = a·x + b·y + c`` (world mm) of the board's top surface.

    Attributes
    ----------
    a, b, c : float
        Slopes (mm/mm) and offset (mm).
    inlier_fraction : float
        Fraction of the candidate points within the RANSAC distance of the plane.
    rmse_mm : float
        RMS vertical residual of the inliers.
    n_inliers : int
    """

    a: float
    b: float
    c: float
    inlier_fraction: float
    rmse_mm: float
    n_inliers: int

    @property
    def tilt_deg(self) -> float:
        """Angle between the plane's normal and the z axis."""
        return math.degrees(math.atan(math.hypot(self.a, self.b)))

    def z_mm(self, x_mm, y_mm) -> np.ndarray:
        """Plane height at world ``(x_mm, y_mm)`` (arrays broadcast)."""
        return self.a * np.asarray(x_mm, np.float64) + self.b * np.asarray(y_mm, np.float64) + self.c

    def height_above(self, x_mm, y_mm, z_mm) -> np.ndarray:
        """Vertical height of points above the plane."""
        return np.asarray(z_mm, np.float64) - self.z_mm(x_mm, y_mm)

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "c_mm": self.c, "tilt_deg": self.tilt_deg,
                "inlier_fraction": self.inlier_fraction, "rmse_mm": self.rmse_mm,
                "n_inliers": self.n_inliers}


def fit_board_plane(
    xyz: np.ndarray,
    *,
    distance_mm: float = 0.02,
    iterations: int = 1000,
    max_points: int = 60000,
    seed: int = 0,
) -> BoardPlane:
    """Fit the board plane to points with Open3D's RANSAC, then least squares on inliers.

    Parameters
    ----------
    xyz : (N, 3) float
        Candidate points (x_mm, y_mm, z_mm), e.g. the reliable points of the surface
        outside every component footprint. The bare board must be the largest plane.
    distance_mm : float
        RANSAC inlier distance.
    iterations : int
        RANSAC iterations.
    max_points : int
        Points are randomly subsampled to this many before RANSAC (speed).
    seed : int
        Seeds both the subsampling and Open3D's RANSAC.

    Returns
    -------
    BoardPlane

    Raises
    ------
    RegistrationError
        Fewer than 3 points, or no plane holds at least 10 % of them.
    """
    pts = np.asarray(xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"xyz must have shape (N, 3); got {pts.shape}")
    if not (distance_mm > 0):
        raise InputError(f"distance_mm must be > 0; got {distance_mm!r}")
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) < 50:
        raise RegistrationError(f"too few reliable board points to fit the board plane ({len(pts)})")
    rng = np.random.default_rng(seed)
    sample = pts if len(pts) <= max_points else pts[rng.choice(len(pts), max_points, replace=False)]
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - dependency of the package
        raise ImportError("the board-plane fit needs open3d: pip install open3d") from exc
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    # Open3D's multi-threaded RANSAC draws its samples in a scheduling-dependent order
    # even with a fixed seed (isl-org/Open3D#7270); on one thread it is repeatable and
    # still fast (~30 ms for 60 000 points and 1000 iterations).
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        o3d.utility.random.seed(int(seed))
        model, _ = pcd.segment_plane(distance_threshold=float(distance_mm), ransac_n=3,
                                     num_iterations=int(iterations))
    finally:
        o3d.utility.set_max_threads(threads)
    na, nb, nc, nd = (float(v) for v in model)
    if abs(nc) < 0.5:
        raise RegistrationError(
            f"the dominant plane of the measurement is steep ({math.degrees(math.acos(min(1.0, abs(nc)))):.0f}° "
            "from horizontal); it is not a board seen from above")
    # n·p + d = 0  →  z = -(na x + nb y + nd) / nc; refine by least squares on all inliers.
    a, b, c = -na / nc, -nb / nc, -nd / nc
    for _ in range(2):
        resid = pts[:, 2] - (a * pts[:, 0] + b * pts[:, 1] + c)
        inl = np.abs(resid) <= distance_mm
        if inl.sum() < 3:
            break
        A = np.column_stack([pts[inl, 0], pts[inl, 1], np.ones(int(inl.sum()))])
        a, b, c = (float(v) for v in np.linalg.lstsq(A, pts[inl, 2], rcond=None)[0])
    resid = pts[:, 2] - (a * pts[:, 0] + b * pts[:, 1] + c)
    inl = np.abs(resid) <= distance_mm
    frac = float(inl.mean())
    if frac < 0.1:
        raise RegistrationError(f"no board plane found: only {frac:.0%} of the points lie on one plane")
    rmse = float(np.sqrt(np.mean(resid[inl] ** 2)))
    log.debug("board plane z = %.5f x + %.5f y + %.4f; %.0f%% inliers, rmse %.4f mm",
              a, b, c, 100 * frac, rmse)
    return BoardPlane(a=a, b=b, c=c, inlier_fraction=frac, rmse_mm=rmse, n_inliers=int(inl.sum()))
