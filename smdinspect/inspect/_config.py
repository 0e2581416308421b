"""Settings of the inspection: registration limits and verdict thresholds."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from enum import Enum
from typing import Any

from ..errors import InputError

__all__ = ["FilletModel", "InspectConfig", "Verdict"]


class FilletModel(str, Enum):
    """How a chip joint's max solder height is estimated."""

    #: Fit a concave meniscus ``F·(1 − d/L)²`` to the fillet in front of the end face and
    #: report F, the height where the solder meets the termination.
    MENISCUS = "meniscus"
    #: The ``height_percentile`` percentile of the solder area's heights.
    PERCENTILE = "percentile"


class Verdict(str, Enum):
    """Verdict of one joint; the names match the simulator's truth labels.

    ``ok`` passes, ``unreliable`` neither passes nor fails (the surface under the joint
    was not measured well enough to judge it), every other value is a defect.
    """

    OK = "ok"
    MISSING = "missing"
    INSUFFICIENT = "insufficient"
    EXCESS = "excess"
    BRIDGE = "bridge"
    LIFTED_LEAD = "lifted_lead"
    TOMBSTONE = "tombstone"
    COMPONENT_MISSING = "component_missing"
    COMPONENT_SHIFTED = "component_shifted"
    UNRELIABLE = "unreliable"

    @property
    def is_defect(self) -> bool:
        return self not in (Verdict.OK, Verdict.UNRELIABLE)


