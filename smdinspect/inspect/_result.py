"""Result objects of the inspection: per joint, per component, per board."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._config import InspectConfig, Verdict
from ._plane import BoardPlane
from ._register import RegistrationResult

__all__ = ["ComponentResult", "InspectionResult", "JointResult"]


@dataclass(frozen=True)
class JointResult:
    """Measurement and verdict of one solder joint.

    Heights are above the local board plane in mm; ``x_mm``, ``y_mm`` is the pad centre
    in the BOARD frame, ``world_x_mm``, ``world_y_mm`` where it was found in the image.
    Measured values are NaN when no reliable pixel was available.
    """

    id: str
    component: str
    pad_number: str
    termination: str
    x_mm: float
    y_mm: float
    world_x_mm: float
    world_y_mm: float
    measured_max_mm: float
    measured_mean_mm: float
    uncertainty_mm: float
    mean_uncertainty_mm: float
    volume_mm3: float
    volume_uncertainty_mm3: float
    area_mm2: float
    area_uncertainty_mm2: float
    reliable_fraction: float
    n_pixels: int
    expected_nominal_mm: float
    expected_min_mm: float
    expected_max_mm: float
    verdict: Verdict
    reason: str
    #: Gull-wing only: height of the lead foot above the pad (NaN otherwise / unknown).
    lead_height_mm: float = float("nan")
    #: Height reached in the gap towards the neighbouring pad (NaN when there is none).
    gap_height_mm: float = float("nan")
    #: How ``measured_max_mm`` was obtained: "meniscus", "percentile", "foot" or "side".
    max_method: str = ""
    #: Fraction of the visible pad that looks like the bare finish (colour; NaN: no cue).
    bare_fraction: float = float("nan")
    #: Gull-wing: percentile height over the lead's foot, and over the pad beside the lead.
    foot_height_mm: float = float("nan")
    side_height_mm: float = float("nan")
    #: Chip: end-cap top minus the nominal body top.
    cap_excess_mm: float = float("nan")
    #: Chip meniscus fit: the model's height fraction (of the fitted max) at the highest
    #: reliable pixels; small means the max height is an extrapolation.
    fillet_reach: float = float("nan")
    #: Pad outline in image pixels, (N, 2) (col, row); for pictures.
    polygon_px: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def is_defect(self) -> bool:
        return self.verdict.is_defect

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "component": self.component,
            "pad_number": self.pad_number,
            "termination": self.termination,
            "position_mm": {"x": _r(self.x_mm), "y": _r(self.y_mm)},
            "world_mm": {"x": _r(self.world_x_mm), "y": _r(self.world_y_mm)},
            "measured": {
                "max_height_mm": _r(self.measured_max_mm),
                "mean_height_mm": _r(self.measured_mean_mm),
                "uncertainty_mm": _r(self.uncertainty_mm),
                "mean_uncertainty_mm": _r(self.mean_uncertainty_mm),
                "volume_mm3": _r(self.volume_mm3, 6),
                "volume_uncertainty_mm3": _r(self.volume_uncertainty_mm3, 6),
                "area_mm2": _r(self.area_mm2, 5),
                "area_uncertainty_mm2": _r(self.area_uncertainty_mm2, 5),
                "reliable_fraction": _r(self.reliable_fraction, 3),
                "n_pixels": int(self.n_pixels),
                "max_method": self.max_method,
                "lead_height_mm": _r(self.lead_height_mm),
                "foot_height_mm": _r(self.foot_height_mm),
                "side_height_mm": _r(self.side_height_mm),
                "cap_excess_mm": _r(self.cap_excess_mm),
                "fillet_reach": _r(self.fillet_reach, 3),
                "gap_height_mm": _r(self.gap_height_mm),
                "bare_fraction": _r(self.bare_fraction, 3),
            },
            "expected": {
                "nominal_height_mm": _r(self.expected_nominal_mm),
                "min_height_mm": _r(self.expected_min_mm),
                "max_height_mm": _r(self.expected_max_mm),
            },
            "verdict": self.verdict.value,
            "reason": self.reason,
        }


@dataclass(frozen=True)
class ComponentResult:
    """Body measurements of one component (presence, position, tilt)."""

    ref: str
    kind: str
    package: str
    verdict: Verdict
    reason: str
    #: Fraction of reliable body pixels standing above half the nominal body top.
    present_fraction: float
    #: Median height of the raised body pixels (mm above the board).
    body_height_mm: float
    #: Measured minus nominal body centroid, BOARD frame (mm).
    offset_mm: tuple[float, float]
    #: Tilt of the body top along the component axis (degrees; NaN when not measured).
    tilt_deg: float
    #: Fraction of reliable pixels in the body footprint.
    reliable_fraction: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "ref": self.ref, "kind": self.kind, "package": self.package,
            "verdict": self.verdict.value, "reason": self.reason,
            "present_fraction": _r(self.present_fraction, 3),
            "body_height_mm": _r(self.body_height_mm),
            "offset_mm": [_r(self.offset_mm[0]), _r(self.offset_mm[1])],
            "tilt_deg": _r(self.tilt_deg, 2),
            "reliable_fraction": _r(self.reliable_fraction, 3),
        }


@dataclass(frozen=True, eq=False)
class InspectionResult:
    """Everything :func:`smdinspect.inspect.inspect_surface` found on one board.

    ``exit_code`` is 0 when no joint has a defect (``unreliable`` joints do not fail
    but are reported) and 1 otherwise.
    """

    board: str
    board_source: str
    registration: RegistrationResult
    plane: BoardPlane
    joints: list[JointResult]
    components: list[ComponentResult]
    config: InspectConfig
    pixel_size_mm: float
    shape: tuple[int, int]
    coverage: float
    #: Levelled heights (above the board plane) of the whole image, (H, W) float32.
    height_above_mm: np.ndarray | None = field(default=None, repr=False)
    #: The measured surface (for the pictures of the report).
    surface: Any = field(default=None, repr=False)
    #: The raw numbers the verdict rules read, per joint id
    #: (:class:`~smdinspect.inspect._measure.JointMeasurement`; not in summary.json).
    measurements: dict[str, Any] = field(default_factory=dict, repr=False)
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def defects(self) -> list[JointResult]:
        return [j for j in self.joints if j.is_defect]

    @property
    def unreliable(self) -> list[JointResult]:
        return [j for j in self.joints if j.verdict is Verdict.UNRELIABLE]

    @property
    def passed(self) -> bool:
        return not self.defects

    @property
    def exit_code(self) -> int:
        return 0 if self.passed else 1

    def counts(self) -> dict[str, int]:
        """Number of joints per verdict (every verdict listed, zeros included)."""
        out = {v.value: 0 for v in Verdict}
        for j in self.joints:
            out[j.verdict.value] += 1
        return out

    def joint(self, joint_id: str) -> JointResult:
        for j in self.joints:
            if j.id == joint_id:
                return j
        raise KeyError(joint_id)

    def summary(self) -> str:
        """One line per fact, for the CLI."""
        c = self.counts()
        reg = self.registration
        lines = [
            f"board {self.board}: {len(self.joints)} joints, {len(self.defects)} defective, "
            f"{c['unreliable']} unreliable -> {'PASS' if self.passed else 'FAIL'}",
            f"registration: {reg.method}, rotation {reg.rotation_deg:+.2f} deg, board centre "
            f"offset ({reg.offset_mm[0]:+.3f}, {reg.offset_mm[1]:+.3f}) mm, score "
            f"{reg.score:.2f}, fitness {reg.fitness:.2f}, rmse {reg.rmse_mm * 1000:.1f} µm",
        ]
        for j in self.joints:
            if j.verdict is not Verdict.OK:
                lines.append(f"  {j.id:<10} {j.verdict.value:<18} {j.reason}")
        return "\n".join(lines)


def _r(value: float, ndigits: int = 4) -> float | None:
    """Round for JSON; NaN/inf become null."""
    v = float(value)
    if not np.isfinite(v):
        return None
    return round(v, ndigits)
