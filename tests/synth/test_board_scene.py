"""Synthetic boards: placement, defects against the ok board, truth labels, determinism."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.inspect._board import load_board
from smdinspect.synth._board_scene import DEFECTS, board_scene, parse_defects
from smdinspect.synth._scene import Scene

REFS = Path(__file__).resolve().parents[2] / "references"
P = 0.03          # mm/px: the demo board fits ~510 px
PLACE = dict(offset_mm=(0.6, -0.4), rotate_deg=3.0, pixel_size_mm=P, seed=3)


@pytest.fixture(scope="module")
def demo():
    return load_board(REFS / "demo_board.json")


@pytest.fixture(scope="module")
def ok_scene(demo):
    return board_scene(demo, **PLACE)


def _to_px(labels, pts_board):
    T = np.array(labels["placement"]["board_to_world"])
    pts = np.asarray(pts_board, float).reshape(-1, 2)
    w = pts @ T[:2, :2].T + T[:2, 2]
    h = labels["image_shape"][0]
    p = labels["pixel_size_mm"]
    return np.column_stack([w[:, 0] / p, h - 1 - w[:, 1] / p])      # (col, row)


def _mask(labels, polys, minus=()):
    m = np.zeros(labels["image_shape"], np.uint8)
    for poly in polys:
        cv2.fillPoly(m, [np.round(_to_px(labels, poly) * 16).astype(np.int32)], 1, shift=4)
    for poly in minus:
        cv2.fillPoly(m, [np.round(_to_px(labels, poly) * 16).astype(np.int32)], 0, shift=4)
    return m.astype(bool)


def _h_at(scene, labels, pt_board):
    c, r = _to_px(labels, pt_board)[0]
    return float(scene.height_mm[int(round(r)), int(round(c))])


def _visible_pad(board, labels, jid):
    """Pad minus the part's body and the termination over it (the solder seen from above)."""
    j = board.joint(jid)
    comp = board.component(j.component)
    return _mask(labels, [j.polygon_mm],
                 minus=[comp.body_polygon_mm(), comp.termination_polygon_mm(jid)])


def _label(labels, jid):
    return next(e for e in labels["joints"] if e["id"] == jid)