def _check_number(name: str, value: Any, lo: float | None = None, hi: float | None = None,
                   *, lo_open: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{name} must be a finite number; got {value!r}")
    if lo is not None and (value <= lo if lo_open else value < lo):
        raise InputError(f"{name} must be {'>' if lo_open else '>='} {lo}; got {value!r}")
    if hi is not None and value > hi:
        raise InputError(f"{name} must be <= {hi}; got {value!r}")


@dataclass(frozen=True)
class InspectConfig:
    """Settings of :func:`smdinspect.inspect.inspect_surface`.

    Every threshold is documented with the rule that uses it in the README ("Verdict rules").
    Heights are above the locally fitted board plane, in mm.

    Parameters
    ----------
    min_reliable_fraction : float
        A joint whose solder area (the pad outside the component body) has a smaller
        fraction of reliable pixels is ``unreliable``: neither passed nor failed.
    height_percentile : float
        The joint's "max" solder height is this percentile of the heights of the
        reliable pixels of the solder area (robust against single outliers), not the
        raw maximum.
    missing_height_mm : float
        Without a colour cue: ``missing`` when the joint's max height is below this
        (nearly no solder).
    bare_missing_fraction : float
        With a colour cue (RGB image, fiducials of a coloured finish): a joint below its
        band is ``missing`` when at least this fraction of its visible pad looks like the
        bare finish, else ``insufficient``.
    bare_dominant_fraction : float
        When at least this fraction of the visible pad looks like the bare finish, the
        joint is ``missing`` whatever heights were read on it: solder that reaches the
        band wets the pad out from the termination or foot, so a pad that is mostly
        bare has no such fillet, and the heights read there are the termination's or
        the lead's edge spread by the focus window.
    fillet_model : FilletModel or str
        ``"meniscus"`` (default) or ``"percentile"``; see :mod:`._measure`.
    min_fillet_reach : float
        Chips, meniscus fit: when the reliable pixels reach less than this fraction of
        the fitted fillet height (the fillet's top lies in the band next to the body
        that shape from focus cannot measure), the fitted max is an extrapolation. It
        may then pass a joint but not fail it: below or above the band, the joint is
        ``unreliable``, unless the pixels' own percentile is above the band (excess).
    side_fillet_ratio : float
        Gull-wing: the side fillets' percentile height divided by this estimates the
        heel fillet height when no solder shows above the lead. A calibration of how
        much of a narrow strip's height shape from focus reads (0.5 for a 5-px window at
        20 µm/px on the synthetic boards; ~0.8 on an ideal height map).
    cap_excess_mm : float
        Chips: ``excess`` also when solder covers the end cap higher than this above the
        body top.
    standing_fraction : float
        Chips: ``tombstone`` when pixels standing higher than the body top +
        max(0.2 mm, 30 % of the body height) cover at least this fraction of the body's
        area (an upright part).
    solder_min_height_mm : float
        A pixel counts as covered by solder (area, volume) when it stands higher than
        this above the board.
    body_margin_mm : float
        Pixels this close to a body (or a gull-wing lead's knee) are not used for
        solder: shape from focus spreads a tall edge over about half the focus window.
        Keep it >= (window_px / 2 + 1) pixels.
    bridge_height_mm : float
        Solder in the gap between two neighbouring pads of a component is a ``bridge``
        when the gap is covered higher than this ...
    bridge_lead_height_mm : float
        The same for the gaps between the feet of a gull-wing part's leads. Those gaps
        lie far from any body, whose blurred edge lifts the heights along a chip's sides
        (good chips' gaps read up to ~45 µm), so the noise sets the limit: over 504 gaps
        of good gull-wing joints on 32 randomised tuning boards through shape from focus
        the highest read 2.7 µm (robust σ 2.2 µm). 25 µm is about 10 σ and half a 50 µm
        focus step; narrow bridges read 50–65 % of their height with a 5-px window
        (a 78 µm, 0.19 mm-wide bridge read 38 µm) and passed the chips' 50 µm.
    bridge_min_fraction : float
        ... along at least this fraction of a path across the gap (the gap is sampled
        in strips running from one pad to the other; a bridge connects them).
    gap_margin_mm : float
        The gap region stays this far from both pads and from the body.
    lifted_lead_gap_mm : float
        Gull-wing: ``lifted_lead`` when the lead foot stands higher than this above its
        nominal height (lead thickness) and no solder reaches it.
    tombstone_tilt_deg : float
        Chip: ``tombstone`` when the plane fitted to the body's top tilts more than this
        along the component's axis.
    component_present_fraction : float
        ``component_missing`` when fewer than this fraction of the reliable pixels of the
        body footprint stand higher than half the body's nominal top height.
    shift_tol_mm : float
        ``component_shifted`` when the measured body centroid is further than
        ``max(shift_tol_mm, shift_tol_fraction * body_width_mm)`` from nominal.
    shift_tol_fraction : float
        See ``shift_tol_mm``.
    focus_noise : float
        Relative noise ε of the focus measure, used to turn the focus-curve width σ_F
        into a height uncertainty: ``u = σ_F² · ε / (√2 · Δd)`` (3-point Gaussian fit).
    plane_distance_mm : float
        RANSAC inlier distance of the board-plane fit.
    low_band_mm : float
        The first board-plane fit sees only reliable points within this of the lowest
        ones (2nd percentile): the board is the lowest large surface, not always the
        largest reliable one.
    local_plane_radius_mm : float
        Board pixels within this distance of a pad's component are used to correct the
        global plane locally (median residual).
    max_rotation_deg : float
        Coarse registration searches rotations in ±this.
    max_offset_mm : float
        Coarse registration searches translations of the board centre in ±this from the
        image centre.
    coarse_pixel_size_mm : float
        Pixel size of the coarse (downsampled) registration search.
    min_match_score : float
        Board not located when the best normalised cross-correlation of the measured
        and reference height maps is below this.
    min_fitness : float
        Board not located when fewer than this fraction of the measured reliable points
        over the board have a reference point within ``icp_distance_mm``.
    max_rmse_mm : float
        Board not located when the inlier RMSE of the fine registration is above this.
    icp_distance_mm : float
        Correspondence distance of the ICP (and of fitness / RMSE).
    fine_features : bool
        Refine the coarse placement with body centroids and fiducials (robust rigid fit).
    icp : bool
        Then run Open3D point-to-plane ICP against the reference surface, kept only when
        it raises the fitness and lowers the RMSE. Off by default: on the synthetic
        boards the ICP drifted 0.2–0.5° (the nominal fillets and body edges of the
        reference differ from real ones, and a height field constrains x, y only at
        edges), while the features reach a few µm.
    seed : int
        Seed of the RANSAC plane fit and the reference point sampling.
    """

    min_reliable_fraction: float = 0.4
    height_percentile: float = 97.0
    missing_height_mm: float = 0.04
    bare_missing_fraction: float = 0.5
    bare_dominant_fraction: float = 0.8
    fillet_model: FilletModel = FilletModel.MENISCUS
    min_fillet_reach: float = 0.4
    cap_excess_mm: float = 0.05
    side_fillet_ratio: float = 0.5
    standing_fraction: float = 0.05
    solder_min_height_mm: float = 0.02
    body_margin_mm: float = 0.08
    bridge_height_mm: float = 0.05
    bridge_lead_height_mm: float = 0.025
    bridge_min_fraction: float = 0.8
    gap_margin_mm: float = 0.03
    lifted_lead_gap_mm: float = 0.06
    tombstone_tilt_deg: float = 8.0
    component_present_fraction: float = 0.5
    shift_tol_mm: float = 0.10
    shift_tol_fraction: float = 0.25
    focus_noise: float = 0.05
    plane_distance_mm: float = 0.02
    low_band_mm: float = 0.12
    local_plane_radius_mm: float = 0.6
    max_rotation_deg: float = 6.0
    max_offset_mm: float = 3.0
    coarse_pixel_size_mm: float = 0.08
    min_match_score: float = 0.5
    min_fitness: float = 0.6
    max_rmse_mm: float = 0.05
    icp_distance_mm: float = 0.08
    fine_features: bool = True
    icp: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "fillet_model", FilletModel(self.fillet_model))
        except ValueError:
            raise InputError(f"fillet_model must be one of "
                             f"{', '.join(m.value for m in FilletModel)}; got {self.fillet_model!r}") from None
        _check_number("min_reliable_fraction", self.min_reliable_fraction, 0.0, 1.0)
        _check_number("height_percentile", self.height_percentile, 50.0, 100.0)
        for name in ("missing_height_mm", "solder_min_height_mm", "body_margin_mm",
                     "gap_margin_mm", "shift_tol_mm", "local_plane_radius_mm"):
            _check_number(name, getattr(self, name), 0.0)
        for name in ("bridge_height_mm", "bridge_lead_height_mm", "lifted_lead_gap_mm",
                     "plane_distance_mm", "low_band_mm",
                     "max_offset_mm", "coarse_pixel_size_mm", "max_rmse_mm",
                     "icp_distance_mm", "focus_noise"):
            _check_number(name, getattr(self, name), 0.0, lo_open=True)
        _check_number("cap_excess_mm", self.cap_excess_mm, 0.0, lo_open=True)
        _check_number("side_fillet_ratio", self.side_fillet_ratio, 0.0, 1.0, lo_open=True)
        for name in ("bridge_min_fraction", "component_present_fraction", "min_match_score",
                     "bare_missing_fraction", "bare_dominant_fraction", "standing_fraction",
                     "min_fillet_reach",
                     "min_fitness", "shift_tol_fraction"):
            _check_number(name, getattr(self, name), 0.0, 1.0)
        _check_number("tombstone_tilt_deg", self.tombstone_tilt_deg, 0.0, 90.0, lo_open=True)
        _check_number("max_rotation_deg", self.max_rotation_deg, 0.0, 45.0)
        for name in ("fine_features", "icp"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"{name} must be true or false; got {getattr(self, name)!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise InputError(f"seed must be an integer; got {self.seed!r}")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of every setting (written into ``report.json``)."""
        d = asdict(self)
        d["fillet_model"] = self.fillet_model.value
        return d

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> "InspectConfig":
        """Build from a dict, rejecting unknown keys with the list of known ones."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(doc) - known)
        if unknown:
            raise InputError(f"unknown inspect setting(s) {', '.join(unknown)}; "
                             f"known: {', '.join(sorted(known))}")
        return cls(**doc)
