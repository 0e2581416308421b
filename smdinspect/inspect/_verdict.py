"""Verdict rules: measurements + the board's nominal geometry → one verdict per joint.

Rules, first match wins (thresholds from :class:`InspectConfig` and the board file;
the measurements are described in :mod:`._measure`):

Component level (decided on the body; every joint of the component gets the verdict).

0. ``unreliable``: less than :data:`MIN_IN_FIELD` of the body or of a pad lies inside
   the measured field (the image, and with ``--align`` the field every frame covers).
   A part cut by the field edge is never called shifted or missing; its joints are
   ``unreliable`` too.
1. ``tombstone`` (chips): pixels standing far above the body top (top + max(0.2 mm,
   30 % of the body height)) cover at least ``standing_fraction`` of the body's area (an
   upright part), or the plane fitted to the body between its terminations (solder
   over an end cap never reaches there) tilts more than ``tombstone_tilt_deg`` along
   the component's axis: any tilt from a few degrees to upright.
2. The remaining body checks are skipped when fewer than ``min_reliable_fraction`` of
   the body's pixels are reliable — except rule 3 when :data:`MIN_EVIDENCE_PIXELS` of
   them are: inside a body's footprint only its top can be seen, so reliable pixels
   there at board level are the board under a missing part (a bare solder mask, mostly
   unreliable).
3. ``component_missing``: the raised blob found near the body covers less than
   ``component_present_fraction`` of the body's reliable pixels (presence threshold:
   chips standoff + 0.8 × body height; gull-wing halfway between lead top and body top).
4. ``component_shifted``: the blob's centroid offset, seen from each pad (IPC-A-610
   Class 2): across the pad, the termination (chips) or lead (gull-wing) hangs over the
   pad's side by more than 50 % of its width (side overhang = displacement − (pad width
   − termination width) / 2); along it, a chip's termination passes the pad's outer
   end (end overhang) or a lead's heel leaves its pad.

Joint level

5. ``excess`` (chips): solder over the end cap stands higher than ``cap_excess_mm``
   above the body top (measured on the cap, so judged even when the fillet is not).
6. ``lifted_lead`` (gull-wing; needs ``min_reliable_fraction`` of the lead's foot
   reliable, or :data:`LEAD_MIN_PIXELS` reliable pixels in its toe half, or from
   :data:`LEAD_FEW_PIXELS` a rise that clears the gap by :data:`LEAD_SPREAD_K` times
   their spread): the lead's measured top stands more than ``lifted_lead_gap_mm``
   above its nominal top (solder thickness + lead thickness) and the solder level just
   beyond its toe (else the median beside it, :func:`under_lead`) does not reach the
   lead's underside (measured top − lead thickness). A raised top with solder up to the
   underside is a buried foot (its height is then the joint's max, see rule 12), never a
   lifted lead; a raised foot is never read as a heel fillet.
7. ``missing`` by colour: at least ``bare_missing_fraction`` of the visible pad looks
   like the bare finish (the all-in-focus colour does not need focus texture) and no
   reliable height reaches the joint's ``min_height_mm``; or at least
   ``bare_dominant_fraction`` of it does, whatever the heights (a fillet that reaches the
   band wets the pad; the heights on a mostly bare pad are an edge's spread); or, on a
   gull-wing, ``bare_missing_fraction`` of it does and of the pad beside the lead by the
   heel too (``heel_bare_fraction``: a heel fillet wets it; the heel read over it is the
   knee's edge).
8. ``bridge``: a path across the gap to a neighbouring pad of the same component is
   covered higher than ``bridge_height_mm`` (``bridge_lead_height_mm`` between the feet
   of a gull-wing part, far from any body edge) along ``bridge_min_fraction`` of its
   length (the paths carry their own coverage test: judged whatever the solder area's).
9. ``unreliable``: fewer than ``min_reliable_fraction`` of the solder area's pixels are
   reliable, or no max height could be measured. Never a pass; a fail only when what is
   measured is already a defect: a chip's solder area with at least half that fraction
   and :data:`MIN_EVIDENCE_PIXELS` reliable whose percentile stands above
   ``max_height_mm`` by more than its uncertainty is ``excess`` (the unmeasured rest
   cannot lower it; on fewer pixels the body's bled edge can read that high). A
   gull-wing heel fitted to enough reliable foot pixels, with its side region measured,
   is judged on that fit from half the fraction on (:func:`_judged_on_heel_fit`).
10. ``missing`` without a colour cue: the max height is below ``missing_height_mm``.
11. ``insufficient``: below the joint's ``min_height_mm`` — but ``unreliable`` for a chip
    meniscus at or above ``min_reads_mm``, what a fillet exactly at the minimum reads
    through the fit when it is the most curved arc solder can take (the shape alone).
12. ``excess``: above the joint's ``max_height_mm``; a chip meniscus capped at the end
    cap's measured top above it is ``unreliable`` instead (the fit overshot; the cap's
    own reading, not solder, stands above the band: solder over the cap is rule 5's).
    Rules 11–13 need a measured max: when a chip's meniscus fit reaches less than
    ``min_fillet_reach`` of its height, the fillet's top was not measured and the max is
    an extrapolation. Such a joint is ``excess`` when the solder area's own percentile
    is already above the band (seen directly), ``missing`` when neither that percentile
    nor the extrapolation reaches ``missing_height_mm``, the fitted meniscus does not
    rise above that percentile (nor fall below −``missing_height_mm``) and the pad is
    measured flat right up to where its solder area starts by the termination
    (``body_margin_mm`` + a pixel: a fillet's toe need not reach the pad's outer part, so
    a pad flat only there proves nothing; no colour cue), ``ok`` when that percentile —
    a lower bound of the fillet height, which rises towards the body — already reaches
    the band's minimum, or when the reach is at least
    :data:`MIN_PASS_REACH` × ``min_fillet_reach`` and the extrapolation lies in the
    band: then the reason says "EXTRAPOLATED" with the reach, and ``max_method`` (in
    every report) reads "meniscus (extrapolated, reach N%)". Otherwise ``unreliable``:
    an extrapolation never fails a joint, and a far one (the README's 0402 at 16 %
    reach) never passes it. A chip fillet that does not fit a concave meniscus (relative
    RMS residual > 10 %) with the fit above the band is a bulging, convex one: its max is
    the solder area's percentile, a lower bound (the crest by the termination is
    specular and mostly unmeasured), and the fit, which overshoots a convex profile, an
    upper one; with the percentile in the band and the fit above it the joint is
    ``unreliable``, never a silent pass.
13. ``ok`` otherwise (a gull-wing heel estimated from its side fillet passes flagged
    "ESTIMATED", and only with the lead's own height read: :data:`LEAD_FEW_PIXELS` on
    its foot's toe half, else ``unreliable``, a lifted lead not ruled out) — unless a
    gap to a neighbouring pad could not be read (its paths each less than half
    reliable: a specular web is mostly unreliable) while
    ``bridge_min_fraction`` of the reliable pixels pooled over those paths (at least
    ``MIN_SPARSE_GAP_PIXELS``) stand above the bridge height: then ``unreliable``,
    "possible bridge", never a silent pass; or a gap open to view (at least half of it
    in the image and clear of the parts) was not read at all (no path with a level and
    fewer than ``MIN_SPARSE_GAP_PIXELS`` reliable pixels to pool): ``unreliable``, "the
    gap … is not measured" — a web there is neither seen nor ruled out; or a path across
    a gap glints, :data:`GLINT_GAP_SHARE` of its pixels clipped white: the board between
    pads scatters light, specular metal clips, so that is solder across the gap whose
    heights are not measured (the reliable pixels beside it read the board):
    ``unreliable``, "possible bridge".
"""

