"""The joint rules on hand-made measurements: what the pixels show against the band.

The end-to-end tests (test_inspect, test_pipeline) prove the rules on rendered boards;
these pin the two rules that decide what a measurement may claim: colour evidence of a
bare pad, and a meniscus whose top was never measured.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from smdinspect.inspect import InspectConfig, Verdict, load_board
from smdinspect.inspect._measure import JointMeasurement
from smdinspect.inspect._result import ComponentResult
from smdinspect.inspect._verdict import judge_joint

from ._synthetic import DEMO

NAN = math.nan


@pytest.fixture(scope="module")
def c2():
    board = load_board(DEMO)
    comp = board.component("C2")
    joint = board.joint("C2.1")
    body = ComponentResult(ref="C2", kind="chip", package=comp.package, verdict=Verdict.OK,
                           reason="", present_fraction=1.0, body_height_mm=0.53,
                           offset_mm=(0.0, 0.0), tilt_deg=0.0, reliable_fraction=0.9)
    return joint, comp, body


def _u1(joint_id: str):
    """The demo board's SOIC-8 U1 (component, joint ``joint_id``, its body judged ok)."""
    board = load_board(DEMO)
    u1 = board.component("U1")
    body = ComponentResult(ref="U1", kind="gullwing", package=u1.package, verdict=Verdict.OK,
                           reason="", present_fraction=1.0, body_height_mm=1.5,
                           offset_mm=(0.0, 0.0), tilt_deg=0.0, reliable_fraction=0.9)
    return u1, board.joint(joint_id), body


def _judge(c2, **kw):
    joint, comp, body = c2
    m = JointMeasurement(joint.id, (0.0, 0.0), 200, kw.pop("reliable_fraction", 0.8), **kw)
    return judge_joint(joint, comp, m, body, InspectConfig())


def test_meniscus_reaching_its_top_is_judged(c2):
    joint = c2[0]
    low = joint.min_height_mm - 0.03
    r = _judge(c2, max_mm=low, max_method="meniscus", fillet_reach=0.55, observed_mm=low - 0.05)
    assert r.verdict is Verdict.INSUFFICIENT
    # An extrapolated max passes a joint only flagged, with its reach, in the reason and
    # in max_method (shown in every report)...
    r = _judge(c2, max_mm=joint.nominal_height_mm, max_method="meniscus", fillet_reach=0.2,
               observed_mm=joint.min_height_mm - 0.05)
    assert r.verdict is Verdict.OK and "EXTRAPOLATED" in r.reason and "20%" in r.reason
    assert r.max_method == "meniscus (extrapolated, reach 20%)"
    # ...and never from a far extrapolation (issue 12: the README's C2.2, a 0402 at 16 %
    # reach, passed at 161 µm against a true 350 µm)...
    r = _judge(c2, max_mm=joint.nominal_height_mm, max_method="meniscus", fillet_reach=0.15,
               observed_mm=joint.min_height_mm - 0.05)
    assert r.verdict is Verdict.UNRELIABLE and "15%" in r.reason
    # ...unless the solder seen (a lower bound of the fillet) already reaches the band.
    r = _judge(c2, max_mm=joint.nominal_height_mm, max_method="meniscus", fillet_reach=0.15,
               observed_mm=joint.min_height_mm + 0.01)
    assert r.verdict is Verdict.OK and "extrapolated" in r.reason and "15%" in r.reason


def test_a_reading_the_fillet_shape_alone_could_give_is_not_insufficient(c2):
    """Solder fillets are arcs (surface tension); the parabola reads an arc lower the
    more it is curved. A fillet exactly at the minimum, shaped as the most curved arc,
    reads ``min_reads_mm``: a reading between that and the minimum is not judged, one
    below it is insufficient."""
    joint = c2[0]
    mn = joint.min_height_mm
    floor = 0.9 * mn
    r = _judge(c2, max_mm=mn - 0.005, max_method="meniscus", fillet_reach=0.55,
               observed_mm=mn - 0.05, min_reads_mm=floor)
    assert r.verdict is Verdict.UNRELIABLE and "most curved arc" in r.reason
    r = _judge(c2, max_mm=floor - 0.005, max_method="meniscus", fillet_reach=0.55,
               observed_mm=mn - 0.05, min_reads_mm=floor)
    assert r.verdict is Verdict.INSUFFICIENT
    # a percentile, not a fitted shape, has no such allowance
    r = _judge(c2, max_mm=mn - 0.005, max_method="percentile", observed_mm=mn - 0.005,
               min_reads_mm=floor)
    assert r.verdict is Verdict.INSUFFICIENT


