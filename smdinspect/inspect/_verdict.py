"""Verdict rules: measurements + the board's nominal geometry → one verdict per joint.

Rules, first match wins (thresholds from :class:`InspectConfig` and the board file;
the measurements are described in :mod:`._measure`):

Component level (decided on the body; every joint of the component gets the verdict).

1. ``tombstone`` (chips): pixels standing far above the body top (top + max(0.2 mm,
   30 % of the body height)) cover at least ``standing_fraction`` of the body's area (an
   upright part), or the plane fitted to the body top tilts more than
   ``tombstone_tilt_deg`` along the component's axis.
2. The remaining body checks are skipped when fewer than ``min_reliable_fraction`` of
   the body's pixels are reliable.
3. ``component_missing``: the raised blob found near the body covers less than
   ``component_present_fraction`` of the body's reliable pixels (presence threshold:
   chips standoff + 0.8 × body height; gull-wing halfway between lead top and body top).
4. ``component_shifted``: the blob's centroid, in the part's own axes, lies outside the
   ellipse of half-axes ``max(shift_tol_mm, shift_tol_fraction × body_length_mm)``
   along the part and ``max(shift_tol_mm, shift_tol_fraction × body_width_mm)`` across.

Joint level

5. ``excess`` (chips): solder over the end cap stands higher than ``cap_excess_mm``
   above the body top (measured on the cap, so judged even when the fillet is not).
6. ``lifted_lead`` (gull-wing; needs ``min_reliable_fraction`` of the lead's foot
   reliable): the lead stands more than ``lifted_lead_gap_mm`` above its nominal top
   (solder thickness + lead thickness) and the solder beside it does not reach the
   lead's underside.
7. ``missing`` by colour: at least ``bare_missing_fraction`` of the visible pad looks
   like the bare finish (the all-in-focus colour does not need focus texture) and no
   reliable height reaches the joint's ``min_height_mm``.
8. ``unreliable``: fewer than ``min_reliable_fraction`` of the solder area's pixels are
   reliable, or no max height could be measured. Never a pass or a fail.
9. ``bridge``: a path across the gap to a neighbouring pad of the same component is
   covered higher than ``bridge_height_mm`` along ``bridge_min_fraction`` of its length.
10. ``missing`` without a colour cue: the max height is below ``missing_height_mm``.
11. ``insufficient``: below the joint's ``min_height_mm``.
12. ``excess``: above the joint's ``max_height_mm``.
    Rules 11 and 12 need a measured max: when a chip's meniscus fit reaches less than
    ``min_fillet_reach`` of its height, the fillet's top was not measured and the max is
    an extrapolation; the joint is then ``unreliable`` instead, unless the solder
    area's own percentile is already above the band (excess seen directly).
13. ``ok`` otherwise.
"""

from __future__ import annotations

import math

from ._config import InspectConfig, Verdict
from ._measure import ComponentMeasurement, JointMeasurement
from ._reference import lead_top_mm
from ._result import ComponentResult, JointResult

__all__ = ["judge_component", "judge_joint"]


def _um(x: float) -> str:
    return f"{x * 1000:.0f} µm" if math.isfinite(x) else "n/a"


def judge_component(comp, m: ComponentMeasurement, config: InspectConfig) -> ComponentResult:
    """Apply the component-level rules (1–4)."""
    verdict, reason = Verdict.OK, "body present, level and in place"
    if comp.kind == "chip" and m.standing_fraction >= config.standing_fraction:
        verdict = Verdict.TOMBSTONE
        reason = (f"part stands upright: {m.standing_fraction:.0%} of its area is far above the "
                  f"body top (>= {config.standing_fraction:.0%})")
    elif comp.kind == "chip" and math.isfinite(m.tilt_deg) and m.tilt_deg > config.tombstone_tilt_deg \
            and m.reliable_fraction >= config.min_reliable_fraction:
        verdict = Verdict.TOMBSTONE
        reason = f"body top tilted {m.tilt_deg:.1f} deg along its axis (> {config.tombstone_tilt_deg} deg)"
    elif m.reliable_fraction < config.min_reliable_fraction:
        verdict = Verdict.UNRELIABLE
        reason = (f"only {m.reliable_fraction:.0%} of the body is reliable "
                  f"(< {config.min_reliable_fraction:.0%}); body checks skipped")
    elif m.present_fraction < config.component_present_fraction:
        verdict = Verdict.COMPONENT_MISSING
        reason = (f"only {m.present_fraction:.0%} of the body footprint stands at body height "
                  f"(< {config.component_present_fraction:.0%})")
    elif all(map(math.isfinite, m.offset_mm)):
        # Component-local offset: along the body (x) and across it (y), each against its
        # own tolerance (fillets and excess solder bias the along-axis centroid).
        a = math.radians(comp.rotation_deg)
        dx = math.cos(a) * m.offset_mm[0] + math.sin(a) * m.offset_mm[1]
        dy = -math.sin(a) * m.offset_mm[0] + math.cos(a) * m.offset_mm[1]
        tol_x = max(config.shift_tol_mm, config.shift_tol_fraction * comp.body_length_mm)
        tol_y = max(config.shift_tol_mm, config.shift_tol_fraction * comp.body_width_mm)
        if (dx / tol_x) ** 2 + (dy / tol_y) ** 2 > 1.0:
            verdict = Verdict.COMPONENT_SHIFTED
            reason = (f"body centroid off by {dx:+.3f} mm along and {dy:+.3f} mm across the part "
                      f"(tolerances {tol_x:.3f}, {tol_y:.3f} mm)")
    return ComponentResult(
        ref=comp.ref, kind=comp.kind, package=comp.package, verdict=verdict, reason=reason,
        present_fraction=m.present_fraction, body_height_mm=m.body_height_mm,
        offset_mm=m.offset_mm, tilt_deg=m.tilt_deg, reliable_fraction=m.reliable_fraction)


