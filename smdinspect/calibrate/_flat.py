"""Focal-plane tilt and field curvature from a reconstruction of a flat target.

A flat target swept through focus should reconstruct as a constant height. What it
reconstructs as instead (the stage axis not square to the lens, a curved field of best
focus) is a smooth surface over the field. :func:`calibrate_flat` fits it with a
low-order 2D polynomial in normalised image coordinates

    P(u, v) = Σ c_ab · u^a · v^b,  a + b ≤ degree,
    u = (col − cx) / cx,  v = (cy − row) / cy   (cx = (W − 1)/2, cy = (H − 1)/2)

robustly (iterated 3·MAD clipping: textured dirt and edges do not pull it), and
:func:`apply_calibration` subtracts ``P(u, v) − P(0, 0)`` from a later reconstruction:
heights at the field centre keep their value, the tilt and curvature go.

A target's own tilt on the stage cannot be told from the focal plane's: calibrate on a
target that sits where boards sit (the inspection also levels each board on its own).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = ["FocalPlaneCalibration", "apply_calibration", "calibrate_flat"]


def _monomials(degree: int) -> list[tuple[int, int]]:
    return [(a, t - a) for t in range(degree + 1) for a in range(t, -1, -1)]


def _uv(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    cx, cy = max((w - 1) / 2.0, 0.5), max((h - 1) / 2.0, 0.5)
    cols = (np.arange(w) - cx) / cx
    rows = (cy - np.arange(h)) / cy
    return cols, rows


@dataclass(frozen=True)
class FocalPlaneCalibration:
    """A focal-plane correction and what it measured.

    Attributes
    ----------
    degree : int
        Polynomial degree (1: tilt only, 2: tilt + curvature, ...).
    coefficients : tuple of float
        ``c_ab`` in mm, in the order of ``(a, b)`` for total degree 0, 1, ... (a first
        descending): (0,0), (1,0), (0,1), (2,0), (1,1), (0,2), ...
    shape : (int, int)
        Image (H, W) the correction applies to.
    pixel_size_mm : float or None
    step_mm : float or None
        Δd of the calibration sweep.
    tilt_deg, tilt_azimuth_deg : float or None
        Slope of the fitted surface at the field centre, and the image direction in
        which it rises (0: +x, 90: +y up the image); None without a pixel size.
    curvature_sag_mm : float
        Peak-to-valley over the field of the terms above first order.
    raw_rms_mm, residual_rms_mm : float
        RMS of the flat target's heights about their mean, and about the fit.
    coverage : float
        Fraction of the field's pixels that were reliable and used.
    """

    degree: int
    coefficients: tuple[float, ...]
    shape: tuple[int, int]
    pixel_size_mm: float | None
    step_mm: float | None
    tilt_deg: float | None
    tilt_azimuth_deg: float | None
    curvature_sag_mm: float
    raw_rms_mm: float
    residual_rms_mm: float
    coverage: float

    def __post_init__(self) -> None:
        if not isinstance(self.degree, int) or not 1 <= self.degree <= 4:
            raise InputError(f"degree must be an integer in 1..4; got {self.degree!r}")
        n = len(_monomials(self.degree))
        if len(self.coefficients) != n:
            raise InputError(f"a degree-{self.degree} correction has {n} coefficients; got "
                             f"{len(self.coefficients)}")
        if len(self.shape) != 2 or min(self.shape) < 2:
            raise InputError(f"shape must be (H, W) with H, W >= 2; got {self.shape!r}")

    def surface_mm(self) -> np.ndarray:
        """``P(u, v)`` over the image, (H, W) float64 mm."""
        cols, rows = _uv(self.shape)
        u, v = np.meshgrid(cols, rows)
        out = np.zeros(self.shape)
        for (a, b), c in zip(_monomials(self.degree), self.coefficients):
            out += c * u ** a * v ** b
        return out

    def correction_mm(self) -> np.ndarray:
        """What :func:`apply_calibration` subtracts: ``P(u, v) − P(0, 0)``, (H, W) float32."""
        return (self.surface_mm() - self.coefficients[0]).astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        return {"model": "polynomial", "degree": self.degree,
                "monomials_uv": [list(m) for m in _monomials(self.degree)],
                "coefficients_mm": list(self.coefficients), "shape": list(self.shape),
                "pixel_size_mm": self.pixel_size_mm, "step_mm": self.step_mm,
                "tilt_deg": self.tilt_deg, "tilt_azimuth_deg": self.tilt_azimuth_deg,
                "curvature_sag_mm": self.curvature_sag_mm, "raw_rms_mm": self.raw_rms_mm,
                "residual_rms_mm": self.residual_rms_mm, "coverage": self.coverage}

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "calibration") -> "FocalPlaneCalibration":
        try:
            if d.get("model", "polynomial") != "polynomial":
                raise InputError(f"{source}: focal_plane model must be 'polynomial'; got "
                                 f"{d.get('model')!r}")
            return cls(degree=int(d["degree"]),
                       coefficients=tuple(float(c) for c in d["coefficients_mm"]),
                       shape=(int(d["shape"][0]), int(d["shape"][1])),
                       pixel_size_mm=d.get("pixel_size_mm"), step_mm=d.get("step_mm"),
                       tilt_deg=d.get("tilt_deg"), tilt_azimuth_deg=d.get("tilt_azimuth_deg"),
                       curvature_sag_mm=float(d.get("curvature_sag_mm", 0.0)),
                       raw_rms_mm=float(d.get("raw_rms_mm", 0.0)),
                       residual_rms_mm=float(d.get("residual_rms_mm", 0.0)),
                       coverage=float(d.get("coverage", 0.0)))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError(f"{source}: focal_plane: missing or bad field ({exc})") from None

    def summary(self) -> str:
        step = self.step_mm
        dd = (lambda mm: f" = {mm / step:.2f} Δd") if step else (lambda mm: "")
        tilt = (f"tilt {self.tilt_deg:.3f}° towards {self.tilt_azimuth_deg:.0f}°"
                if self.tilt_deg is not None else "tilt (no pixel size)")
        return (f"{tilt}, field curvature sag {self.curvature_sag_mm * 1000:.1f} µm; flat target "
                f"RMS {self.raw_rms_mm * 1000:.1f} µm{dd(self.raw_rms_mm)} → "
                f"{self.residual_rms_mm * 1000:.1f} µm{dd(self.residual_rms_mm)} after the "
                f"degree-{self.degree} correction ({100 * self.coverage:.0f} % of the field used)")


def calibrate_flat(surface, *, degree: int = 2, max_points: int = 200_000,
                   seed: int = 0) -> FocalPlaneCalibration:
    """Fit the focal-plane shape to a reconstruction of a flat target.

    Parameters
    ----------
    surface : smdinspect.sff.Surface
        Reconstruction of a sweep of a flat, textured target.
    degree : int
        1 (tilt) to 4; 2 (tilt + field curvature) by default.
    max_points : int
        Reliable pixels sampled for the fit (a fixed-seed random subset beyond this).

    Returns
    -------
    FocalPlaneCalibration

    Raises
    ------
    InputError
        Fewer reliable pixels than 20 per coefficient, or a bad degree.
    """
    if not isinstance(degree, int) or not 1 <= degree <= 4:
        raise InputError(f"degree must be an integer in 1..4; got {degree!r}")
    h_mm = np.asarray(surface.height_mm, dtype=np.float64)
    shape = h_mm.shape
    ok = np.asarray(surface.reliable, bool) & np.asarray(surface.field, bool) & np.isfinite(h_mm)
    mons = _monomials(degree)
    rows, cols = np.nonzero(ok)
    if len(rows) < 20 * len(mons):
        raise InputError(f"only {len(rows)} reliable pixels in the flat-target reconstruction; "
                         f"need {20 * len(mons)} for a degree-{degree} fit (is the target "
                         f"textured and inside the sweep?)")
    if len(rows) > max_points:
        pick = np.random.default_rng(seed).choice(len(rows), max_points, replace=False)
        rows, cols = rows[pick], cols[pick]
    cu, rv = _uv(shape)
    u, v, z = cu[cols], rv[rows], h_mm[rows, cols]
    X = np.column_stack([u ** a * v ** b for a, b in mons])
    keep = np.ones(len(z), bool)
    for _ in range(8):
        coef, *_ = np.linalg.lstsq(X[keep], z[keep], rcond=None)
        r = z - X @ coef
        mad = 1.4826 * float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        new = np.abs(r) <= max(3.0 * mad, 1e-9)
        if new.sum() < 10 * len(mons) or np.array_equal(new, keep):
            break
        keep = new
    resid = float(np.sqrt(np.mean(r[keep] ** 2)))
    raw = float(np.std(z[keep]))
    pixel = getattr(surface, "pixel_size_mm", None)
    zs = np.asarray(getattr(surface, "z_mm", []), dtype=np.float64)
    step = float(np.median(np.abs(np.diff(zs)))) if zs.size > 1 else None
    cal0 = FocalPlaneCalibration(degree, tuple(float(c) for c in coef), shape, pixel, step,
                                 None, None, 0.0, raw, resid, float(ok.mean()))
    # tilt at the centre: dP/du, dP/dv are the (1,0), (0,1) coefficients
    c10, c01 = coef[1], coef[2]
    tilt = azim = None
    if pixel:
        hx = max((shape[1] - 1) / 2.0, 0.5) * pixel
        hy = max((shape[0] - 1) / 2.0, 0.5) * pixel
        gx, gy = c10 / hx, c01 / hy
        tilt = math.degrees(math.atan(math.hypot(gx, gy)))
        azim = math.degrees(math.atan2(gy, gx)) % 360.0
    higher = [c if a + b >= 2 else 0.0 for (a, b), c in zip(mons, coef)]
    curv = replace(cal0, coefficients=tuple(higher)).surface_mm()
    return replace(cal0, tilt_deg=tilt, tilt_azimuth_deg=azim,
                   curvature_sag_mm=float(curv.max() - curv.min()))


def apply_calibration(surface, calibration: FocalPlaneCalibration):
    """A copy of ``surface`` with the focal-plane correction subtracted from its heights.

    Raises
    ------
    InputError
        When the surface's image size differs from the calibration's.
    """
    shape = tuple(surface.height_mm.shape)
    if shape != tuple(calibration.shape):
        raise InputError(f"the calibration is for {calibration.shape[1]}x{calibration.shape[0]} "
                         f"px images; this reconstruction is {shape[1]}x{shape[0]} px")
    corrected = (surface.height_mm - calibration.correction_mm()).astype(np.float32)
    meta = dict(surface.meta)
    meta["focal_plane_calibration"] = {"degree": calibration.degree,
                                       "tilt_deg": calibration.tilt_deg,
                                       "curvature_sag_mm": calibration.curvature_sag_mm}
    return replace(surface, height_mm=corrected, meta=meta)