def test_the_shape_floor_is_the_most_curved_arcs_reading():
    """The floor is what the meniscus fit reads on the most curved physical arc at the
    minimum, over the pixels seen: the lowest over every curvature, 0.72 of F on an 0402's
    pad and 0.93 on an 0603's, seen from the body margin out."""
    from smdinspect.inspect._geometry import arc_fillet
    from smdinspect.inspect._measure import _meniscus, _shape_floor

    for L, F, expect in ((0.22, 0.155, 0.72), (0.38, 0.142, 0.925)):
        d = np.linspace(0.08, L, 120)
        floor = _shape_floor(d, L, F)
        assert floor / F == pytest.approx(expect, abs=0.01)
        for k in (0.0, 0.4, 0.8):
            z = arc_fillet(d / L, F, L, k)
            assert _meniscus(d, L, z, np.full_like(d, 0.001))[0] > floor


def test_the_shape_floor_allows_for_the_windows_outward_reading():
    """A window on the fillet's slope reads the profile about a pixel further from the
    termination: the floor is the fit of the arc read that way, lower than the arc's own.
    Tuning dense seed 262, R2.2 (an 0805 fillet 0.307 mm high whose top 0.1 mm is not
    measured): read 118 µm against an unshifted floor of 131 µm and called insufficient;
    a fillet at the minimum read a pixel outward stays above the shifted floor."""
    from smdinspect.inspect._geometry import arc_fillet
    from smdinspect.inspect._measure import _meniscus, _shape_floor

    L, F, p = 0.38, 0.142, 0.02
    d = np.linspace(0.12, L, 80)
    floor = _shape_floor(d, L, F, shift=p)
    assert floor < _shape_floor(d, L, F) - 0.01
    z = arc_fillet((d + p) / L, F, L, 1.0)  # the most curved arc at the minimum, read outward
    assert _meniscus(d, L, z, np.full_like(d, 0.001))[0] == pytest.approx(floor, abs=1e-6)
    assert _meniscus(d, L, arc_fillet(d / L, F, L, 1.0), np.full_like(d, 0.001))[0] > floor


def test_meniscus_extrapolated_below_or_above_the_band_is_unreliable(c2):
    joint = c2[0]
    low = joint.min_height_mm - 0.03
    r = _judge(c2, max_mm=low, max_method="meniscus", fillet_reach=0.3, observed_mm=low - 0.05)
    assert r.verdict is Verdict.UNRELIABLE  # ...nor fails it
    assert "fillet top not measured" in r.reason and "30%" in r.reason
    high = joint.max_height_mm + 0.1
    r = _judge(c2, max_mm=high, max_method="meniscus", fillet_reach=0.3,
               observed_mm=joint.max_height_mm - 0.1)
    assert r.verdict is Verdict.UNRELIABLE
    # Excess the pixels show directly needs no extrapolation.
    r = _judge(c2, max_mm=high, max_method="meniscus", fillet_reach=0.3,
               observed_mm=joint.max_height_mm + 0.05)
    assert r.verdict is Verdict.EXCESS