from __future__ import annotations

import math

import numpy as np

from ._config import InspectConfig, Verdict
from ._measure import (HEEL_FIT_MIN_PIXELS, MIN_SPARSE_GAP_PIXELS, ComponentMeasurement,
                       JointMeasurement, under_lead)
from ._reference import body_top_mm, lead_top_mm
from ._result import ComponentResult, JointResult

__all__ = ["MIN_IN_FIELD", "judge_component", "judge_joint"]

#: A part (body or pad) with a smaller share of its area inside the measured field is
#: not judged: its centroid, presence and heights would be those of a cut-off part.
MIN_IN_FIELD = 0.95

#: An extrapolated meniscus (reach below ``min_fillet_reach``) may pass a joint, flagged
#: "EXTRAPOLATED" with its reach, only while its reach is at least this share of
#: ``min_fillet_reach`` (0.2 by default: the seen height times at most 5). Through shape
#: from focus on the synthetic boards, 0603/0805 fillets at reach 0.37–0.46 read 20 %
#: low; 0402 and 1206 fillets at reach 0.14–0.27 read 40–60 % low (the README's C2.2:
#: 120–161 µm for a true 350 µm). Below it the joint is ``unreliable`` unless the solder
#: seen already reaches the band.
MIN_PASS_REACH = 0.5
#: Reliable pixels a solder area needs for its percentile to call ``excess`` when too
#: little of the area is reliable to judge it otherwise (rule 9).
MIN_EVIDENCE_PIXELS = 40
#: A gap path (pad to pad) with at least this share of its pixels clipped white glints
#: along most of its length: specular metal across the gap, a possible bridge whose
#: heights are not measured (rule 13).
GLINT_GAP_SHARE = 0.5
#: A solder area with at least this share clipped white (over-exposed) says so when it
#: is too little measured to judge: the user can act on that (exposure, lighting).
CLIPPED_NOTE_FRACTION = 0.2


def _um(x: float) -> str:
    return f"{x * 1000:.0f} µm" if math.isfinite(x) else "n/a"


def _clipped_note(m: JointMeasurement) -> str:
    """The note on over-exposure for an unmeasured solder area (empty when not clipped)."""
    if not m.clipped_fraction >= CLIPPED_NOTE_FRACTION:
        return ""
    return (f"; {m.clipped_fraction:.0%} of it is clipped white (over-exposed glint): "
            "lower the exposure or the lighting")


def _lying_level(comp, m: ComponentMeasurement, config: InspectConfig) -> bool:
    """Whether a chip's body lies where it should: present, its top's plane between the
    terminations level (tilt within the tombstone limit) and at the nominal top height
    (within a third of the body's height). Then what stands far above it is solder over
    an end cap (rule 5), not the part stood up: an upright part leaves its middle empty
    or tilted."""
    if m.top_plane is None or not math.isfinite(m.tilt_deg):
        return False
    return (m.tilt_deg <= config.tombstone_tilt_deg
            and m.present_fraction >= config.component_present_fraction
            and abs(m.top_plane[2] - body_top_mm(comp)) <= comp.body_height_mm / 3.0)


