"""Detection is monotonic in a defect's severity (issue 12, item 2).

For every defect class with a severity parameter (:data:`SEVERITY`), hypothesis draws a
part of the right kind, two severities s < s' (s' the worse) in the class's drawn range,
the board seed (textures, noise, holes), the finish and a small rotation. The same board
is rendered with the defect at s and at s', each true height map is inspected (3 µm
noise, 5 % holes: the verdict rules without shape from focus, as the benchmark's
``--mode truth``), and a defect *detected* at s must be detected at s'.

Detected: a defect verdict (anything but ``ok`` and ``unreliable``, the wrong class
included) on a joint the defect touches: the joint itself, a bridge's partner, every
joint of a tombstoned or shifted part. Each case is a crop around the part, judged at
the scene's true placement (registration needs the board's layout, out of view here), so
a render and an inspection take 0.03-0.7 s. An anchor test checks that the worst end of
each range, past the IPC-A-610 Class 2 limit, is detected, so the property cannot hold
by never flagging.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from smdinspect.inspect import load_board
from smdinspect.synth._board_scene import FINISHES, SEVERITY

from ._synthetic import DEMO, DENSE, inspect_placed, part_crop, truth_surface

#: Parts of the right kind per class, as (board, part, joint carrying the defect): SOIC-8
#: and TSSOP-8 leads, chips from 0402 to 1206 on both boards.
CANDIDATES = {
    "lifted_lead": [(DEMO, "U1", "U1.6"), (DEMO, "U1", "U1.1"), (DENSE, "U2", "U2.3")],
    "tombstone": [(DEMO, "C1", "C1.1"), (DEMO, "R2", "R2.2"), (DEMO, "R3", "R3.1"),
                  (DEMO, "C2", "C2.2"), (DENSE, "R3", "R3.1")],
    "insufficient": [(DEMO, "U1", "U1.4"), (DEMO, "R2", "R2.1"), (DEMO, "C1", "C1.2"),
                     (DEMO, "C2", "C2.1"), (DENSE, "R1", "R1.2")],
    "excess": [(DEMO, "U1", "U1.8"), (DEMO, "R2", "R2.2"), (DEMO, "C1", "C1.1"),
               (DEMO, "C2", "C2.1"), (DENSE, "U2", "U2.6")],
    "bridge": [(DEMO, "U1", "U1.2"), (DEMO, "R1", "R1.1"), (DEMO, "C2", "C2.1"),
               (DENSE, "U2", "U2.7"), (DENSE, "C3", "C3.2")],
    "component_shifted": [(DEMO, "R1", "R1.1"), (DEMO, "C2", "C2.1"), (DEMO, "C1", "C1.2"),
                          (DEMO, "U1", "U1.1"), (DENSE, "R2", "R2.1")],
}
assert set(CANDIDATES) == set(SEVERITY)


def _detected(board_file, ref, jid, cls, value, *, seed, finish="enig", rotate_deg=0.0,
              extra=None):
    """(detected, {joint: (verdict, reason)} of the joints the defect touches, labels)."""
    margin = 0.8
    if cls == "component_shifted":
        # the crop holds the part where it stands: a body running out of the field is
        # not judged (rule 0)
        part = load_board(board_file).component(ref)
        margin += max(part.body_length_mm, part.body_width_mm)
    board, off, shape = part_crop(board_file, ref, rotate_deg=rotate_deg, margin_mm=margin)
    params = {jid: {SEVERITY[cls]["param"]: value, **(extra or {})}}
    surface, labels, board = truth_surface(board, f"{jid}:{cls}", seed=seed, params=params,
                                           offset_mm=off, rotate_deg=rotate_deg, shape=shape,
                                           finish=finish)
    result = inspect_placed(surface, board, labels)
    touched = {j["id"] for j in labels["joints"] if j["class"] != "ok" or "bridged_by" in j}
    got = {j.id: j for j in result.joints if j.id in touched}
    assert set(got) == touched
    return (any(j.verdict.is_defect for j in got.values()),
            {k: (j.verdict.value, j.reason) for k, j in sorted(got.items())}, labels)


def _worst_first(cls, a, b):
    """(s, s') with s' the worse severity of the two."""
    lo, hi = sorted((a, b))
    return (lo, hi) if SEVERITY[cls]["direction"] > 0 else (hi, lo)


@st.composite
def _case(draw, cls):
    board_file, ref, jid = draw(st.sampled_from(CANDIDATES[cls]))
    lo, hi = SEVERITY[cls]["range"]
    values = st.floats(lo, hi, allow_nan=False, allow_infinity=False)
    a, b = draw(values), draw(values)
    assume(a != b)
    extra = {}
    if cls == "excess":
        extra["style"] = draw(st.sampled_from(("cap", "convex")))
    if cls == "component_shifted":
        extra["direction"] = draw(st.sampled_from((1, -1)))
    return dict(board_file=board_file, ref=ref, jid=jid, pair=(a, b), extra=extra,
                seed=draw(st.integers(0, 2**16)), finish=draw(st.sampled_from(sorted(FINISHES))),
                rotate_deg=draw(st.floats(-5.0, 5.0, allow_nan=False)))


@pytest.mark.parametrize("cls", sorted(SEVERITY))
@settings(max_examples=24, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.differing_executors])
@given(data=st.data())
def test_detection_is_monotonic_in_severity(cls, data):
    # differing_executors: one @given body runs once per class (parametrize); the draws
    # do not depend on which, so the check's concern (state kept between runs) is moot.
    c = data.draw(_case(cls), label="case")
    s, s_worse = _worst_first(cls, *c["pair"])
    kw = dict(seed=c["seed"], finish=c["finish"], rotate_deg=c["rotate_deg"], extra=c["extra"])
    at_s, why_s, _ = _detected(c["board_file"], c["ref"], c["jid"], cls, s, **kw)
    event("detected at s" if at_s else "not detected at s: nothing to compare")
    if not at_s:
        return
    at_worse, why_worse, _ = _detected(c["board_file"], c["ref"], c["jid"], cls, s_worse, **kw)
    assert at_worse, (f"{cls} on {c['jid']}: detected at {SEVERITY[cls]['param']}={s:.4f} "
                      f"{why_s}, not at the worse {s_worse:.4f} {why_worse}")


@pytest.mark.parametrize("cls, board_file, ref, jid",
                         [(cls, *c) for cls, cs in sorted(CANDIDATES.items()) for c in cs])
def test_worst_end_of_the_range_is_detected(cls, board_file, ref, jid):
    spec = SEVERITY[cls]
    lo, hi = spec["range"]
    worst = hi if spec["direction"] > 0 else lo
    detected, why, labels = _detected(board_file, ref, jid, cls, worst, seed=0)
    lab = {j["id"]: j for j in labels["joints"]}
    assert lab[jid]["beyond_limit"], lab[jid]
    assert detected, (cls, jid, worst, why)