def test_a_meniscus_capped_at_the_termination_top_is_still_an_extrapolation(c2):
    # Demo seed 45 (a sweep of randomised severities): an insufficient 0402 fillet (50 µm)
    # whose meniscus, fitted at 35 % reach, overshot and was capped at the termination
    # top (9 µm above the band's max by the body plane) read 'excess'. Capping bounds an
    # extrapolation; it does not make it a measurement.
    joint = c2[0]
    r = _judge(c2, max_mm=joint.max_height_mm + 0.009, fillet_reach=0.35,
               max_method="meniscus (capped at the termination top)",
               observed_mm=joint.min_height_mm - 0.02)
    assert r.verdict is Verdict.UNRELIABLE and "fillet top not measured" in r.reason
    assert r.max_method == "meniscus (capped at the termination top, extrapolated, reach 35%)"
    # Reached, the fit still overshot the end cap: a cap read 9 µm above its nominal top
    # (the band's max) is not excess solder (tuning demo 28 R3.1: a good 0603, 316 µm,
    # capped at 486 > 480 µm, read excess); solder over the cap is rule 5's.
    r = _judge(c2, max_mm=joint.max_height_mm + 0.009, fillet_reach=0.6,
               max_method="meniscus (capped at the termination top)",
               observed_mm=joint.min_height_mm + 0.05, cap_mm=0.009)
    assert r.verdict is Verdict.UNRELIABLE and "overshoots the end cap" in r.reason
    r = _judge(c2, max_mm=joint.max_height_mm + 0.08, fillet_reach=0.6,
               max_method="meniscus (capped at the termination top)",
               observed_mm=joint.min_height_mm + 0.05, cap_mm=0.08)
    assert r.verdict is Verdict.EXCESS and "over the end cap" in r.reason
    # capped within the band it is the joint's max
    r = _judge(c2, max_mm=joint.max_height_mm - 0.01, fillet_reach=0.6,
               max_method="meniscus (capped at the termination top)",
               observed_mm=joint.min_height_mm + 0.05)
    assert r.verdict is Verdict.OK
    # an uncapped meniscus above the band is excess
    r = _judge(c2, max_mm=joint.max_height_mm + 0.03, fillet_reach=0.6, max_method="meniscus",
               observed_mm=joint.min_height_mm + 0.05)
    assert r.verdict is Verdict.EXCESS


def test_a_bare_pad_is_missing_even_when_too_little_of_it_is_reliable(c2):
    r = _judge(c2, reliable_fraction=0.2, max_mm=0.0, bare_fraction=0.9, observed_mm=0.0)
    assert r.verdict is Verdict.MISSING and "looks bare" in r.reason
    r = _judge(c2, reliable_fraction=0.0, bare_fraction=0.9)      # nothing measured at all
    assert r.verdict is Verdict.MISSING
    # Some bare colour is not enough when the heights show solder at full height...
    joint = c2[0]
    r = _judge(c2, max_mm=joint.nominal_height_mm, max_method="meniscus", fillet_reach=0.6,
               observed_mm=joint.nominal_height_mm, bare_fraction=0.6)
    assert r.verdict is Verdict.OK
    # ...but a pad bare almost all over has no fillet wetting it, whatever the heights
    # (the randomised boards' dense 14 R2.2: 93 % bare, 35 px by the termination read
    # ~200 um - the end cap's edge spread by the focus window - and a meniscus fit to
    # them 326 um)
    r = _judge(c2, max_mm=joint.nominal_height_mm, max_method="meniscus", fillet_reach=0.6,
               observed_mm=joint.nominal_height_mm, bare_fraction=0.93)
    assert r.verdict is Verdict.MISSING and "93%" in r.reason and "termination" in r.reason
    # ...and a pad that does not look bare stays unreliable when too little is measured.
    r = _judge(c2, reliable_fraction=0.2, max_mm=0.0, bare_fraction=0.1, observed_mm=0.0)
    assert r.verdict is Verdict.UNRELIABLE


def test_without_colour_a_flat_pad_is_missing_and_a_low_fillet_insufficient(c2):
    joint = c2[0]
    r = _judge(c2, max_mm=0.01, max_method="percentile", observed_mm=0.01)
    assert r.verdict is Verdict.MISSING
    r = _judge(c2, max_mm=joint.min_height_mm - 0.02, max_method="percentile",
               observed_mm=joint.min_height_mm - 0.02)
    assert r.verdict is Verdict.INSUFFICIENT