def judge_component(comp, m: ComponentMeasurement, config: InspectConfig) -> ComponentResult:
    """Apply the component-level rules (1–4)."""
    verdict, reason = Verdict.OK, "body present, level and in place"
    if m.in_field_fraction < MIN_IN_FIELD:
        verdict = Verdict.UNRELIABLE
        reason = (f"part partly outside the measured field ({m.in_field_fraction:.0%} of its "
                  f"body and pads inside); not judged")
    elif comp.kind == "chip" and m.standing_fraction >= config.standing_fraction \
            and not _lying_level(comp, m, config):
        verdict = Verdict.TOMBSTONE
        reason = (f"part stands upright: {m.standing_fraction:.0%} of its area is far above the "
                  f"body top (>= {config.standing_fraction:.0%})")
    elif comp.kind == "chip" and math.isfinite(m.tilt_deg) and m.tilt_deg > config.tombstone_tilt_deg \
            and m.reliable_fraction >= config.min_reliable_fraction:
        verdict = Verdict.TOMBSTONE
        reason = f"body top tilted {m.tilt_deg:.1f} deg along its axis (> {config.tombstone_tilt_deg} deg)"
    elif m.reliable_fraction < config.min_reliable_fraction \
            and m.n_pixels * m.reliable_fraction >= MIN_EVIDENCE_PIXELS \
            and m.present_fraction < config.component_present_fraction:
        # Too little of the footprint is measured to check a body, but what is measured
        # there is not a body: only the body's top can be seen inside its footprint, so
        # reliable pixels at board level there are the board under a missing part (a
        # bare solder mask, weakly textured: mostly unreliable).
        verdict = Verdict.COMPONENT_MISSING
        reason = (f"only {m.reliable_fraction:.0%} of the body footprint is reliable, and "
                  f"only {m.present_fraction:.0%} of its "
                  f"{round(m.n_pixels * m.reliable_fraction)} reliable pixels stand at body "
                  f"height (< {config.component_present_fraction:.0%}): no body there")
    elif m.reliable_fraction < config.min_reliable_fraction:
        verdict = Verdict.UNRELIABLE
        reason = (f"only {m.reliable_fraction:.0%} of the body is reliable "
                  f"(< {config.min_reliable_fraction:.0%}); body checks skipped")
    elif m.present_fraction < config.component_present_fraction:
        verdict = Verdict.COMPONENT_MISSING
        reason = (f"only {m.present_fraction:.0%} of the body footprint stands at body height "
                  f"(< {config.component_present_fraction:.0%})")
    elif all(map(math.isfinite, m.offset_mm)):
        offset = np.asarray(m.offset_mm, np.float64)
        why = _misplaced(comp, offset, m.offset_slack_mm, turn_deg=m.turn_deg)
        if why:
            verdict = Verdict.COMPONENT_SHIFTED
            reason = why
        elif m.offset_cov_mm2 is not None:
            # Within the limit as read, but the placement it is read against is itself
            # known only so well here: never a silent pass of a shift it may hide.
            why = _misplaced(comp, offset, m.offset_slack_mm, turn_deg=m.turn_deg,
                             margin_cov=m.offset_cov_mm2)
            if why:
                sd = 1000.0 * math.sqrt(max(float(np.max(np.linalg.eigvalsh(
                    m.offset_cov_mm2))), 0.0))
                verdict = Verdict.UNRELIABLE
                reason = (f"{MAY_BE_SHIFTED}: in place as read, but the board's placement "
                          f"is known here only to σ = {sd:.0f} µm, and {PLACEMENT_K:g}σ "
                          f"further out: {why}; not judged")
    return ComponentResult(
        ref=comp.ref, kind=comp.kind, package=comp.package, verdict=verdict, reason=reason,
        present_fraction=m.present_fraction, body_height_mm=m.body_height_mm,
        offset_mm=m.offset_mm, tilt_deg=m.tilt_deg, reliable_fraction=m.reliable_fraction)


#: IPC-A-610 Class 2: side overhang up to 50 % of the termination (lead) width.
MAX_SIDE_OVERHANG = 0.5
#: A part is passed in place only while its displacement, taken this many standard
#: deviations of the board's placement at the part further out, stays within the limits
#: (rule 4): else ``unreliable``, "may be shifted".
PLACEMENT_K = 2.0
#: How such a part's reason begins; its joints are then ``unreliable`` too.
MAY_BE_SHIFTED = "may be shifted"