def judge_joint(joint, comp, m: JointMeasurement, comp_result: ComponentResult,
                config: InspectConfig) -> JointResult:
    """Apply the rules to one joint (component-level verdicts take precedence)."""
    v, reason = _joint_rule(joint, comp, m, comp_result, config)
    return JointResult(
        id=joint.id, component=joint.component, pad_number=joint.pad_number,
        termination=joint.termination, x_mm=float(joint.center_mm[0]),
        y_mm=float(joint.center_mm[1]), world_x_mm=m.world_xy_mm[0],
        world_y_mm=m.world_xy_mm[1], measured_max_mm=m.max_mm, measured_mean_mm=m.mean_mm,
        uncertainty_mm=m.u_max_mm, mean_uncertainty_mm=m.u_mean_mm, volume_mm3=m.volume_mm3,
        volume_uncertainty_mm3=m.u_volume_mm3, area_mm2=m.area_mm2,
        area_uncertainty_mm2=m.u_area_mm2, reliable_fraction=m.reliable_fraction,
        n_pixels=m.n_pixels, expected_nominal_mm=joint.nominal_height_mm,
        expected_min_mm=joint.min_height_mm, expected_max_mm=joint.max_height_mm,
        verdict=v, reason=reason, lead_height_mm=m.lead_mm, gap_height_mm=m.gap_mm,
        max_method=m.max_method, bare_fraction=m.bare_fraction, foot_height_mm=m.foot_mm,
        side_height_mm=m.side_mm, cap_excess_mm=m.cap_mm, fillet_reach=m.fillet_reach,
        polygon_px=m.polygon_px)


def _joint_rule(joint, comp, m: JointMeasurement, comp_result: ComponentResult,
                config: InspectConfig) -> tuple[Verdict, str]:
    if comp_result.verdict.is_defect:
        return comp_result.verdict, f"{comp.ref}: {comp_result.reason}"
    if comp.kind == "gullwing" and math.isfinite(m.lead_mm) \
            and m.foot_reliable_fraction >= config.min_reliable_fraction:
        nominal = lead_top_mm(comp)
        underside = m.lead_mm - float((comp.lead or {}).get("thickness_mm", 0.0))
        beside = m.side_mm if math.isfinite(m.side_mm) else 0.0
        if m.lead_mm - nominal > config.lifted_lead_gap_mm and beside < underside:
            return Verdict.LIFTED_LEAD, (f"lead foot at {_um(m.lead_mm)} (nominal {_um(nominal)}, "
                                         f"> +{_um(config.lifted_lead_gap_mm)}); solder beside it "
                                         f"reaches only {_um(beside)}, below its underside")
    if comp.kind == "chip" and math.isfinite(m.cap_mm) and m.cap_mm > config.cap_excess_mm:
        return Verdict.EXCESS, (f"solder over the end cap {_um(m.cap_mm)} above the body top "
                                f"(> {_um(config.cap_excess_mm)})")
    bare = math.isfinite(m.bare_fraction) and m.bare_fraction >= config.bare_missing_fraction
    if bare and not (m.max_mm >= joint.min_height_mm):   # NaN (nothing measured) counts
        return Verdict.MISSING, (f"no solder: {m.bare_fraction:.0%} of the visible pad looks bare; "
                                 f"max height {_um(m.max_mm)}, {m.reliable_fraction:.0%} reliable")
    if m.reliable_fraction < config.min_reliable_fraction or not math.isfinite(m.max_mm):
        return Verdict.UNRELIABLE, (f"only {m.reliable_fraction:.0%} of the solder area is reliable "
                                    f"(< {config.min_reliable_fraction:.0%}); not judged")
    if math.isfinite(m.gap_mm) and m.gap_mm > config.bridge_height_mm:
        return Verdict.BRIDGE, (f"solder across the gap to {m.gap_neighbour}: "
                                f"{config.bridge_min_fraction:.0%} of a path stands above "
                                f"{_um(m.gap_mm)} (> {_um(config.bridge_height_mm)})")
    h, u = m.max_mm, m.u_max_mm
    pm = f" ± {_um(u)}" if math.isfinite(u) else ""
    how = f" ({m.max_method})" if m.max_method else ""
    if h < joint.min_height_mm and not math.isfinite(m.bare_fraction) \
            and h < config.missing_height_mm:
        return Verdict.MISSING, f"no solder: max height {_um(h)}{pm}{how} < {_um(config.missing_height_mm)}"
    outside = h < joint.min_height_mm or h > joint.max_height_mm
    if outside and m.fillet_reach < config.min_fillet_reach \
            and not m.observed_mm > joint.max_height_mm:
        return Verdict.UNRELIABLE, (f"fillet top not measured (reliable pixels reach "
                                    f"{m.fillet_reach:.0%} of the fitted height, < "
                                    f"{config.min_fillet_reach:.0%}): extrapolated {_um(h)}{pm}, "
                                    f"not judged")
    if h < joint.min_height_mm:
        return Verdict.INSUFFICIENT, f"max solder height {_um(h)}{pm}{how} < min {_um(joint.min_height_mm)}"
    if h > joint.max_height_mm:
        return Verdict.EXCESS, f"max solder height {_um(h)}{pm}{how} > max {_um(joint.max_height_mm)}"
    return Verdict.OK, (f"max solder height {_um(h)}{pm}{how} within "
                        f"[{_um(joint.min_height_mm)}, {_um(joint.max_height_mm)}]")