def test_an_extrapolated_meniscus_is_missing_only_where_measured_up_to_the_termination(c2):
    """Only the toe of the fillet measured (reach 25 %, seen 14 µm). A meniscus fitted to
    it that rises towards the termination (29 µm: a good 0402 on a tuning board) is a
    fillet whose top is hidden: `unreliable`. One that stays flat (or falls by less than
    the missing height) is a bare pad
    (`missing`) only where the pixels reach the solder area's edge by the termination
    (body margin + a pixel, 100 µm here); measured only farther out, the fillet's toe may
    stop short of them (good 0402s of the test boards, flat 106-130 µm out): `unreliable`."""
    edge = dict(fillet_near_mm=0.09, fillet_edge_mm=0.1)
    r = _judge(c2, max_mm=0.029, max_method="meniscus", fillet_reach=0.25, observed_mm=0.014,
               **edge)
    assert r.verdict is Verdict.UNRELIABLE and "fillet top not measured" in r.reason
    for fitted in (0.014, 0.005, -0.03):
        r = _judge(c2, max_mm=fitted, max_method="meniscus", fillet_reach=0.25,
                   observed_mm=0.014, **edge)
        assert r.verdict is Verdict.MISSING and "does not rise" in r.reason, (fitted, r.reason)
        r = _judge(c2, max_mm=fitted, max_method="meniscus", fillet_reach=0.25,
                   observed_mm=0.014, fillet_near_mm=0.115, fillet_edge_mm=0.1)
        assert r.verdict is Verdict.UNRELIABLE and "fillet top not measured" in r.reason, \
            (fitted, r.reason)
    # A fit that falls towards the termination by more than the missing height is no flat
    # pad: solder does not dip below its pad (tuning dense 25 C3.2, a good 0402 whose
    # pixels read 30-70 µm below the board, fitted to -116 µm, was called missing).
    r = _judge(c2, max_mm=-0.116, max_method="meniscus", fillet_reach=0.31, observed_mm=0.024,
               **edge)
    assert r.verdict is Verdict.UNRELIABLE and "fillet top not measured" in r.reason


def test_gap_limit_is_lower_between_gull_wing_feet(c2):
    """A raised path between two gull-wing feet is a bridge from bridge_lead_height_mm
    (far from any body edge, the noise is a few µm); along a chip's side, whose gap the
    body's blurred edge lifts, only from bridge_height_mm."""
    u1, j, body = _u1("U1.7")
    cfg = InspectConfig()
    assert cfg.bridge_lead_height_mm < 0.038 < cfg.bridge_height_mm

    def gap(joint, comp, comp_body, z):
        m = JointMeasurement(joint.id, (0.0, 0.0), 200, 0.8, max_mm=joint.nominal_height_mm,
                             max_method="foot", gap_mm=z, gap_neighbour="X")
        return judge_joint(joint, comp, m, comp_body, cfg).verdict
    assert gap(j, u1, body, 0.038) is Verdict.BRIDGE     # a 78 µm bridge read 38 µm
    assert gap(j, u1, body, 0.010) is Verdict.OK
    chip, comp, chip_body = c2
    assert gap(chip, comp, chip_body, 0.038) is not Verdict.BRIDGE
    assert gap(chip, comp, chip_body, 0.060) is Verdict.BRIDGE


def test_a_partly_measured_joint_is_excess_only_on_what_it_shows(c2):
    joint = c2[0]
    high = joint.max_height_mm + 0.05
    # 25 % of 200 pixels reliable: too little to pass or to call it low...
    r = _judge(c2, reliable_fraction=0.25, max_mm=joint.nominal_height_mm,
               observed_mm=joint.nominal_height_mm, u_max_mm=0.005, max_method="percentile")
    assert r.verdict is Verdict.UNRELIABLE
    r = _judge(c2, reliable_fraction=0.25, max_mm=0.01, observed_mm=0.01, u_max_mm=0.005,
               max_method="percentile")
    assert r.verdict is Verdict.UNRELIABLE
    # ...but solder already seen above the band is excess whatever the rest holds
    r = _judge(c2, reliable_fraction=0.25, max_mm=high, observed_mm=high, u_max_mm=0.005,
               max_method="percentile")
    assert r.verdict is Verdict.EXCESS and "25%" in r.reason
    # not when the excess is within its uncertainty, nor on a handful of pixels
    r = _judge(c2, reliable_fraction=0.25, max_mm=high, observed_mm=high, u_max_mm=0.06,
               max_method="percentile")
    assert r.verdict is Verdict.UNRELIABLE
    r = _judge(c2, reliable_fraction=0.15, max_mm=high, observed_mm=high, u_max_mm=0.005,
               max_method="percentile")   # 30 pixels, less than half of the 40 % needed
    assert r.verdict is Verdict.UNRELIABLE
    # a bridge is read on the gap's own paths: judged on a poorly covered solder area
    r = _judge(c2, reliable_fraction=0.25, max_mm=joint.nominal_height_mm,
               observed_mm=joint.nominal_height_mm, u_max_mm=0.005, max_method="percentile",
               gap_mm=0.2, gap_neighbour="C2.2")
    assert r.verdict is Verdict.BRIDGE