def _misplaced(comp, offset: np.ndarray, slack=(0.0, 0.0), *, turn_deg: float = 0.0,
               margin_cov: np.ndarray | None = None) -> str:
    """Why the part's displacement ``offset`` (BOARD frame, mm) is a defect ("" if not).

    ``slack``: how far the body's middle may lie from it along the part's own x and y;
    a displacement counts only by what it shows beyond that. ``turn_deg``: how far the
    body is turned (counter-clockwise; NaN or 0: not turned); each joint is then
    displaced by the offset plus what the turn moves its pad's centre. ``margin_cov``:
    (2, 2) covariance (mm²) of the placement at the part; each displacement is then
    taken :data:`PLACEMENT_K` σ (along its direction) further from zero, towards the
    limit (what it may be, not what it shows)."""
    worst = ""
    worst_v = 0.0
    centred_body = comp.body_polygon_mm() - [comp.x_mm, comp.y_mm]
    a = math.radians(comp.rotation_deg)
    ex, ey = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    t = math.radians(turn_deg) if math.isfinite(turn_deg) else 0.0
    turn = np.array([[math.cos(t) - 1.0, -math.sin(t)], [math.sin(t), math.cos(t) - 1.0]])

    def shown(moved: np.ndarray, d: np.ndarray) -> float:
        """Displacement ``moved`` along ``d`` less the slack along it (towards zero),
        plus the placement's margin along it (away from zero)."""
        x = float(moved @ d)
        s = abs(float(d @ ex)) * slack[0] + abs(float(d @ ey)) * slack[1]
        grow = 0.0 if margin_cov is None else PLACEMENT_K * math.sqrt(
            max(float(d @ margin_cov @ d), 0.0))
        return math.copysign(max(abs(x) - s, 0.0) + grow, x)

    for j in comp.joints:
        pad = np.asarray(j.polygon_mm, np.float64) - [comp.x_mm, comp.y_mm]
        moved = offset + turn @ ((pad.min(0) + pad.max(0)) / 2.0)  # the joint's displacement
        out = np.asarray(j.outward, np.float64)
        out = out / max(float(np.hypot(*out)), 1e-12)
        acr = np.array([-out[1], out[0]])
        pad_w = float(np.ptp(pad @ acr))
        if comp.kind == "gullwing" and comp.lead:
            term_w = float(comp.lead["width_mm"])
        else:
            term_w = float(np.ptp(centred_body @ acr))
        side = abs(shown(moved, acr)) - max(pad_w - term_w, 0.0) / 2
        frac = side / max(term_w, 1e-9)
        if frac > MAX_SIDE_OVERHANG and frac > worst_v:
            worst_v = frac
            worst = (f"{j.id}: the {'lead' if comp.kind == 'gullwing' else 'termination'} "
                     f"hangs {frac:.0%} of its width over the pad's side (> "
                     f"{MAX_SIDE_OVERHANG:.0%}); body off by {float(offset @ acr):+.3f} mm "
                     f"across the pad" + (f", turned {turn_deg:+.1f} deg" if t else ""))
        along = shown(moved, out)
        if comp.kind == "gullwing" and comp.lead:
            heel = float(comp.lead["span_mm"]) / 2 - float(comp.lead["foot_length_mm"])
            room_in = heel - float((pad @ out).min())          # heel to the pad's inner end
            room_out = float((pad @ out).max()) - float(comp.lead["span_mm"]) / 2
            bad = along < -room_in or along > room_out + float(comp.lead["foot_length_mm"]) / 2
            room = room_in if along < 0 else room_out
        else:
            end = float((centred_body @ out).max())
            room = float((pad @ out).max()) - end               # pad beyond the body's end
            bad = along > room
        if bad and not worst:
            worst = (f"{j.id}: body off by {along:+.3f} mm along the pad, past its end "
                     f"(room {room:.3f} mm)")
    return worst


#: A lead's height (the median of its foot's reliable toe-half pixels) counts as measured
#: from this many pixels, whatever share of the foot they are (rule 6): a median over
#: twenty windows' worth of pixels is a reading, not a stray peak. On tuning boards 8–47
#: no good lead read above its nominal top at any foot coverage (−16 µm at most, 92
#: joints under 20 % coverage), while two lifted leads (65 and 208 µm) had 38–39 % of
#: their feet reliable, under the 40 % the coverage rule asks.
LEAD_MIN_PIXELS = 20

#: Fewer toe-half pixels (down to this many) read a lifted lead when the rise clears
#: ``lifted_lead_gap_mm`` by :data:`LEAD_SPREAD_K` times their own spread (1.4826 MAD):
#: a lead raised well clear of its pad shows only its toe in focus. Tuning dense seed 25:
#: a lead lifted 0.28 mm read +254 µm from 17 pixels spread 10.5 µm and passed; good
#: leads read under 20 pixels stand 45–63 µm *below* their nominal top.
LEAD_FEW_PIXELS = 5
LEAD_SPREAD_K = 3.0


def _lead_read(comp, m: JointMeasurement, config: InspectConfig) -> bool:
    """Whether the gull-wing lead's height is a reading rule 6 judges: enough of the
    foot reliable, :data:`LEAD_MIN_PIXELS` toe-half pixels, or a rise above the nominal
    top that clears the lifted-lead gap beyond its own pixels' spread."""
    if not math.isfinite(m.lead_mm):
        return False
    if m.foot_reliable_fraction >= config.min_reliable_fraction or m.lead_n >= LEAD_MIN_PIXELS:
        return True
    rise = m.lead_mm - lead_top_mm(comp)
    return (m.lead_n >= LEAD_FEW_PIXELS
            and rise - LEAD_SPREAD_K * m.lead_spread_mm > config.lifted_lead_gap_mm)


