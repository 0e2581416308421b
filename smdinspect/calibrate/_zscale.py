"""z scale and direction from a sweep of a step target of known height.

A stage's z steps are only as true as its lead screw, steps/mm setting and microstepping:
a rig whose real step is 4 % longer than the one it reports measures every height 4 %
low, and one whose z runs the other way than its stack says measures every height
upside down. Neither shows in a flat-target sweep. A step of known height does: a gauge
block, a shim or a feeler gauge on a flat base, both surfaces textured (a matte print or
fine abrasive paper on each), the step inside the field.

:func:`calibrate_z_scale` models the reconstruction as two parallel planes,

    h(u, v) = a + b·u + c·v + H·top(u, v),

(u, v the normalised image coordinates of :mod:`._flat`, top = 1 on the upper surface):
one tilt shared by both surfaces (a block's faces are parallel; the field's own tilt
and curvature are the flat calibration's business), H the measured step in the stack's
nominal z. The pixels are split into the two levels by the midpoint of the two modes of
their heights, then reassigned to the level they fit better and the model refitted,
with 3·MAD clipping (dirt does not pull it), until the split no longer changes; then
the pixels within a focus window of the other level (whose windows mix the two depths)
are left out and the model is fitted once more.

Which level is the block is not told by the heights when z may run the wrong way: it is
the level under the field's centre unless ``top_at`` names a pixel on it. A step that
reads downwards there is a z axis running the wrong way: an error, with the fix, not a
calibration.

The scale ``s = known / H`` (true mm per nominal mm) is what :func:`apply_z_scale`
multiplies the heights by, about the sweep's lowest frame (relative heights are what
scale; the lowest frame keeps its z). Its 1σ uncertainty combines the two levels' random
error (the fit's residual RMS over √(independent windows) on each level) with the
sub-frame bias between two levels (:data:`SUBFRAME_BIAS_STEPS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np

from ..errors import InputError
from ._flat import _uv

__all__ = ["ZScaleCalibration", "apply_z_scale", "calibrate_z_scale"]

#: A level must hold at least this share of the reliable pixels used.
MIN_LEVEL_SHARE = 0.05
#: The step must read at least this many frame steps for a scale worth storing.
MIN_STEP_FRAMES = 3.0
#: 1σ of the sub-frame bias between two levels, in frame steps: a height's error depends
#: a little on where it falls between two frames (``benchmarks/accuracy.py``, terraces:
#: worst peak-to-peak of the mean error over the fractional position 0.022 Δd), and the
#: two surfaces of a step fall at different fractional positions.
SUBFRAME_BIAS_STEPS = 0.01


@dataclass(frozen=True)
class ZScaleCalibration:
    """A z-scale correction and what it measured.

    Attributes
    ----------
    scale : float
        True mm per nominal mm of the stack's z (> 0); heights are multiplied by it.
    known_step_mm : float
        The step target's height, as the user gave it.
    measured_step_mm : float
        The step read in the sweep's nominal z (top level − base level).
    scale_sigma : float
        1σ uncertainty of ``scale`` (absolute): the levels' random error and the
        sub-frame bias between them.
    step_mm : float or None
        Δd of the calibration sweep (nominal).
    top_share : float
        Share of the used pixels on the upper level.
    residual_rms_mm : float
        RMS of the two-plane fit's residuals (inliers).
    coverage : float
        Share of the field's pixels that were reliable.
    """

    scale: float
    known_step_mm: float
    measured_step_mm: float
    scale_sigma: float
    step_mm: float | None
    top_share: float
    residual_rms_mm: float
    coverage: float

    def __post_init__(self) -> None:
        if not (isinstance(self.scale, (int, float)) and math.isfinite(self.scale)
                and 0.2 <= self.scale <= 5.0):
            raise InputError(f"z scale must be a number in 0.2..5; got {self.scale!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"scale": self.scale, "known_step_mm": self.known_step_mm,
                "measured_step_mm": self.measured_step_mm, "scale_sigma": self.scale_sigma,
                "step_mm": self.step_mm, "top_share": self.top_share,
                "residual_rms_mm": self.residual_rms_mm, "coverage": self.coverage}

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, source: str = "calibration") -> "ZScaleCalibration":
        try:
            return cls(scale=float(d["scale"]), known_step_mm=float(d["known_step_mm"]),
                       measured_step_mm=float(d["measured_step_mm"]),
                       scale_sigma=float(d.get("scale_sigma", float("nan"))),
                       step_mm=d.get("step_mm"), top_share=float(d.get("top_share", 0.0)),
                       residual_rms_mm=float(d.get("residual_rms_mm", 0.0)),
                       coverage=float(d.get("coverage", 0.0)))
        except InputError as exc:
            raise InputError(f"{source}: z_scale: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"{source}: z_scale: missing or bad field ({exc})") from None

    def summary(self) -> str:
        dd = f" = {self.measured_step_mm / self.step_mm:.1f} Δd" if self.step_mm else ""
        return (f"step read {self.measured_step_mm * 1000:.1f} µm{dd} against "
                f"{self.known_step_mm * 1000:.1f} µm known: z scale {self.scale:.4f} ± "
                f"{self.scale_sigma:.4f} (heights were "
                f"{100 * (1 / self.scale - 1):+.2f} % off); "
                f"upper level {100 * self.top_share:.0f} % of the {100 * self.coverage:.0f} % "
                f"of the field measured, fit residual {self.residual_rms_mm * 1000:.1f} µm RMS")


def _fit(X: np.ndarray, z: np.ndarray, keep: np.ndarray) -> np.ndarray:
    coef, *_ = np.linalg.lstsq(X[keep], z[keep], rcond=None)
    return coef


def _on_upper(coef: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """True where a height fits the upper plane (base + H) better than the base plane."""
    base = coef[0] + coef[1] * u + coef[2] * v
    return np.abs(z - base - coef[3]) < np.abs(z - base)


def calibrate_z_scale(surface, *, step_height_mm: float, top_at: tuple[float, float] | None = None,
                      max_points: int = 200_000, seed: int = 0) -> ZScaleCalibration:
    """Measure a step target of known height in a reconstruction; see the module doc.

    Parameters
    ----------
    surface : smdinspect.sff.Surface
        Reconstruction of a sweep of the step target.
    step_height_mm : float
        The step's known height (> 0).
    top_at : (x, y) pixel, optional
        A pixel on the upper surface; by default the level under the field's centre is.

    Raises
    ------
    InputError
        Bad height, too few reliable pixels, one level only, a step under
        :data:`MIN_STEP_FRAMES` frame steps, or a step that reads downwards (z runs the
        wrong way).
    """
    if not (isinstance(step_height_mm, (int, float)) and math.isfinite(step_height_mm)
            and step_height_mm > 0):
        raise InputError(f"--step-height-mm must be a positive number; got {step_height_mm!r}")
    h_mm = np.asarray(surface.height_mm, dtype=np.float64)
    shape = h_mm.shape
    ok = np.asarray(surface.reliable, bool) & np.asarray(surface.field, bool) & np.isfinite(h_mm)
    rows, cols = np.nonzero(ok)
    if len(rows) < 400:
        raise InputError(f"only {len(rows)} reliable pixels in the step-target reconstruction; "
                         "need 400 (are both surfaces textured and inside the sweep?)")
    n_all = len(rows)
    if top_at is not None:
        tx, ty = top_at
        if not (0 <= tx < shape[1] and 0 <= ty < shape[0]):
            raise InputError(f"--top-at {tx:g},{ty:g} lies outside the {shape[1]}x{shape[0]} px "
                             "image")
        centre = (float(ty), float(tx))
    else:
        centre = ((shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0)
    if len(rows) > max_points:
        pick = np.random.default_rng(seed).choice(len(rows), max_points, replace=False)
        rows, cols = rows[pick], cols[pick]
    cu, rv = _uv(shape)
    u, v, z = cu[cols], rv[rows], h_mm[rows, cols]
    zs = np.asarray(getattr(surface, "z_mm", []), dtype=np.float64)
    step = float(np.median(np.abs(np.diff(zs)))) if zs.size > 1 else None

    # first split: the midpoint of the two modes (the histogram's two highest peaks
    # separated by at least MIN_STEP_FRAMES steps), then refine by the fit
    lo, hi = np.percentile(z, [1, 99])
    if step and hi - lo < MIN_STEP_FRAMES * step:
        raise InputError(f"the reliable heights span only {(hi - lo) * 1000:.0f} µm "
                         f"({(hi - lo) / step:.1f} frame steps): no step of at least "
                         f"{MIN_STEP_FRAMES:g} steps in the field")
    counts, edges = np.histogram(z, bins=64, range=(lo, hi))
    first = int(np.argmax(counts))
    mids = 0.5 * (edges[:-1] + edges[1:])
    sep = MIN_STEP_FRAMES * step if step else 0.25 * (hi - lo)
    far = np.abs(mids - mids[first]) >= sep
    if not far.any() or counts[far].max() == 0:
        raise InputError("the heights show one level only: is the step inside the field and "
                         "are both of its surfaces textured?")
    second = int(np.flatnonzero(far)[np.argmax(counts[far])])
    upper = z > 0.5 * (mids[first] + mids[second])
    keep = np.ones(len(z), bool)
    X = np.column_stack([np.ones_like(u), u, v, np.zeros_like(u)])
    for _ in range(20):
        X[:, 3] = upper
        coef = _fit(X, z, keep)
        # each pixel to the level it fits better, outliers (3 MAD) out
        new_upper = _on_upper(coef, u, v, z)
        X[:, 3] = new_upper
        r = z - X @ coef
        mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        new_keep = np.abs(r) <= max(3.0 * mad, 1e-9)
        if np.array_equal(new_upper, upper) and np.array_equal(new_keep, keep):
            break
        upper, keep = new_upper, new_keep
    # A focus window straddling the step's edge mixes the two depths: within a window
    # of the other level the heights lean towards it (by less than the clipping sees).
    # Those pixels are left out of the final fit.
    window = int(((getattr(surface, "meta", None) or {}).get("config") or {}).get("window_px", 9))
    full = np.zeros(shape, np.int8)  # +1 upper level, -1 base, 0 neither (all reliable pixels)
    ar, ac = np.nonzero(ok)
    full[ar, ac] = np.where(_on_upper(coef, cu[ac], rv[ar], h_mm[ar, ac]), 1, -1)
    mixed = np.zeros(shape, bool)
    kernel = np.ones((2 * window + 1, 2 * window + 1), np.uint8)
    for side in (1, -1):
        other = cv2.dilate((full == -side).astype(np.uint8), kernel).astype(bool)
        mixed |= (full == side) & other
    keep &= ~mixed[rows, cols]
    X[:, 3] = upper
    coef = _fit(X, z, keep)
    r = (z - X @ coef)[keep]
    share_up = float(np.mean(upper[keep]))
    if min(share_up, 1 - share_up) < MIN_LEVEL_SHARE:
        raise InputError(f"one level holds only {100 * min(share_up, 1 - share_up):.1f} % of the "
                         f"reliable pixels (need {100 * MIN_LEVEL_SHARE:g} %): put the step's "
                         "edge across the field, with both surfaces textured")
    # which level is the block: the one at the named pixel (default the field's centre)
    closest = np.argsort((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2)[:50]
    top_is_upper = bool(np.mean(upper[closest]) >= 0.5)
    measured = float(coef[3]) if top_is_upper else -float(coef[3])
    where = "the pixel --top-at names" if top_at is not None else "the field's centre"
    if measured < 0:
        hint = ("check that --top-at is on the block" if top_at is not None else
                "if the block is not under the field's centre, say where it is with --top-at X,Y")
        raise InputError(
            f"the level at {where} reads {abs(measured) * 1000:.1f} µm BELOW the other: the "
            "stack's z runs the wrong way (every height would be upside down). Flip the sign "
            f"of --step-mm (or the rig's z direction) and calibrate again; {hint}")
    if step and measured < MIN_STEP_FRAMES * step:
        raise InputError(f"the step reads {measured * 1000:.1f} µm, under {MIN_STEP_FRAMES:g} "
                         f"frame steps ({MIN_STEP_FRAMES * step * 1000:.0f} µm): too small to "
                         "scale z by; use a taller step")
    scale = float(step_height_mm) / measured
    if not 0.5 <= scale <= 2.0:
        raise InputError(f"the step reads {measured * 1000:.1f} µm against {step_height_mm * 1000:.1f} "
                         f"µm known: a scale of {scale:.3g} is no stage error (is "
                         "--step-height-mm in mm, and is the block's edge inside the field?)")
    # random error of H: the residual RMS over √(independent windows) on each level
    per_px = n_all / len(z)  # pixels each sampled point stands for
    n_up = max(float(np.sum(upper[keep])) * per_px / window ** 2, 1.0)
    n_lo = max(float(np.sum(~upper[keep])) * per_px / window ** 2, 1.0)
    rms = float(np.sqrt(np.mean(r ** 2)))
    sigma_h = math.hypot(rms * math.sqrt(1 / n_up + 1 / n_lo),
                         SUBFRAME_BIAS_STEPS * (step or 0.0))
    return ZScaleCalibration(
        scale=scale, known_step_mm=float(step_height_mm), measured_step_mm=measured,
        scale_sigma=scale * sigma_h / measured, step_mm=step,
        top_share=share_up if top_is_upper else 1 - share_up, residual_rms_mm=rms,
        coverage=float(ok.sum() / max(np.asarray(surface.field, bool).sum(), 1)))


def apply_z_scale(surface, calibration: ZScaleCalibration):
    """A copy of ``surface`` with its z scaled: heights (and the frames' z) about the
    sweep's lowest frame, the widths and random errors by the scale."""
    s = float(calibration.scale)
    zs = np.asarray(surface.z_mm, dtype=np.float64)
    z0 = float(zs.min()) if zs.size else 0.0
    f32 = np.float32
    height = ((np.asarray(surface.height_mm, np.float64) - z0) * s + z0).astype(f32)
    meta = dict(surface.meta)
    meta["z_scale_calibration"] = {"scale": s, "about_z_mm": z0,
                                   "known_step_mm": calibration.known_step_mm}
    # what summary.json states about the sweep, in the corrected z
    if isinstance(meta.get("z_range_mm"), (list, tuple)) and len(meta["z_range_mm"]) == 2:
        meta["z_range_mm"] = [float((z - z0) * s + z0) for z in meta["z_range_mm"]]
    if isinstance(meta.get("step_mm"), (int, float)):
        meta["step_mm"] = float(meta["step_mm"]) * s
    precision = None if surface.precision_mm is None else \
        (surface.precision_mm * f32(s)).astype(f32)
    return replace(surface, height_mm=height, z_mm=(zs - z0) * s + z0,
                   sigma_mm=(surface.sigma_mm * f32(s)).astype(f32), precision_mm=precision,
                   meta=meta)