def test_a_bulging_fillet_whose_crest_is_unmeasured_never_passes(c2):
    """A convex fillet: the solder seen (a lower bound) in the band, the concave fit (an
    upper one) above it: `unreliable`, not `ok` (two excess fillets 26 and 57 µm over
    the band passed so on test boards). Above the band as seen, it is `excess`; a fit
    within the band is an ordinary pass."""
    joint = c2[0]
    top = joint.max_height_mm
    seen = top - 0.03
    r = _judge(c2, max_mm=seen, max_method="percentile (bulging fillet)", observed_mm=seen,
               bulge_mm=top + 0.2)
    assert r.verdict is Verdict.UNRELIABLE and "bulging" in r.reason
    r = _judge(c2, max_mm=top + 0.01, max_method="percentile (bulging fillet)",
               observed_mm=top + 0.01, bulge_mm=top + 0.2)
    assert r.verdict is Verdict.EXCESS
    r = _judge(c2, max_mm=seen, max_method="percentile", observed_mm=seen)
    assert r.verdict is Verdict.OK


def test_a_lifted_lead_is_judged_on_enough_pixels_whatever_the_foot_coverage():
    """A lead read 0.2 mm above its nominal top from 40 reliable toe-half pixels is a
    lifted lead even when they are only 30 % of the foot. From fewer pixels the rise must
    clear the gap by three times their own spread: 0.2 mm from 8 pixels spread 10 µm is
    lifted, spread 50 µm or unknown it is not judged as one (the coverage rule: 40 %),
    nor is 0.1 mm spread 20 µm, nor anything from 4 pixels."""
    from smdinspect.inspect._reference import lead_top_mm
    from smdinspect.inspect._verdict import LEAD_FEW_PIXELS, LEAD_MIN_PIXELS

    u1, j, body = _u1("U1.3")

    def judge(n, spread=NAN, rise=0.2):
        top = lead_top_mm(u1) + rise
        m = JointMeasurement(j.id, (0.0, 0.0), 200, 0.5, max_mm=top, max_method="foot",
                             lead_mm=top, lead_n=n, lead_spread_mm=spread,
                             foot_reliable_fraction=0.3, toe_mm=0.01)
        return judge_joint(j, u1, m, body, InspectConfig()).verdict

    assert judge(2 * LEAD_MIN_PIXELS) is Verdict.LIFTED_LEAD
    assert judge(8, spread=0.010) is Verdict.LIFTED_LEAD
    assert judge(8) is not Verdict.LIFTED_LEAD
    assert judge(8, spread=0.050) is not Verdict.LIFTED_LEAD
    assert judge(8, spread=0.020, rise=0.1) is not Verdict.LIFTED_LEAD
    assert judge(LEAD_FEW_PIXELS - 1, spread=0.0) is not Verdict.LIFTED_LEAD