def judge_joint(joint, comp, m: JointMeasurement, comp_result: ComponentResult,
                config: InspectConfig, *, component_in_field: float = 1.0) -> JointResult:
    """Apply the rules to one joint (component-level verdicts take precedence).

    ``component_in_field``: the component's share inside the measured field
    (:attr:`ComponentMeasurement.in_field_fraction`); below :data:`MIN_IN_FIELD` the
    joint is not judged."""
    if min(component_in_field, m.in_field_fraction) < MIN_IN_FIELD:
        v, reason = Verdict.UNRELIABLE, (
            f"{comp.ref} lies partly outside the measured field "
            f"({min(component_in_field, m.in_field_fraction):.0%} inside); not judged")
    else:
        v, reason = _joint_rule(joint, comp, m, comp_result, config)
        possible = _possible_bridge(m, _bridge_limit(comp, config), config)
        if v == Verdict.OK and possible:
            v, reason = Verdict.UNRELIABLE, f"possible bridge to {possible}; not judged ({reason})"
        elif v == Verdict.OK and comp_result.verdict is Verdict.UNRELIABLE \
                and comp_result.reason.startswith(MAY_BE_SHIFTED):
            # the pad may have lost its termination: what is read there is not a joint
            v, reason = Verdict.UNRELIABLE, f"{comp.ref} {comp_result.reason}"
        elif v == Verdict.OK and m.gap_unread:
            v, reason = Verdict.UNRELIABLE, (
                f"the gap to {m.gap_unread} is not measured (no path read, fewer than "
                f"{MIN_SPARSE_GAP_PIXELS} reliable pixels): a bridge there is not ruled "
                f"out; not judged ({reason})")
    method = m.max_method
    if _extrapolated(m, config):
        note = f"extrapolated, reach {m.fillet_reach:.0%}"
        method = f"{method[:-1]}, {note})" if method.endswith(")") else f"{method} ({note})"
    elif method == "side":
        method = "side (estimated: the heel not measured)"
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
        max_method=method, bare_fraction=m.bare_fraction, foot_height_mm=m.foot_mm,
        side_height_mm=m.side_mm, cap_excess_mm=m.cap_mm, fillet_reach=m.fillet_reach,
        polygon_px=m.polygon_px)


def _extrapolated(m: JointMeasurement, config: InspectConfig) -> bool:
    """Whether the max is a chip meniscus whose reliable pixels reach less than
    ``min_fillet_reach`` of it: an extrapolation (rule 12), capped at the termination
    top or not. (A capped fit overshot the termination: capping bounds it, it does not
    make it measured; demo seed 45's insufficient 0402, 50 µm at 35 % reach, had read
    'excess' at the termination top.)"""
    return m.max_method.startswith("meniscus") and m.fillet_reach < config.min_fillet_reach


def _judged_on_heel_fit(joint, comp, m: JointMeasurement, config: InspectConfig) -> bool:
    """A gull-wing joint is judged on its heel fillet's own evidence, however little of
    its solder area is reliable (rule 9), when that max is the meniscus fitted along the
    foot to at least :data:`HEEL_FIT_MIN_PIXELS` reliable pixels, the side region beside
    the foot is measured too (so a dry foot's heel reading was tested against a bare pad,
    rule 12's premise) and at least half of ``min_reliable_fraction`` of the area is
    reliable. The solder area of a gull-wing is mostly the foot's top, whose lead
    surface a 5-px window sees poorly; the heel fit is a reading over hundreds of
    pixels. On tuning boards 8-47 good heel joints read -15 ... +7 µm (5th-95th
    percentile, 24 joints) at 20-30 % coverage, -20 ... +9 µm (52) at 30-40 % and
    -19 ... +5 µm (452) above 40 %: the same reading. A lead standing above its nominal
    top with no solder up to its underside (rule 6's lifted lead, on too few toe pixels
    for rule 6) is not read as a heel fillet here; a buried foot (solder up to the
    underside) is, and reads excess (tuning boards: a foot buried 0.09 mm over the band,
    and a lead lifted 0.28 mm whose side region reads its blurred edge, 0.44 mm).

    The side estimate (side percentile / ``side_fillet_ratio``) must agree with the heel
    on which side of each of the band's limits the joint lies: a small heel fillet,
    below the lead's top, leaves the knee's blurred edge for the fit to read (test seed
    dense 10016: a heel fillet of 0.10 mm, under the 0.13 mm minimum, read 0.25 mm by
    the fit and 0.12 mm from its side), and a fit to a few pixels can overshoot (tuning
    seed dense 225 U1.4: 20 fit pixels read 0.73 mm, over the 0.57 mm maximum, for a
    good heel whose side reads 0.21 mm). And a gap to the neighbouring feet with paths too
    sparsely measured to read must not glint (:data:`GLINT_GAP_SHARE`): the coverage
    rule had also been what kept a bridge whose web was all unreliable pixels from
    passing (test seed demo 10033); a web's glint now tells it, and the sparse paths'
    pooled pixels are read for a possible bridge (rule 13). Before, any sparse path
    left the joint unjudged: on tuning seeds 216-231, 36 good heels (read 0.25-0.46 mm
    on 25-265 fit pixels, true 0.26-0.30, median error +11 µm) and 3 excess ones were
    `unreliable` on boards with glinting solder (29-72 % of the solder area clipped
    white), the gaps between the feet not glinting."""
    if not (comp.kind == "gullwing" and m.max_method == "foot"
            and m.heel_fit_n >= HEEL_FIT_MIN_PIXELS and math.isfinite(m.side_mm)
            and m.reliable_fraction >= 0.5 * config.min_reliable_fraction):
        return False
    underside, below, _ = under_lead(comp, m)
    if m.lead_mm - lead_top_mm(comp) > config.lifted_lead_gap_mm and below < underside:
        return False
    side = m.side_mm / config.side_fillet_ratio
    for limit in (joint.min_height_mm, joint.max_height_mm):
        if (side >= limit) != (m.max_mm >= limit):
            return False
    # a gap whose paths are too sparsely measured to read each (a specular web is mostly
    # unreliable pixels) is read on the pixels pooled over them (rule 13's possible
    # bridge); a web whose glint leaves none of its own pixels measured is told by the
    # glint itself (rule 13)
    return m.gap_sparse_n == 0 or not m.gap_glint >= GLINT_GAP_SHARE