def test_ok_board_scene_and_placement(demo, ok_scene):
    scene, labels = ok_scene
    assert isinstance(scene, Scene)
    assert scene.is_color and scene.specular is not None
    assert scene.height_mm.dtype == np.float32
    assert labels["board"] == "demo_board" and labels["seed"] == 3
    assert labels["board_file"].endswith("demo_board.json")
    h, w = scene.shape
    assert labels["image_shape"] == [h, w]
    # Placement: board centre at image centre + offset, rotation as asked.
    T = np.array(labels["placement"]["board_to_world"])
    a = np.radians(3.0)
    np.testing.assert_allclose(T[:2, :2], [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    centre = T[:2, :2] @ np.array(demo.size_mm) / 2 + T[:2, 2]
    np.testing.assert_allclose(centre, [(w - 1) / 2 * P + 0.6, (h - 1) / 2 * P - 0.4])
    assert labels["placement"]["offset_mm"] == [0.6, -0.4]
    assert labels["placement"]["rotate_deg"] == 3.0
    # Every joint labelled ok, in view, and its rendered fillet inside its band.
    assert [e["id"] for e in labels["joints"]] == [j.id for j in demo.joints()]
    for j in demo.joints():
        e = _label(labels, j.id)
        assert e["class"] == "ok" and e["in_view"]
        assert j.min_height_mm < e["true_height_mm"] < j.max_height_mm, j.id
        # The map itself shows it in the visible solder area of the projected pad.
        vis = _visible_pad(demo, labels, j.id)
        hmax = float(scene.height_mm[vis].max())
        assert j.min_height_mm < hmax < j.max_height_mm + 0.01, (j.id, hmax)
    # Body tops where the board file puts the parts; bare mask near zero.
    for comp in demo.components:
        top = _h_at(scene, labels, [comp.x_mm, comp.y_mm])
        assert top == pytest.approx(comp.body_height_mm + (comp.standoff_mm if comp.kind ==
                                    "chip" else 0.0), abs=0.04), comp.ref
    mask_h = _h_at(scene, labels, [demo.size_mm[0] / 2, 0.3])
    assert abs(mask_h) < 0.03
    assert 0 <= scene.albedo.min() and scene.albedo.max() <= 1


def test_textures_weak_mask_grainy_solder(demo, ok_scene):
    scene, labels = ok_scene
    lum = scene.albedo.mean(axis=2)
    solder = np.zeros(scene.shape, bool)
    for j in demo.joints():
        solder |= _visible_pad(demo, labels, j.id)
    solder &= scene.height_mm > 0.02
    # Fine (high-pass) texture contrast, what a focus measure sees.
    fine = lum - cv2.GaussianBlur(lum, (0, 0), 3.0)
    bare = (np.abs(scene.height_mm) < 0.005).astype(np.uint8)
    bare = cv2.erode(bare, np.ones((9, 9), np.uint8)).astype(bool)
    assert bare.mean() > 0.3
    rel_mask = fine[bare].std() / lum[bare].mean()
    rel_solder = fine[solder].std() / lum[solder].mean()
    assert 0.02 < rel_mask < 0.12           # weakly textured, not flat
    assert rel_solder > 2 * rel_mask         # solder grain is what SFF locks onto
    assert scene.specular[solder].mean() > 0.6 > np.median(scene.specular[bare]) + 0.3


@pytest.mark.parametrize("jid", ["R3.1", "U1.4"])
def test_insufficient_and_excess(demo, ok_scene, jid):
    scene0, lab0 = ok_scene
    j = demo.joint(jid)
    s_ins, l_ins = board_scene(demo, defects={jid: "insufficient"}, **PLACE)
    s_exc, l_exc = board_scene(demo, defects={jid: "excess"}, **PLACE)
    vis = _visible_pad(demo, lab0, jid)
    assert _label(l_ins, jid)["class"] == "insufficient"
    assert 0 < _label(l_ins, jid)["true_height_mm"] < j.min_height_mm
    assert float(s_ins.height_mm[vis].max()) < j.min_height_mm
    assert _label(l_exc, jid)["true_height_mm"] > j.max_height_mm + 0.05
    assert float(s_exc.height_mm[vis].max()) > j.max_height_mm + 0.03
    # Nothing else changed.
    other = ~_mask(lab0, [demo.component(j.component).body_polygon_mm()] +
                   [q.polygon_mm for q in demo.component(j.component).joints])
    other &= ~cv2.dilate(other.astype(np.uint8) ^ 1, np.ones((9, 9), np.uint8)).astype(bool)
    np.testing.assert_array_equal(s_ins.height_mm[other], scene0.height_mm[other])


def test_missing_joint_leaves_bare_pad(demo, ok_scene):
    scene0, lab0 = ok_scene
    s, lab = board_scene(demo, defects={"R1.2": "missing", "U1.2": "missing"}, **PLACE)
    for jid in ("R1.2", "U1.2"):
        assert _label(lab, jid)["true_height_mm"] == 0.0
        vis = _visible_pad(demo, lab0, jid)
        assert float(np.percentile(s.height_mm[vis], 95)) < 0.01
        assert float(np.percentile(scene0.height_mm[vis], 95)) > 0.1
        # Bare ENIG pad: yellow (red > blue) where the solder used to be.
        rgb = s.albedo[vis].mean(axis=0)
        assert rgb[0] > 1.5 * rgb[2]


@pytest.mark.parametrize("jid, partner", [("U1.4", "U1.3"), ("R2.1", "R2.2")])
def test_bridge_raises_the_gap(demo, ok_scene, jid, partner):
    scene0, lab0 = ok_scene
    s, lab = board_scene(demo, defects={jid: "bridge"}, **PLACE)
    e = _label(lab, jid)
    assert e["class"] == "bridge" and e["bridge_to"] == partner
    assert _label(lab, partner)["bridged_by"] == jid
    assert _label(lab, partner)["class"] == "ok"
    a, b = demo.joint(jid), demo.joint(partner)
    comp = demo.component(a.component)
    # The gap between the two pads (outside the part) is mask in the ok board and
    # solder well above it with the bridge.
    gap = np.zeros(lab0["image_shape"], bool)
    ca, cb = np.array(a.center_mm), np.array(b.center_mm)
    for t in np.linspace(0.0, 1.0, 41):
        for side in np.linspace(-1.5, 1.5, 61):
            pt = ca + t * (cb - ca) + side * np.array([-(cb - ca)[1], (cb - ca)[0]]) / \
                np.hypot(*(cb - ca))
            c, r = np.round(_to_px(lab0, pt)[0]).astype(int)
            gap[r, c] = True
    keep = ~_mask(lab0, [comp.body_polygon_mm(), a.polygon_mm, b.polygon_mm] +
                  [comp.termination_polygon_mm(q.id) for q in comp.joints])
    gap &= keep
    assert float(scene0.height_mm[gap].max()) < 0.05
    assert float(s.height_mm[gap].max()) > 0.1


def test_lifted_lead(demo, ok_scene):
    scene0, lab0 = ok_scene
    jid = "U1.6"
    s, lab = board_scene(demo, defects={jid: "lifted_lead"}, **PLACE)
    j = demo.joint(jid)
    comp = demo.component("U1")
    lead = comp.lead
    # Middle of the foot: heel + foot/2 outward from the body, on the lead centre line.
    toe = lead["span_mm"] / 2
    foot_mid_local = comp.to_local([j.center_mm])[0]
    foot_mid_local[1] = np.sign(foot_mid_local[1]) * (toe - lead["foot_length_mm"] / 2)
    pt = comp.to_board([foot_mid_local])[0]
    h0, h1 = _h_at(scene0, lab0, pt), _h_at(s, lab, pt)
    assert h0 == pytest.approx(lead["solder_thickness_mm"] + lead["thickness_mm"], abs=0.01)
    assert 0.09 < h1 - h0 < 0.21
    e = _label(lab, jid)
    assert e["class"] == "lifted_lead" and 0 < e["true_height_mm"] < j.min_height_mm
    with pytest.raises(InputError, match="lifted_lead applies to gull-wing leads only"):
        board_scene(demo, defects={"R1.1": "lifted_lead"}, **PLACE)


def test_tombstone(demo, ok_scene):
    scene0, lab0 = ok_scene
    s, lab = board_scene(demo, defects={"R1.1": "tombstone"}, **PLACE)
    comp = demo.component("R1")
    area = _mask(lab0, [j.polygon_mm for j in comp.joints] + [comp.body_polygon_mm()])
    top0 = float(scene0.height_mm[area].max())
    top1 = float(s.height_mm[area].max())
    assert top0 == pytest.approx(comp.standoff_mm + comp.body_height_mm, abs=0.02)
    assert top1 > top0 + comp.body_length_mm / 2
    assert {_label(lab, j.id)["class"] for j in comp.joints} == {"tombstone"}
    assert _label(lab, "R1.1")["lifted"] is True
    # The lifted end's pad shows only a low bump, the other keeps its fillet.
    assert _label(lab, "R1.1")["true_height_mm"] < demo.joint("R1.1").min_height_mm
    assert _label(lab, "R1.2")["true_height_mm"] > demo.joint("R1.2").min_height_mm
    with pytest.raises(InputError, match="tombstone applies to 2-terminal chips only"):
        board_scene(demo, defects={"U1.1": "tombstone"}, **PLACE)


@pytest.mark.parametrize("ref", ["C1", "U1"])
def test_component_missing(demo, ok_scene, ref):
    scene0, lab0 = ok_scene
    comp = demo.component(ref)
    s, lab = board_scene(demo, defects={comp.joints[0].id: "component_missing"}, **PLACE)
    assert _h_at(scene0, lab0, [comp.x_mm, comp.y_mm]) > 0.8 * comp.body_height_mm
    assert abs(_h_at(s, lab, [comp.x_mm, comp.y_mm])) < 0.03
    for j in comp.joints:
        e = _label(lab, j.id)
        assert e["class"] == "component_missing"
        assert 0.03 < e["true_height_mm"] < 0.12          # reflowed solder bump only


@pytest.mark.parametrize("ref", ["R2", "U1"])
def test_component_shifted(demo, ok_scene, ref):
    scene0, lab0 = ok_scene
    comp = demo.component(ref)
    s, lab = board_scene(demo, defects={comp.joints[1].id: "component_shifted"}, **PLACE)
    shift = np.array(_label(lab, comp.joints[0].id)["shift_mm"])
    j = comp.joints[0]
    pad_w = float(np.ptp(comp.to_local(j.polygon_mm)[:, 0 if comp.kind == "gullwing" else 1]))
    # The termination (lead) overhangs the pad's side by 60–80 % of its width.
    term_w = comp.lead["width_mm"] if comp.kind == "gullwing" else comp.body_width_mm
    over = (np.hypot(*shift) - (pad_w - term_w) / 2) / term_w
    assert 0.59 < over < 0.81
    assert {_label(lab, q.id)["class"] for q in comp.joints} == {"component_shifted"}
    # The body now sits at the shifted place: its edge moved by the shift.
    d = shift / np.hypot(*shift)
    half = (abs(d @ comp.to_board([[comp.body_length_mm / 2, 0]])[0] - d @ [comp.x_mm,
            comp.y_mm]) if comp.kind == "gullwing" else comp.body_width_mm / 2)
    inside_new = np.array([comp.x_mm, comp.y_mm]) + d * (half + 0.5 * np.hypot(*shift))
    assert _h_at(scene0, lab0, inside_new) < 0.5 * comp.body_height_mm
    assert _h_at(s, lab, inside_new) > 0.8 * comp.body_height_mm


def test_same_seed_same_arrays_and_random_placement(demo):
    a, la = board_scene(demo, pixel_size_mm=0.06, seed=11, defects={"R3.1": "excess"})
    b, lb = board_scene(demo, pixel_size_mm=0.06, seed=11, defects={"R3.1": "excess"})
    assert np.array_equal(a.height_mm, b.height_mm)
    assert np.array_equal(a.albedo, b.albedo) and np.array_equal(a.specular, b.specular)
    assert la == lb
    offsets, rots = [], []
    for seed in range(6):
        s, lab = board_scene(demo, pixel_size_mm=0.08, seed=seed)
        off = lab["placement"]["offset_mm"]
        rot = lab["placement"]["rotate_deg"]
        assert max(abs(off[0]), abs(off[1])) <= 2.0 and abs(rot) <= 5.0
        # The default shape keeps every pad in view.
        assert all(e["in_view"] for e in lab["joints"])
        offsets.append(off)
        rots.append(rot)
    assert len({round(r, 6) for r in rots}) == 6
    assert np.std(np.array(offsets)) > 0.3


def test_a_replaced_board_keeps_its_texture(demo):
    """The same board (seed) at two placements shows the same texture under its parts:
    the solder-mask relief at a board point is the same wherever the board lies (a gauge
    study re-places one board; new texture under every joint counted against the gauge)."""
    kw = dict(pixel_size_mm=P, seed=5)
    a, la = board_scene(demo, offset_mm=(0.0, 0.0), rotate_deg=0.0, **kw)
    b, _ = board_scene(demo, offset_mm=(0.3, -0.15), rotate_deg=0.0, **kw)  # 10 and 5 px
    rows, cols = slice(150, 350), slice(150, 350)
    moved = (slice(155, 355), slice(160, 360))
    # (the same up to the rescaled spread and the drawn parts' sub-pixel edges)
    assert np.percentile(np.abs(b.height_mm[moved] - a.height_mm[rows, cols]), 98) < 2e-5
    assert np.percentile(np.abs(b.albedo[moved] - a.albedo[rows, cols]), 98) < 1e-3
    # turned 4°: the same board points, read through each placement (bilinear)
    from scipy.ndimage import map_coordinates

    c, lc = board_scene(demo, offset_mm=(0.0, 0.0), rotate_deg=4.0, **kw)
    pts = [[x, y] for x in np.linspace(2, 16, 57) for y in np.linspace(2, 10, 33)]
    pa, pc = _to_px(la, pts), _to_px(lc, pts)

    def read(scene, px):
        return map_coordinates(scene.height_mm, [px[:, 1], px[:, 0]], order=1)

    ha, hc, same = read(a, pa), read(c, pc), read(c, pa)
    mask = (ha < 0.005) & (hc < 0.005)  # bare solder mask (its relief is ±1.5 µm)
    assert mask.sum() > 300
    assert np.corrcoef(ha[mask], hc[mask])[0, 1] > 0.6       # the relief moved with it (0.77)
    assert abs(np.corrcoef(ha[mask], same[mask])[0, 1]) < 0.5  # not the same pixel's
    # a small field on part of the board shows the texture the whole field shows there
    d, ld = board_scene(demo, offset_mm=(-2.0, 1.0), rotate_deg=4.0, shape=(120, 200), **kw)
    rows, cols = np.mgrid[5:115:3, 5:195:3]
    pd = np.column_stack([cols.ravel(), rows.ravel()]).astype(float)
    T = np.array(ld["placement"]["board_to_world"])
    world = np.column_stack([pd[:, 0] * P, (119 - pd[:, 1]) * P])  # (col, row) -> mm
    board_pts = (world - T[:2, 2]) @ np.linalg.inv(T[:2, :2]).T
    hd, hc = read(d, pd), read(c, _to_px(lc, board_pts))
    mask = (hd < 0.005) & (hc < 0.005)
    assert mask.sum() > 300
    assert np.corrcoef(hd[mask], hc[mask])[0, 1] > 0.8  # the same relief (0.88)
    # moving the board by half a pixel does not blur its finest textures (resampled from
    # the pixel grid, it took 40 % of their Laplacian energy)
    from smdinspect.synth._board_scene import _Canvas

    def energy(canvas, name):
        lap = cv2.Laplacian(getattr(canvas, name), cv2.CV_32F)[20:-20, 20:-20]
        return float(np.mean(lap ** 2))

    here = _Canvas((300, 300), P, demo, (0.0, 0.0), 0.0, 5)
    half = _Canvas((300, 300), P, demo, (P / 2, P / 2), 0.0, 5)
    for name in ("n_fine", "n_grain", "n_med"):
        assert 0.9 < energy(half, name) / energy(here, name) < 1.1, name


def test_dense_board_all_ok_in_band():
    dense = load_board(REFS / "dense_board.json")
    scene, lab = board_scene(dense, pixel_size_mm=0.03, seed=5,
                             defects={"U2.3": "bridge", "C3.1": "tombstone"})
    assert len(lab["joints"]) == 36
    for j in dense.joints():
        e = _label(lab, j.id)
        if e["class"] == "ok" and "bridged_by" not in e:
            assert j.min_height_mm < e["true_height_mm"] < j.max_height_mm, j.id
    assert _label(lab, "U2.3")["bridge_to"] in ("U2.2", "U2.4")


def test_board_path_and_argument_errors(demo, tmp_path):
    s, lab = board_scene(REFS / "demo_board.json", pixel_size_mm=0.1, seed=1)
    assert lab["board"] == "demo_board"
    with pytest.raises(InputError, match="pixel_size_mm must be a number > 0; got -0.01"):
        board_scene(demo, pixel_size_mm=-0.01)
    with pytest.raises(InputError, match="shape must be at least"):
        board_scene(demo, shape=(8, 8))
    with pytest.raises(InputError, match="seed must be an integer >= 0"):
        board_scene(demo, seed=-1)
    with pytest.raises(InputError, match="unknown joint 'R9.1' on board demo_board; valid "
                                         "ids are like U1.1, U1.2"):
        board_scene(demo, defects={"R9.1": "missing"})
    with pytest.raises(InputError, match="too large"):
        board_scene(demo, pixel_size_mm=0.0005)
    with pytest.raises(InputError, match="board must be a Board"):
        board_scene(42)


def test_parse_defects(demo):
    assert parse_defects("R3.1:insufficient, U1.4:bridge") == {"R3.1": "insufficient",
                                                               "U1.4": "bridge"}
    assert parse_defects("") == {} and parse_defects(None) == {}
    assert parse_defects("R3.1:Excess", board=demo) == {"R3.1": "excess"}
    with pytest.raises(InputError, match=r"unknown defect class 'cracked' for joint R3\.1; "
                                         r"classes: ok, missing, insufficient"):
        parse_defects("R3.1:cracked")
    with pytest.raises(InputError, match=r"bad defect 'R3\.1'"):
        parse_defects("R3.1")
    with pytest.raises(InputError, match=r"bad defect 'R3:missing'"):
        parse_defects("R3:missing")
    with pytest.raises(InputError, match="given two defects"):
        parse_defects("R3.1:missing,R3.1:excess")
    with pytest.raises(InputError, match=r"unknown joint 'X1\.1' on board demo_board"):
        parse_defects("X1.1:missing", board=demo)
    with pytest.raises(InputError, match="component R3: tombstone applies to the whole "
                                         "component and cannot be combined"):
        parse_defects("R3.1:tombstone,R3.2:missing", board=demo)
    assert set(DEFECTS) == {"ok", "missing", "insufficient", "excess", "bridge",
                            "lifted_lead", "tombstone", "component_missing",
                            "component_shifted"}


def test_custom_geometry_polygon_pads_and_unknown_package():
    from smdinspect.inspect._board import board_from_dict

    data = {
        "schema": "smdinspect-board", "version": 1, "name": "custom", "units": "mm",
        "size_mm": [6.0, 4.0], "thickness_mm": 1.0,
        "components": [
            {"ref": "R1", "package": "0805", "x_mm": 1.6, "y_mm": 2.0, "rotation_deg": 0.0,
             "pads": [
                 {"number": "1", "polygon_mm": [[-1.45, -0.7], [-0.45, -0.7], [-0.45, 0.7],
                                                [-1.2, 0.7], [-1.45, 0.45]]},
                 {"number": "2", "x_mm": 0.95, "y_mm": 0.0, "length_mm": 1.0,
                  "width_mm": 1.4}]},
            {"ref": "Q1", "package": "SOT-X", "kind": "gullwing", "x_mm": 4.4, "y_mm": 2.0,
             "rotation_deg": 30.0,
             "body": {"length_mm": 1.6, "width_mm": 1.2, "height_mm": 0.9,
                      "standoff_mm": 0.05},
             "lead": {"width_mm": 0.3, "thickness_mm": 0.12, "foot_length_mm": 0.35,
                      "span_mm": 2.4, "exit_height_mm": 0.45},
             "pads": [{"number": "1", "x_mm": -0.5, "y_mm": -1.05, "length_mm": 0.7,
                       "width_mm": 0.45},
                      {"number": "2", "x_mm": 0.5, "y_mm": -1.05, "length_mm": 0.7,
                       "width_mm": 0.45},
                      {"number": "3", "x_mm": 0.0, "y_mm": 1.05, "length_mm": 0.7,
                       "width_mm": 0.45}]},
        ],
    }
    board = board_from_dict(data, source="custom")
    scene, lab = board_scene(board, pixel_size_mm=0.02, offset_mm=(0, 0), rotate_deg=0,
                             seed=2, defects={"Q1.3": "excess", "Q1.1": "bridge"})
    by_id = {e["id"]: e for e in lab["joints"]}
    for j in board.joints():
        e = by_id[j.id]
        if e["class"] == "excess":
            assert e["true_height_mm"] > j.max_height_mm
        else:
            assert j.min_height_mm < e["true_height_mm"] < j.max_height_mm, j.id
    assert by_id["Q1.1"]["bridge_to"] == "Q1.2"
    top = _h_at(scene, lab, [4.4, 2.0])
    assert top == pytest.approx(0.9, abs=0.03)


def test_arc_fillet_is_a_circular_arc_from_toe_to_end_face():
    """The constant-curvature meniscus: through (L, 0) and (0, F), one radius everywhere,
    a wedge at curvature 0, the quarter circle when F = L at curvature 1, never rising
    above F or dipping below the pad."""
    from smdinspect.inspect._geometry import arc_fillet

    s = np.linspace(0.0, 1.0, 201)
    np.testing.assert_allclose(arc_fillet(s, 0.3, 0.4, 0.0), 0.3 * (1 - s), atol=1e-12)
    q = arc_fillet(s, 0.3, 0.3, 1.0)   # quarter circle of radius 0.3 centred on (L, F)
    np.testing.assert_allclose(q, 0.3 - np.sqrt(0.3 ** 2 - (0.3 - s * 0.3) ** 2), atol=1e-9)
    for F, L, k in ((0.2, 0.4, 1.0), (0.4, 0.2, 0.7), (0.3, 0.35, 0.4)):
        z = arc_fillet(s, F, L, k)
        assert z[0] == pytest.approx(F, abs=1e-9) and z[-1] == pytest.approx(0.0, abs=1e-9)
        assert np.all(np.diff(z) <= 1e-12) and z.min() >= 0.0 and z.max() <= F + 1e-12
        # one circle fits every point: algebraic circle fit x² + z² + a·x + b·z + c = 0
        x = s * L
        A = np.column_stack([x, z, np.ones_like(x)])
        sol, *_ = np.linalg.lstsq(A, -(x ** 2 + z ** 2), rcond=None)
        cx, cz = -sol[0] / 2, -sol[1] / 2
        r = np.hypot(x - cx, z - cz)
        assert np.ptp(r) < 1e-6 * r.mean()
        assert r.mean() == pytest.approx((L * L + F * F) / (2 * min(F, L)) / k, rel=1e-6)
        assert cz > z.max()   # the centre over the solder's free side: a concave meniscus


def test_arc_fillets_keep_the_fillet_height_and_change_the_profile(demo, ok_scene):
    scene0, lab0 = ok_scene
    scene1, lab1 = board_scene(demo, fillet_curvature=(1.0, 1.0), **PLACE)
    for jid in ("R1.1", "C1.2", "R3.2"):
        # the label is the highest pixel: the arc, vertical at the face, has fallen a
        # little by the pixel next to it (a 1206's 0.71 mm reads 0.69 at 30 µm/px)
        F1 = _label(lab1, jid)["true_height_mm"]
        assert F1 == pytest.approx(_label(lab0, jid)["true_height_mm"], rel=0.05)
        vis = _visible_pad(demo, lab0, jid)
        assert scene1.height_mm[vis].max() <= F1 + 1e-6
        assert (np.abs(scene1.height_mm[vis] - scene0.height_mm[vis]) > 0.02).mean() > 0.2, jid
    assert scene1.meta["fillet_curvature"] == [1.0, 1.0]
    for bad in ((0.5, 1.5), (0.8, 0.2), "x"):
        with pytest.raises(InputError, match="fillet_curvature"):
            board_scene(demo, fillet_curvature=bad, **PLACE)


def test_case_gather_stack_photographs_a_case_with_its_own_imaging(tmp_path):
    """A randomised case through the independent gather model: the case's sensor, a PSF
    and vignetting drawn from a stream of its own (the same case, the same frames), and
    the board sharpest in the frame focused on it."""
    import json

    from smdinspect.synth._board_scene import (case_gather_stack, case_imaging,
                                               random_board_case, scene_kwargs)

    case = random_board_case(load_board(REFS / "demo_board.json"), 10001)
    scene, _ = board_scene(case["board"], **scene_kwargs(case))
    z = [0.0, 0.6, 1.2]
    a = case_gather_stack(case, scene, z, tmp_path / "a")
    b = case_gather_stack(case, scene, z, tmp_path / "b")
    assert len(a) == 3
    for k in range(3):
        np.testing.assert_array_equal(a.read_frame(k), b.read_frame(k))
    meta = json.loads((tmp_path / "a" / "stack.json").read_text())["meta"]
    assert meta["psf"] in ("gauss", "disc")
    assert meta["noise"]["photons_full_scale"] == case_imaging(case)[1].full_well_e
    board = scene.height_mm < 0.01

    def sharpness(k):
        g = a.read_frame(k).astype(np.float32).mean(axis=2)
        return float(np.mean(np.abs(cv2.Laplacian(g, cv2.CV_32F))[board]))

    assert sharpness(0) > 1.5 * sharpness(2)