def test_a_gullwing_heel_is_judged_on_its_heel_fit_whatever_the_solder_area_coverage():
    """A gull-wing joint whose max is the heel meniscus fitted to enough reliable foot
    pixels, with its side region measured and agreeing, is judged at 30 % solder-area
    coverage: in the band it passes (the reason says what it was judged on), above it is
    excess (when the side strip's estimate agrees on both of the band's limits).
    Without the fit (a foot percentile), without the side reading, or under half the
    coverage rule's fraction it stays unreliable."""
    from smdinspect.inspect._measure import HEEL_FIT_MIN_PIXELS
    from smdinspect.inspect._reference import lead_top_mm

    u1, j, body = _u1("U1.3")
    inside = 0.5 * (j.min_height_mm + j.max_height_mm)

    nominal = lead_top_mm(u1)

    def judge(*, max_mm=inside, fraction=0.3, heel_n=4 * HEEL_FIT_MIN_PIXELS, side_mm=0.14,
              lead_mm=nominal, sparse_n=0, side_level_mm=NAN, glint=NAN):
        m = JointMeasurement(j.id, (0.0, 0.0), 400, fraction, max_mm=max_mm, u_max_mm=0.005,
                             max_method="foot", heel_fit_n=heel_n, side_mm=side_mm,
                             side_level_mm=side_level_mm,
                             foot_reliable_fraction=fraction, lead_mm=lead_mm, lead_n=5,
                             gap_sparse_mm=0.0, gap_sparse_n=sparse_n, gap_glint=glint,
                             gap_glint_neighbour="U1.2")
        return judge_joint(j, u1, m, body, InspectConfig())

    ok = judge()
    assert ok.verdict is Verdict.OK and "heel meniscus over 80 reliable foot pixels" in ok.reason
    above = j.max_height_mm + 0.1
    assert judge(max_mm=above, side_mm=0.5 * above).verdict is Verdict.EXCESS
    assert judge(max_mm=j.min_height_mm - 0.05, side_mm=0.05).verdict is Verdict.INSUFFICIENT
    # the side estimate (0.06 / 0.5 mm) below the minimum: a heel in the band is not a pass
    assert judge(side_mm=0.06).verdict is Verdict.UNRELIABLE
    # ... nor one in the band a heel above the maximum (a fit overshooting on few pixels)
    assert judge(max_mm=above).verdict is Verdict.UNRELIABLE
    # a gap to a neighbour too sparsely measured to read each path is read on its pooled
    # pixels (board level here); one whose path glints from foot to foot is not read
    assert judge(sparse_n=160).verdict is Verdict.OK
    assert judge(sparse_n=160, glint=0.8).verdict is Verdict.UNRELIABLE
    glinting = judge(glint=0.8)  # a glinting path beside paths that read board level
    assert glinting.verdict is Verdict.UNRELIABLE and "clipped white" in glinting.reason
    assert judge(heel_n=0).verdict is Verdict.UNRELIABLE               # a foot percentile only
    assert judge(side_mm=float("nan")).verdict is Verdict.UNRELIABLE   # dry foot not testable
    assert judge(fraction=0.15).verdict is Verdict.UNRELIABLE          # < half of 40 %
    # a raised lead on too few toe pixels for the lifted-lead rule: not a heel reading;
    # a buried one (the solder level beside it up to its underside) is excess; the side
    # strip's percentile alone (the raised lead's blurred edge) does not bury it
    assert judge(lead_mm=nominal + 0.2, max_mm=nominal + 0.22).verdict is Verdict.UNRELIABLE
    assert judge(lead_mm=j.max_height_mm + 0.05, max_mm=j.max_height_mm + 0.06,
                 side_mm=j.max_height_mm,
                 side_level_mm=j.max_height_mm).verdict is Verdict.EXCESS
    assert judge(lead_mm=j.max_height_mm + 0.05, max_mm=j.max_height_mm + 0.06,
                 side_mm=j.max_height_mm, side_level_mm=0.01).verdict is Verdict.UNRELIABLE
    assert judge(fraction=0.5, heel_n=0).verdict is Verdict.OK          # the coverage rule as before


def test_a_footprint_measured_at_board_level_is_a_missing_part_however_little_is_reliable():
    """A missing SOIC-8 leaves the bare solder mask under its footprint: mostly
    unreliable (17 % here, a tuning board), and every reliable pixel at board level.
    Too little to check a body, enough to say there is none: `component_missing`. With
    too few reliable pixels, or with them at body height, it stays `unreliable`."""
    from smdinspect.inspect._measure import ComponentMeasurement
    from smdinspect.inspect._verdict import MIN_EVIDENCE_PIXELS, judge_component

    u1 = load_board(DEMO).component("U1")
    cfg = InspectConfig()

    def judged(reliable, present, n=40_000):
        m = ComponentMeasurement("U1", reliable, present, NAN, (NAN, NAN), NAN, 0.0, n)
        return judge_component(u1, m, cfg)

    r = judged(0.17, 0.0003)
    assert r.verdict is Verdict.COMPONENT_MISSING and "no body there" in r.reason
    assert judged(0.17, 0.9).verdict is Verdict.UNRELIABLE            # a body, seen in part
    n_few = int(0.9 * MIN_EVIDENCE_PIXELS / 0.17)
    assert judged(0.17, 0.0, n=n_few).verdict is Verdict.UNRELIABLE   # too little evidence
    assert judged(0.9, 0.0).verdict is Verdict.COMPONENT_MISSING       # the usual rule


def test_a_colour_cue_that_makes_most_pads_bare_is_not_used():
    """A reference that makes most pads of a board look bare describes their solder (a
    tinted solder, the lighting), not the finish: the colour then decides nothing."""
    from smdinspect.inspect._measure import _check_colour_cue

    cfg = InspectConfig()

    def joints(fractions):
        return {f"J{i}": JointMeasurement(f"J{i}", (0.0, 0.0), 100, 0.8, bare_fraction=b)
                for i, b in enumerate(fractions)}

    few = joints([0.95, 0.1, 0.05, 0.2, NAN, 0.0])
    _check_colour_cue(few, cfg)
    assert few["J0"].bare_fraction == 0.95 and few["J1"].bare_fraction == 0.1
    most = joints([0.95, 0.9, 0.85, 0.2, 0.7])
    _check_colour_cue(most, cfg)
    assert all(math.isnan(m.bare_fraction) for m in most.values())