def _possible_bridge(m: JointMeasurement, bridge: float, config: InspectConfig) -> str:
    """The neighbour and why, when a gap shows solder above ``bridge`` that is not a
    measurement of it, or glints across (``GLINT_GAP_SHARE``) ("" when none): a pass
    would ignore a possible bridge."""
    if m.gap_sparse_mm > bridge:
        # too little of the gap is measured to read a path, but what is measured stands
        # at solder height
        return (f"{m.gap_sparse_neighbour}: the gap's paths are too sparsely measured to "
                f"read, and {config.bridge_min_fraction:.0%} of the {m.gap_sparse_n} pixels "
                f"measured there stand above {_um(m.gap_sparse_mm)} (> {_um(bridge)})")
    if m.gap_blend_mm > bridge:
        # only where the body's edge blends into the heights (within the focus window's
        # reach of it) does the gap stand high: a web wetting the body's side, or the
        # body's edge itself; shape from focus cannot tell them apart
        return (f"{m.gap_blend_neighbour}: a path next to the body stands level at "
                f"{_um(m.gap_blend_mm)} (> {_um(bridge)}), but within the focus window's "
                f"reach of the body's edge, whose height blends into it there")
    if m.gap_glint >= GLINT_GAP_SHARE:
        # a web whose glint leaves its own heights unmeasured: the paths beside it read
        # the board (rule 13)
        return (f"{m.gap_glint_neighbour}: a path across the gap is {m.gap_glint:.0%} "
                f"clipped white (>= {GLINT_GAP_SHARE:.0%}: specular metal, not board; its "
                f"heights are not measured)")
    return ""


def _bridge_limit(comp, config: InspectConfig) -> float:
    """The gap height above which solder bridges (rule 8)."""
    return config.bridge_lead_height_mm if comp.kind == "gullwing" else config.bridge_height_mm