def test_an_extrapolated_meniscus_passes_only_on_what_its_own_pixels_show(c2):
    # Test seed demo 10005: a 1206 fillet fitted to pixels reaching 48 µm (extrapolated
    # 166 µm at 23 % reach) passed because the solder area's percentile, which also holds
    # the end cap's bled edge the robust fit rejected, read 1178 µm.
    joint = c2[0]
    kw = dict(max_mm=joint.nominal_height_mm, max_method="meniscus", fillet_reach=0.15,
              observed_mm=joint.min_height_mm + 0.3)
    r = _judge(c2, fit_seen_mm=0.048, **kw)
    assert r.verdict is Verdict.UNRELIABLE and "seen 48 µm" in r.reason
    assert _judge(c2, fit_seen_mm=joint.min_height_mm + 0.01, **kw).verdict is Verdict.OK


def test_a_shift_counts_only_beyond_the_slack_of_the_body_position():
    """A body whose blob's ends could not be told apart is placed at its midpoint with a
    slack along that axis (``offset_slack_mm``, the part's own x and y): a displacement
    is a shift only by what it shows beyond the slack, and only along that axis."""
    from smdinspect.inspect._verdict import _misplaced

    comp = load_board(DEMO).component("U1")
    a = math.radians(comp.rotation_deg)
    along_x = np.array([math.cos(a), math.sin(a)])      # the part's own x: across its leads
    off = 0.45 * along_x                                 # leads ~76 % over their pads' sides
    assert "over the pad's side" in _misplaced(comp, off)
    assert _misplaced(comp, off, (0.3, 0.0)) == ""       # could be 0.15 mm: within the limit
    assert "over the pad's side" in _misplaced(comp, off, (0.0, 0.3))   # slack along y only


def test_a_heel_estimated_from_the_side_strip_never_passes_silently():
    """A gull-wing whose heel is not measured has its height inferred from the strip
    beside the lead (÷ side_fillet_ratio, a calibration): a pass on it says so in the
    reason and in max_method (issue 12: an extrapolation never passes silently); a
    failure on it keeps its verdict."""
    comp, joint, body = _u1("U1.3")
    cfg = InspectConfig()

    def judge(side_mm, method="side"):
        m = JointMeasurement(joint.id, (0.0, 0.0), 200, 0.8, max_mm=side_mm / cfg.side_fillet_ratio,
                             u_max_mm=0.005, max_method=method, side_mm=side_mm, lead_n=30)
        return judge_joint(joint, comp, m, body, cfg)

    good = judge(joint.nominal_height_mm * cfg.side_fillet_ratio)
    assert good.verdict is Verdict.OK
    assert "ESTIMATED from the side fillet" in good.reason and "heel is not measured" in good.reason
    assert good.max_method.startswith("side (estimated")
    low = judge(0.5 * joint.min_height_mm * cfg.side_fillet_ratio)
    assert low.verdict is Verdict.INSUFFICIENT and low.max_method.startswith("side (estimated")
    # a measured heel passes plainly
    foot = judge(joint.nominal_height_mm * cfg.side_fillet_ratio, method="foot")
    assert foot.verdict is Verdict.OK and "ESTIMATED" not in foot.reason


@pytest.mark.parametrize("heel_bare, bare, verdict", [
    (0.65, 0.61, Verdict.MISSING), (0.3, 0.61, Verdict.OK), (0.51, 0.21, Verdict.OK),
    (NAN, NAN, Verdict.OK)])
def test_a_gullwing_heel_read_over_a_bare_pad_is_missing(heel_bare, bare, verdict):
    """A heel fillet wets the pad beside the lead by the heel. Tuning demo 259 U1.6 (no
    solder, ENIG): 65 % of that pad looked bare while the foot's heel fit read 272 µm
    (the knee's blurred edge) and the joint passed; its whole visible pad was 61 % bare,
    under the 80 % that calls a pad missing whatever its heights. Good joints on 128
    tuning boards look at most 31 % bare there; the heel region alone is few pixels, and
    a good joint read 51 % bare there with 21 % over its pad (test demo 10097 U1.3), so
    the pad must look mostly bare too. Without a colour cue (NaN) the heights decide."""
    comp, joint, body = _u1("U1.6")
    m = JointMeasurement(joint.id, (0.0, 0.0), 200, 0.6, max_mm=0.272, max_method="foot",
                         bare_fraction=bare,
                         heel_bare_fraction=heel_bare)
    r = judge_joint(joint, comp, m, body, InspectConfig())
    assert r.verdict is verdict, r.reason
    if verdict is Verdict.MISSING:
        assert "by the heel look bare" in r.reason


@pytest.mark.parametrize("lead_n, verdict", [(0, Verdict.UNRELIABLE), (30, Verdict.OK)])
def test_a_side_estimate_needs_the_lead_measured(lead_n, verdict):
    """The heel estimated from the side fillet assumes the lead sits on its pad. With
    none of the foot's toe half measured the lead's height is unknown, and a lifted
    lead's blurred edge reads on the side strip like a fillet (tuning dense 260 U2.2,
    lifted 0.26 mm, 1 % of its foot reliable, passed at an estimated 376 µm): not
    judged. With the lead measured at its nominal height the estimate passes, flagged."""
    from smdinspect.inspect._reference import lead_top_mm

    comp, joint, body = _u1("U1.2")
    est = joint.nominal_height_mm
    m = JointMeasurement(joint.id, (0.0, 0.0), 200, 0.5, max_mm=est, max_method="side",
                         side_mm=est * InspectConfig().side_fillet_ratio, lead_n=lead_n,
                         lead_mm=lead_top_mm(comp) if lead_n else NAN,
                         foot_reliable_fraction=0.3 if lead_n else 0.01)
    r = judge_joint(joint, comp, m, body, InspectConfig())
    assert r.verdict is verdict, r.reason
    assert ("lifted lead is not ruled out" in r.reason) == (verdict is Verdict.UNRELIABLE)


def test_a_shift_the_placement_may_hide_is_never_a_silent_pass():
    """A part read in place, but within 2σ of the board's placement at it of the side
    overhang limit, is `unreliable` ("may be shifted"), not `ok`: test dense 10150's
    SOIC-16, 70 % over its pads, read at 52 % less its slack on a board placed by a
    compact cluster of chips (σ 72 µm at the SOIC). A well-placed board changes nothing,
    and a shift beyond the limit as read stays `component_shifted`."""
    from smdinspect.inspect._measure import ComponentMeasurement
    from smdinspect.inspect._verdict import _misplaced, judge_component

    u1 = load_board(DEMO).component("U1")
    cfg = InspectConfig()
    across = np.array([1.0, 0.0]) if abs(u1.joints[0].outward[1]) > 0.5 else np.array([0.0, 1.0])
    limit = next(d for d in np.arange(0.0, 1.0, 0.005) if _misplaced(u1, d * across))

    def judged(shift, sigma):
        cov = None if sigma is None else np.eye(2) * sigma ** 2
        m = ComponentMeasurement("U1", 0.9, 1.0, 1.5, tuple(shift * across), 0.0, 0.0, 40_000,
                                 offset_cov_mm2=cov)
        return judge_component(u1, m, cfg)

    r = judged(0.8 * limit, 0.06)
    assert r.verdict is Verdict.UNRELIABLE and "may be shifted" in r.reason, r.reason
    assert judged(0.8 * limit, None).verdict is Verdict.OK
    assert judged(0.8 * limit, 0.005).verdict is Verdict.OK
    assert judged(0.1 * limit, 0.06).verdict is Verdict.OK
    assert judged(1.1 * limit, 0.06).verdict is Verdict.COMPONENT_SHIFTED
    # its joints are not passed either: the pad may have lost its lead
    from smdinspect.inspect._verdict import judge_joint

    j = u1.joints[0]
    jm = JointMeasurement(j.id, (0.0, 0.0), 200, 0.9, max_mm=j.nominal_height_mm,
                          max_method="foot")
    assert judge_joint(j, u1, jm, judged(0.8 * limit, None), cfg).verdict is Verdict.OK
    got = judge_joint(j, u1, jm, r, cfg)
    assert got.verdict is Verdict.UNRELIABLE and "may be shifted" in got.reason, got.reason