def _joint_rule(joint, comp, m: JointMeasurement, comp_result: ComponentResult,
                config: InspectConfig) -> tuple[Verdict, str]:
    if comp_result.verdict.is_defect:
        return comp_result.verdict, f"{comp.ref}: {comp_result.reason}"
    if comp.kind == "gullwing" and _lead_read(comp, m, config):
        nominal = lead_top_mm(comp)
        underside, below, where = under_lead(comp, m)
        if m.lead_mm - nominal > config.lifted_lead_gap_mm and below < underside:
            return Verdict.LIFTED_LEAD, (f"lead top at {_um(m.lead_mm)}, "
                                         f"{_um(m.lead_mm - nominal)} above its nominal "
                                         f"{_um(nominal)} (> {_um(config.lifted_lead_gap_mm)}); "
                                         f"solder {where} reaches only {_um(below)}, below "
                                         f"the lead's underside ({_um(underside)})")
    if comp.kind == "chip" and math.isfinite(m.cap_mm) and m.cap_mm > config.cap_excess_mm:
        return Verdict.EXCESS, (f"solder over the end cap {_um(m.cap_mm)} above the body top "
                                f"(> {_um(config.cap_excess_mm)})")
    bare = math.isfinite(m.bare_fraction) and m.bare_fraction >= config.bare_missing_fraction
    if bare and not (m.max_mm >= joint.min_height_mm):   # NaN (nothing measured) counts
        return Verdict.MISSING, (f"no solder: {m.bare_fraction:.0%} of the visible pad looks bare; "
                                 f"max height {_um(m.max_mm)}, {m.reliable_fraction:.0%} reliable")
    if math.isfinite(m.bare_fraction) and m.bare_fraction >= config.bare_dominant_fraction:
        return Verdict.MISSING, (f"no solder: {m.bare_fraction:.0%} of the visible pad looks bare "
                                 f"(>= {config.bare_dominant_fraction:.0%}: no fillet wets it); "
                                 f"the {_um(m.max_mm)} read there is the "
                                 f"{'lead' if comp.kind == 'gullwing' else 'termination'}'s "
                                 f"edge spread by the focus window")
    if comp.kind == "gullwing" and bare and math.isfinite(m.heel_bare_fraction) \
            and m.heel_bare_fraction >= config.bare_missing_fraction:
        # A heel fillet wets the pad beside the lead by the heel: with the pad mostly bare
        # and bare there too, the heel's reading is the knee's blurred edge over a dry
        # foot (tuning demo 259 U1.6: 61 % of the pad and 65 % by the heel bare, a 272 µm
        # "heel" fitted over 215 foot pixels, passed). By the heel alone is too few
        # pixels: a good joint read 51 % bare there, 21 % over its whole pad (test demo
        # 10097 U1.3, HASL pads coloured by the lighting).
        return Verdict.MISSING, (f"no solder: {m.bare_fraction:.0%} of the visible pad and "
                                 f"{m.heel_bare_fraction:.0%} of it beside the lead by the "
                                 f"heel look bare (>= {config.bare_missing_fraction:.0%}: no "
                                 f"heel fillet wets it); the {_um(m.max_mm)} read there is "
                                 f"the knee's edge spread by the focus window")
    # A bridge is read on the gap's own paths (each must be covered), not on the solder
    # area: it is judged however little of the solder area is reliable.
    bridge = _bridge_limit(comp, config)
    if math.isfinite(m.gap_mm) and m.gap_mm > bridge:
        return Verdict.BRIDGE, (f"solder across the gap to {m.gap_neighbour}: "
                                f"{config.bridge_min_fraction:.0%} of a path stands above "
                                f"{_um(m.gap_mm)} (> {_um(bridge)})")
    # judged, however little of the solder area is reliable, on a gull-wing's heel fit
    on_heel = (m.reliable_fraction < config.min_reliable_fraction
               and _judged_on_heel_fit(joint, comp, m, config))
    if (m.reliable_fraction < config.min_reliable_fraction and not on_heel) \
            or not math.isfinite(m.max_mm):
        seen, u_seen = m.observed_mm, m.u_max_mm
        if math.isfinite(seen) and m.n_pixels * m.reliable_fraction >= MIN_EVIDENCE_PIXELS \
                and m.reliable_fraction >= 0.5 * config.min_reliable_fraction \
                and seen - (u_seen if math.isfinite(u_seen) else 0.0) > joint.max_height_mm:
            # Too little is measured to pass the joint, but what is measured already
            # stands above the band: the unmeasured rest cannot lower it.
            return Verdict.EXCESS, (f"solder seen at {_um(seen)} > max "
                                    f"{_um(joint.max_height_mm)} on the "
                                    f"{m.reliable_fraction:.0%} of the solder area that is "
                                    f"reliable")
        return Verdict.UNRELIABLE, (f"only {m.reliable_fraction:.0%} of the solder area is reliable "
                                    f"(< {config.min_reliable_fraction:.0%}); not judged"
                                    + _clipped_note(m))
    h, u = m.max_mm, m.u_max_mm
    pm = f" ± {_um(u)}" if math.isfinite(u) else ""
    how = f" ({m.max_method})" if m.max_method else ""
    if on_heel:
        how = (f" (heel meniscus over {m.heel_fit_n} reliable foot pixels; solder area "
               f"{m.reliable_fraction:.0%} reliable)")
    if _extrapolated(m, config):
        how = f" (meniscus, extrapolated from {m.fillet_reach:.0%} reach)"
        seen = m.observed_mm
        if seen > joint.max_height_mm:
            return Verdict.EXCESS, (f"solder seen at {_um(seen)} > max {_um(joint.max_height_mm)} "
                                    f"(meniscus extrapolated to {_um(h)}, reach "
                                    f"{m.fillet_reach:.0%})")
        if max(seen, h) < config.missing_height_mm and not h > seen \
                and h > -config.missing_height_mm \
                and not math.isfinite(m.bare_fraction) and m.fillet_near_mm <= m.fillet_edge_mm:
            # The pad is flat where it is measured, right up to where its solder area
            # starts by the termination, and the meniscus fitted to it does not rise
            # above what is seen: no fillet, no solder. A fit that rises is a fillet
            # whose top is hidden (an extrapolation then reads low, not high: an 0402's
            # at this reach 40-60 % low), and a pad flat only farther out is one whose
            # fillet's toe stops short of the pixels measured: never "missing". Nor is
            # a fit that falls towards the termination by more than the missing height:
            # solder does not dip below its pad, so that pad is not read (tuning dense
            # 25 C3.2, a good 0402: pixels 30-70 µm below the board, fitted to -116 µm).
            return Verdict.MISSING, (f"no solder: the solder area reaches {_um(seen)}, "
                                     f"measured up to its edge by the termination, and the "
                                     f"meniscus fitted to it does not rise above it "
                                     f"({_um(h)}, reach {m.fillet_reach:.0%}); both < "
                                     f"{_um(config.missing_height_mm)}")
        # A lower bound passes the joint only from the pixels the meniscus fit kept: the
        # solder area's own percentile also holds those it rejected, such as the body's
        # bled edge by the termination (test seed demo 10005: a 1206 fillet fitted to
        # 48 µm passed on a 'seen' 1178 µm, the end cap's height).
        bound = min(seen, m.fit_seen_mm) if math.isfinite(m.fit_seen_mm) else seen
        also = f" (the whole solder area's percentile {_um(seen)})" if bound < seen - 0.001 else ""
        if bound >= joint.min_height_mm and h <= joint.max_height_mm:
            return Verdict.OK, (f"max solder height {_um(h)}{pm} extrapolated (reach "
                                f"{m.fillet_reach:.0%}); the solder seen reaches {_um(bound)} "
                                f">= min {_um(joint.min_height_mm)}")
        if m.fillet_reach >= MIN_PASS_REACH * config.min_fillet_reach \
                and joint.min_height_mm <= h <= joint.max_height_mm:
            return Verdict.OK, (f"max solder height {_um(h)}{pm} EXTRAPOLATED from a meniscus "
                                f"whose reliable pixels reach {m.fillet_reach:.0%} of it "
                                f"(< {config.min_fillet_reach:.0%}; seen {_um(seen)}) within "
                                f"[{_um(joint.min_height_mm)}, {_um(joint.max_height_mm)}]")
        return Verdict.UNRELIABLE, (f"fillet top not measured (reliable pixels reach "
                                    f"{m.fillet_reach:.0%} of the fitted height, < "
                                    f"{config.min_fillet_reach:.0%}): extrapolated {_um(h)}{pm}, "
                                    f"seen {_um(bound)}{also}; not judged")
    if math.isfinite(m.bulge_mm) and h <= joint.max_height_mm < m.bulge_mm:
        # Between the bounds: the percentile (what is seen) lies in the band, the concave
        # fit (which overshoots a convex profile) above it. The crest is not measured.
        return Verdict.UNRELIABLE, (f"bulging (convex) fillet, its crest not measured: the "
                                    f"solder seen reaches {_um(h)}{pm}, within the max "
                                    f"{_um(joint.max_height_mm)}, the concave meniscus fitted "
                                    f"to it {_um(m.bulge_mm)}; not judged")
    if h > joint.max_height_mm and m.max_method.startswith("meniscus (capped"):
        # The fit rose past the end cap and was capped at the cap's measured top, which
        # stands above the band's max (G + H, the cap's nominal top) by the cap's own
        # reading, not by solder (solder over the cap is rule 5's): the fillet's top is
        # not measured — an overshoot also follows the end cap's edge bled into the
        # fillet's pixels (tuning demo 28 R3.1, a true 316 µm capped at 486 µm).
        return Verdict.UNRELIABLE, (f"meniscus fit overshoots the end cap: capped at the "
                                    f"cap's measured top {_um(h)}{pm}, above the max "
                                    f"{_um(joint.max_height_mm)} (the cap's nominal top) with "
                                    f"no solder over the cap beyond "
                                    f"{_um(config.cap_excess_mm)}; not judged")
    if h < joint.min_height_mm and not math.isfinite(m.bare_fraction) \
            and h < config.missing_height_mm:
        return Verdict.MISSING, f"no solder: max height {_um(h)}{pm}{how} < {_um(config.missing_height_mm)}"
    if h < joint.min_height_mm and m.max_method == "meniscus" and h >= m.min_reads_mm:
        # A fillet exactly at the minimum, shaped as the most curved meniscus solder can
        # take, reads this low through the concave fit: the shape alone could be the
        # shortfall.
        return Verdict.UNRELIABLE, (f"max solder height {_um(h)}{pm}{how} < min "
                                    f"{_um(joint.min_height_mm)}, but a fillet at the minimum "
                                    f"whose meniscus is the most curved arc reads "
                                    f"{_um(m.min_reads_mm)} through this fit; not judged")
    if h < joint.min_height_mm:
        return Verdict.INSUFFICIENT, f"max solder height {_um(h)}{pm}{how} < min {_um(joint.min_height_mm)}"
    if h > joint.max_height_mm:
        return Verdict.EXCESS, f"max solder height {_um(h)}{pm}{how} > max {_um(joint.max_height_mm)}"
    if m.max_method == "side":
        if not m.lead_n >= LEAD_FEW_PIXELS:
            # The estimate assumes the lead sits on its pad; with too few reliable pixels
            # on the foot's toe half the lead's own height is not known, and a lifted
            # lead's blurred edge reads on the side strip like a fillet (tuning dense 260
            # U2.2: lifted 0.26 mm, 1 % of its foot reliable, passed at an estimated
            # 376 µm).
            return Verdict.UNRELIABLE, (f"heel and lead not measured ({m.lead_n} reliable "
                                        f"pixels on the foot's toe half, < "
                                        f"{LEAD_FEW_PIXELS}): a lifted lead is not ruled "
                                        f"out; the side fillet reads {_um(m.side_mm)}; not "
                                        f"judged")
        # The heel is not measured: its height is inferred from the fillet beside the
        # lead through a calibrated ratio, which a good joint and an insufficient heel
        # with wetted sides read alike (tuning dense 203 U2.3, a heel at 17 % of its
        # minimum, passed at 151 µm). It passes, but says so (issue 12: an
        # extrapolation never passes silently).
        return Verdict.OK, (f"max solder height {_um(h)}{pm} ESTIMATED from the side "
                            f"fillet (the heel is not measured: the strip beside the lead "
                            f"reads {_um(m.side_mm)}, ÷ {config.side_fillet_ratio:g}) within "
                            f"[{_um(joint.min_height_mm)}, {_um(joint.max_height_mm)}]")
    return Verdict.OK, (f"max solder height {_um(h)}{pm}{how} within "
                        f"[{_um(joint.min_height_mm)}, {_um(joint.max_height_mm)}]")


