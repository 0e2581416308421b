"""Registration from the bodies' layout when the height-map correlation is misled."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from smdinspect.errors import BoardNotLocatedError
from smdinspect.inspect import inspect_surface, load_board, register_board
from smdinspect.inspect._features import global_body_pose, global_fiducial_pose
from smdinspect.inspect._geometry import apply2d, rigid2d
from smdinspect.sff import Surface
from smdinspect.synth._board_scene import board_scene, random_board_case, scene_kwargs

from ._synthetic import DEMO, DENSE, placed_mask, truth_surface


def _corner_error_mm(T, T_true, board):
    c = board.outline_mm()
    return float(np.max(np.hypot(*(apply2d(T, c) - apply2d(T_true, c)).T)))


@pytest.mark.parametrize("offset, angle", [((1.5, -1.0), -4.5), ((-1.8, 1.2), -4.5),
                                           ((-1.8, 1.2), 3.5)])
def test_a_board_without_its_largest_part_is_located_from_the_body_layout(offset, angle):
    # The SOIC-8 is most of the reference's raised area: without it the correlation
    # locks 3-4 mm off and only searching bodies near that placement never recovers.
    surface, labels, board = truth_surface(DEMO, "U1.1:component_missing", seed=3,
                                           offset_mm=offset, rotate_deg=angle,
                                           fiducials=False)
    result = inspect_surface(surface, board)
    reg = result.registration
    T_true = np.array(labels["placement"]["board_to_world"])
    assert reg.method.startswith("bodies"), reg.meta.get("body_layout")
    assert _corner_error_mm(reg.transform, T_true, board) < 0.01
    u1 = [j for j in result.joints if j.component == "U1"]
    assert all(j.verdict.value == "component_missing" for j in u1)


def _truth_case(name, seed):
    board = load_board(name)
    case = random_board_case(board, seed)
    scene, labels = board_scene(case["board"], **scene_kwargs(case))
    rng = np.random.default_rng([seed, 77])
    h = scene.height_mm + rng.normal(0.0, 0.003, scene.height_mm.shape).astype(np.float32)
    reliable = rng.random(h.shape) >= 0.05
    aif = np.round(np.clip(scene.albedo, 0, 1) * 255).astype(np.uint8)
    surface = Surface(height_mm=h, confidence=reliable.astype(np.float32), reliable=reliable,
                      f_peak=np.ones_like(h), sigma_mm=np.full(h.shape, 0.1, np.float32),
                      reliability_db=np.full(h.shape, 30.0, np.float32), aif=aif,
                      pixel_size_mm=scene.pixel_size_mm, z_mm=np.arange(-0.15, 1.8, 0.05))
    return case, surface, labels


def _registered_truth_case(board_file, seed):
    """(case, registration of its true-height surface, true board-to-world transform)."""
    case, surface, labels = _truth_case(board_file, seed)
    reg = register_board(surface.height_mm, surface.reliable, case["board"],
                         pixel_size_mm=surface.pixel_size_mm, aif=surface.aif)
    return case, reg, np.array(labels["placement"]["board_to_world"])


def test_a_cut_board_with_a_tombstone_and_a_missing_chip_is_not_placed_turned():
    # Tuning case demo 25: the SOIC-8 cut by the field edge, the 1206 tombstoned at 60°,
    # the 0402 missing, no fiducials. The correlation preferred a placement 1.45° off
    # (0.22 mm at the corners) and the two bodies left were too few for the feature fit.
    case, reg, T_true = _registered_truth_case(DEMO, 25)
    assert reg.converged, reg.reason
    assert _corner_error_mm(reg.transform, T_true, case["board"]) < 0.01


def test_body_layout_pose_needs_two_agreeing_bodies():
    surface, labels, board = truth_surface(DENSE, "", seed=5, offset_mm=(1.0, -0.5),
                                           rotate_deg=2.0)
    H, W = surface.height_mm.shape
    p = surface.pixel_size_mm
    T_nom = rigid2d(0.0, (W - 1) * p / 2 - board.size_mm[0] / 2,
                    (H - 1) * p / 2 - board.size_mm[1] / 2)
    T, info = global_body_pose(surface.height_mm, surface.reliable, board, p, T_nominal=T_nom,
                               max_rotation_deg=6.0, max_offset_mm=3.0)
    assert _corner_error_mm(T, np.array(labels["placement"]["board_to_world"]), board) < 0.01
    assert len(info["support"]) >= 6
    # A flat, featureless measurement has no bodies to match.
    flat = np.zeros_like(surface.height_mm)
    T, info = global_body_pose(flat, surface.reliable, board, p, T_nominal=T_nom,
                               max_rotation_deg=6.0, max_offset_mm=3.0)
    assert T is None


def test_fiducials_found_anywhere_locate_a_board_its_parts_cannot_place():
    # Tuning case demo 239: the SOIC-8 missing, the 0402 shifted 0.31 mm, an 0603
    # tombstoned, the 1206 and 0805 cut by the field edge; R1 the only whole body in
    # place, two fiducials in view (one centred 1.5 radii from the image's border). The
    # correlation locks 3.5 mm off, no two bodies agree, and the fiducials were searched
    # only where that placement put them: not located. Searched over the whole image
    # they place the board, and R1 agrees.
    case, reg, T_true = _registered_truth_case(DEMO, 239)
    assert reg.converged, reg.reason
    assert reg.method.startswith("fiducials"), reg.meta.get("fiducial_layout")
    assert _corner_error_mm(reg.transform, T_true, case["board"]) < 0.01
    assert reg.meta["fiducial_layout"]["support"] == ["FID1", "FID3"]
    used = reg.meta["features"]["used"]
    assert "body:R1" in used and "body:C2" in reg.meta["features"]["rejected"]


def test_fiducial_pose_needs_two_marks_as_far_apart_as_two_fiducials():
    """Bright discs of the fiducials' diameter drawn where a known placement puts the
    board's three fiducials, with two distractor discs (one beside a fiducial, one
    alone): the placement comes back to a few µm. With a single fiducial left, or its
    partner moved 0.3 mm (no pair at the board's spacing), there is none."""
    import cv2

    board = load_board(DEMO)
    p, shape = 0.02, (560, 600)
    T_true = rigid2d(3.0, 0.6, 0.4)
    T_nom = rigid2d(0.0, ((shape[1] - 1) * p - board.size_mm[0]) / 2,
                    ((shape[0] - 1) * p - board.size_mm[1]) / 2)
    fids = np.array([[f.x_mm, f.y_mm] for f in board.fiducials])
    r_px = board.fiducials[0].diameter_mm / 2 / p

    def image(marks_mm):
        img = np.random.default_rng(0).normal(60, 4, shape).clip(0, 255).astype(np.uint8)
        xy = np.asarray(marks_mm, float)
        cols, rows = xy[:, 0] / p, (shape[0] - 1) - xy[:, 1] / p
        for c, r in zip(cols, rows):
            cv2.circle(img, (int(round(c * 16)), int(round(r * 16))), int(round(r_px * 16)),
                       210, -1, lineType=cv2.LINE_AA, shift=4)
        return np.repeat(img[:, :, None], 3, axis=2)

    world = apply2d(T_true, fids)
    distractors = [world[0] + [1.3, 0.9], world[1] + [-2.0, 3.0]]
    T, info = global_fiducial_pose(image([*world, *distractors]), board, p, T_nominal=T_nom,
                                   max_rotation_deg=6.0, max_offset_mm=3.0)
    assert T is not None, info
    assert info["support"] == ["FID1", "FID2", "FID3"] and info["candidates"] == 5
    assert _corner_error_mm(T, T_true, board) < 0.01
    T, info = global_fiducial_pose(image([world[0], *distractors]), board, p, T_nominal=T_nom,
                                   max_rotation_deg=6.0, max_offset_mm=3.0)
    assert T is None
    moved = [world[0], world[1] + [0.3, 0.0]]
    T, info = global_fiducial_pose(image(moved), board, p, T_nominal=T_nom,
                                   max_rotation_deg=6.0, max_offset_mm=3.0)
    assert T is None and info["reason"] == "no two fiducials agree"


def test_the_wrong_board_is_still_not_located_with_the_layout_search():
    surface, _, _ = truth_surface(DEMO, "U1.1:component_missing", seed=4, fiducials=False)
    with pytest.raises(BoardNotLocatedError, match="not located"):
        inspect_surface(surface, load_board(DENSE))


def test_a_board_without_its_largest_part_is_located_with_biased_body_centroids(monkeypatch):
    # Through shape from focus body centroids carry 10-40 µm of bias (asymmetric fillets,
    # edge blur). With the SOIC-8 missing only the bodies can locate the board; their
    # fit's RMS then exceeds 20 µm but not half the consensus distance (30 µm).
    import dataclasses

    from smdinspect.inspect import _register

    surface, labels, board = truth_surface(DEMO, "U1.1:component_missing", seed=3,
                                           offset_mm=(1.5, -1.0), rotate_deg=-4.5,
                                           fiducials=False)
    real = _register.feature_pairs
    pattern = np.array([[0.03, 0.0], [0.0, -0.03], [-0.03, 0.0], [0.0, 0.03], [0.021, 0.021]])

    def biased(*args, **kwargs):
        out = []
        for k, fp in enumerate(real(*args, **kwargs)):
            d = pattern[k % len(pattern)]
            out.append(dataclasses.replace(fp, world_xy=(fp.world_xy[0] + d[0],
                                                         fp.world_xy[1] + d[1])))
        return out

    monkeypatch.setattr(_register, "feature_pairs", biased)
    reg = register_board(surface.height_mm, surface.reliable, board,
                         pixel_size_mm=surface.pixel_size_mm, aif=surface.aif)
    assert reg.converged, reg.reason
    assert 0.02 < reg.meta["features"]["rms_mm"] <= 0.03
    T_true = np.array(labels["placement"]["board_to_world"])
    assert _corner_error_mm(reg.transform, T_true, board) < 0.05


def test_fiducials_locate_a_board_whose_parts_are_mostly_missing_or_shifted():
    # Two good bodies out of six: too few to vouch for the placement, but the three
    # fiducials, the board's own reference marks, agree with it to a few µm.
    surface, labels, board = truth_surface(
        DEMO, "U1.1:component_missing,R2.1:component_missing,R1.2:component_shifted,"
              "C1.1:component_missing", seed=3, offset_mm=(1.0, -0.8), rotate_deg=2.5)
    result = inspect_surface(surface, board)
    reg = result.registration
    assert reg.score < 0.5 and reg.meta["located_by_features"]
    T_true = np.array(labels["placement"]["board_to_world"])
    assert _corner_error_mm(reg.transform, T_true, board) < 0.01
    verdicts = {j.component: j.verdict.value for j in result.joints}
    assert verdicts["U1"] == verdicts["R2"] == verdicts["C1"] == "component_missing"
    assert verdicts["R3"] == "ok"


def test_body_blobs_as_shape_from_focus_sees_them_match_their_package_only():
    from smdinspect.inspect._features import _Blob, _blob_matches

    board = load_board(DEMO)
    r0603, r0805, c0402 = (next(c for c in board.components if c.ref == ref)
                           for ref in ("R1", "R2", "C2"))
    # Blobs measured through SFF on tuning case demo 25 / 90: edge blur widens a
    # 0.8 mm wide 0603 body to 0.97 mm across.
    seen_0603 = _Blob((0.0, 0.0), (1.678, 0.967), 177.5, 1.198)
    seen_0805 = _Blob((0.0, 0.0), (2.081, 1.325), 90.7, 2.486)
    seen_0402 = _Blob((0.0, 0.0), (1.08, 0.56), 0.0, 0.576)
    assert _blob_matches(r0603, seen_0603)
    assert _blob_matches(r0805, seen_0805) and _blob_matches(c0402, seen_0402)
    assert not _blob_matches(r0603, seen_0805) and not _blob_matches(r0805, seen_0603)
    assert not _blob_matches(c0402, seen_0603) and not _blob_matches(r0603, seen_0402)


def test_a_body_biased_by_an_excess_fillet_does_not_turn_the_board():
    # Tuning case dense 50 (true heights): R3's convex excess fillet reaches the body's
    # presence threshold and lengthens its blob at one end, moving its centre 70 µm
    # along its length; kept at full weight it turned the board 0.26°. Its blob grew
    # more along than across, so it weighs little along its length (or is left out).
    case, reg, T_true = _registered_truth_case(DENSE, 50)
    assert reg.converged, reg.reason
    assert _corner_error_mm(reg.transform, T_true, case["board"]) < 0.01


def _chip_blob_xy(p, length, width, angle_deg, centre, *, cut_end=0.0, notch=False):
    """Pixel centres (WORLD mm) of a chip body's blob on a ``p`` grid: the body grown by
    one pixel of edge bleed all round, ``cut_end`` mm of it missing at its +x end, and
    with ``notch`` an unreliable notch by its +x termination on its +y half."""
    g = np.arange(-3.0, 3.0, p)
    X, Y = np.meshgrid(g, g)
    a = np.radians(angle_deg)
    lx = (X - centre[0]) * np.cos(a) + (Y - centre[1]) * np.sin(a)
    ly = -(X - centre[0]) * np.sin(a) + (Y - centre[1]) * np.cos(a)
    m = (np.abs(lx) <= length / 2 + p) & (np.abs(ly) <= width / 2 + p)
    m &= lx <= length / 2 + p - cut_end
    if notch:
        m &= ~((lx > 0.35 * length) & (lx < 0.45 * length) & (ly > -0.1 * width))
    return np.column_stack([X[m], Y[m]]), np.array([np.cos(a), np.sin(a)])


@pytest.mark.parametrize("angle", [0.0, 90.0, 33.0])
def test_a_chip_centre_is_its_blobs_midpoint_and_a_lost_end_is_known_only_loosely(angle):
    from smdinspect.inspect._features import BODY_SIGMA_MM, _chip_position

    p, L, W, c = 0.02, 1.6, 0.8, np.array([0.3, -0.2])
    xy, u = _chip_blob_xy(p, L, W, angle, c)
    (x, y), s = _chip_position(xy, u, L, W, 0.3)
    assert np.hypot(x - c[0], y - c[1]) < p           # within the pixel grid's rounding
    assert s < 1.0 + p / BODY_SIGMA_MM        # edge bleed alike all round: as well as across
    # a glinting termination (0.3 mm) left out of the blob: the centre moves by half of
    # it along the length, and the uncertainty along covers that move
    xy, u = _chip_blob_xy(p, L, W, angle, c, cut_end=0.3)
    (x, y), s = _chip_position(xy, u, L, W, 0.3)
    d = np.array([x, y]) - c
    assert abs(d @ u + 0.15) < 0.03 and abs(d @ [-u[1], u[0]]) < 0.02
    assert (s - 1.0) * BODY_SIGMA_MM == pytest.approx(0.15, abs=0.03)
    # both terminations lost (end caps clipped white): the ceramic middle is centred;
    # shorter still, the blob is not the body (a tombstone's standing end)
    xy, u = _chip_blob_xy(p, L, W, angle, c, cut_end=0.3)
    xy = xy[(xy - c) @ u > -L / 2 + 0.3 - p]
    (x, y), s = _chip_position(xy, u, L, W, 0.3)
    assert np.hypot(x - c[0], y - c[1]) < p and s < 1.0 + p / BODY_SIGMA_MM
    assert _chip_position(xy[(xy - c) @ u > -L / 2 + 0.45], u, L, W, 0.3) is None
    # a notch shape from focus leaves inside the outline moves the centroid, not the
    # midpoint of the extents
    xy, u = _chip_blob_xy(p, L, W, angle, c, notch=True)
    (x, y), s = _chip_position(xy, u, L, W, 0.3)
    assert np.hypot(x - c[0], y - c[1]) < p and s < 1.0 + p / BODY_SIGMA_MM
    assert np.hypot(*(xy.mean(axis=0) - c)) > 2 * p


def test_a_chip_known_loosely_along_its_length_does_not_turn_the_board():
    """Four chips and an IC; one chip's centre is 120 µm off along its length (a lost
    termination), which its uncertainty along says. The isotropic fit turns the board
    by 0.23°; the fit weighing each pair by its uncertainty in each direction does not."""
    from smdinspect.inspect._features import (FeaturePair, fit_pairs, fit_rigid2d,
                                              refine_with_features)

    T = rigid2d(1.2, 4.0, 3.0)
    refs = {"U1": ((5.0, 5.0), None), "R1": ((1.0, 1.0), 0.0), "R2": ((9.0, 1.0), 0.0),
            "C1": ((1.0, 9.0), 90.0), "C2": ((9.0, 8.0), 90.0)}
    pairs = []
    for ref, (xy, rot) in refs.items():
        world = apply2d(T, np.array([xy]))[0]
        if rot is None:
            pairs.append(FeaturePair("body", ref, xy, tuple(world), 0.05))
            continue
        a = np.radians(rot + 1.2)
        u = np.array([np.cos(a), np.sin(a)])
        off, s = (0.12, 9.0) if ref == "C2" else (0.0, 1.0)
        pairs.append(FeaturePair("body", ref, xy, tuple(world + off * u), 0.05,
                                 axis=tuple(u), along_sigma=s))
    src = np.array([fp.board_xy for fp in pairs])
    dst = np.array([fp.world_xy for fp in pairs])
    iso = fit_rigid2d(src, dst)
    assert abs(np.degrees(np.arctan2(iso[1, 0], iso[0, 0])) - 1.2) > 0.2
    T_fit = fit_pairs(pairs)
    assert abs(np.degrees(np.arctan2(T_fit[1, 0], T_fit[0, 0])) - 1.2) < 0.05
    assert _corner_error_mm(T_fit, T, type("B", (), {"outline_mm": lambda self: np.array(
        [[0, 0], [10, 0], [10, 10], [0, 10]], float)})()) < 0.02
    T_ref, info = refine_with_features(pairs, rigid2d(1.0, 4.05, 2.95))
    assert "body:C2" in info["used"]
    assert abs(np.degrees(np.arctan2(T_ref[1, 0], T_ref[0, 0])) - 1.2) < 0.05


def test_a_body_with_unreliable_notches_along_its_ends_is_still_a_body_blob():
    # Shape from focus leaves the bright terminations' edges unreliable: the blob of a
    # 1.6 x 0.8 mm body loses a fifth of its pixels in notches, but its convex hull
    # keeps the body's area (the old pixel count fell below 0.8 of the nominal).
    from smdinspect.inspect._features import _blob_matches, _measured_blobs

    board = load_board(DEMO)
    r1 = next(c for c in board.components if c.ref == "R1")
    p = 0.02
    h = np.zeros((120, 160), np.float32)
    h[40:80, 40:120] = 0.45                       # 80 x 40 px = 1.6 x 0.8 mm
    rel = np.ones(h.shape, bool)
    for c0 in (44, 106):                          # notches across the body by each end
        rel[40:70, c0:c0 + 10] = False
    rel[64:80, 66:94] = False                     # and one in the other long side
    blobs = _measured_blobs(h, rel, 0.3, p)
    assert len(blobs) == 1
    (b,) = blobs
    assert rel[40:80, 40:120].mean() < 0.75       # the pixels alone fail the area test
    assert b.area_mm2 == pytest.approx(1.6 * 0.8, rel=0.05)
    assert _blob_matches(r1, b)


def test_a_small_body_grown_by_edge_bleed_still_matches():
    # Through shape from focus a 1.0 x 0.5 mm body's outline grows by ~1-2 px (20 µm)
    # all round: its hull's area is ~1.25x the nominal, past 1.2x, though the same band
    # on an 0805 is within it (test seed dense 10006: three 0402 bodies were refused and
    # the board, its largest part missing and no fiducials, was not located).
    from smdinspect.inspect._features import _area_matches, _area_matches_shape

    board = load_board(DEMO)
    c0402, r0805 = (next(c for c in board.components if c.ref == ref) for ref in ("C2", "R2"))
    grown = (1.0 + 0.08) * (0.5 + 0.08)
    assert grown / 0.5 > 1.2 and _area_matches(c0402, grown)
    assert not _area_matches(c0402, (1.0 + 0.3) * (0.5 + 0.3))   # body + fillets
    assert not _area_matches_shape(1.0, 0.5, 0.6 * 0.5)          # half a body is not the body
    # ... though it is as large as the ceramic middle between the end caps (0.5 x 0.5
    # mm), which may be all that is measured: the middle is accepted (test seed demo
    # 10087's 0402, 0.54 x 0.51 mm), and the layout's consensus leaves out a half body,
    # whose centroid lies 0.2 mm off
    assert _area_matches(c0402, 0.54 * 0.51)
    assert not _area_matches(c0402, 0.3 * 0.3)
    L, W = r0805.body_length_mm, r0805.body_width_mm
    assert _area_matches(r0805, 1.15 * L * W) and not _area_matches(r0805, 1.3 * L * W)


def test_a_chip_middle_blob_lies_across_or_along_as_its_bleed_makes_it():
    """A chip's middle between its caps is measured (L − 2t) along the part by its
    width grown by the edge band on both sides (its sides bleed into the board, its
    unmeasured caps do not): an 0402's (0.5 x 0.5 mm) reads long across the part (test
    seed demo 10087 with arc fillets: 0.59 x 0.50 mm at 86° to the part; the board was
    not located when that blob was taken to lie along it), an 0805's (1.2 x 1.25 mm)
    square; a whole body's blob lies along the part."""
    from smdinspect.inspect._features import _axis_turns_with, _Blob

    board = load_board(DEMO)
    c0402, r0805, r0603 = (next(c for c in board.components if c.ref == ref)
                           for ref in ("C2", "R2", "R1"))
    rot = 12.0
    across = (c0402.rotation_deg + 90.0 + rot) % 180.0
    assert _axis_turns_with(c0402, _Blob((0.0, 0.0), (0.59, 0.50), across + 3.0, 0.226), rot)
    assert not _axis_turns_with(c0402, _Blob((0.0, 0.0), (0.59, 0.50), across + 90.0, 0.226),
                                rot)
    for ang in (0.0, 45.0, 90.0):   # a square middle: any direction
        assert _axis_turns_with(r0805, _Blob((0.0, 0.0), (1.40, 1.20), ang, 1.31), rot)
    along = (r0603.rotation_deg + rot) % 180.0
    whole = (1.70, 0.92)
    assert _axis_turns_with(r0603, _Blob((0.0, 0.0), whole, along + 4.0, 1.5), rot)
    assert not _axis_turns_with(r0603, _Blob((0.0, 0.0), whole, along + 30.0, 1.5), rot)


def test_a_far_body_is_kept_against_a_cluster_of_small_ones():
    """Body centroids through shape from focus carry 20-60 µm of bias (more through an
    ordinary lens). With the largest part missing, four small chips in one corner and a
    far TSSOP remain: the far body fixes the rotation and must not be rejected because
    the corner cluster, fitted alone, predicts it poorly (biases measured on a rendered
    dense board through an ordinary lens, SOIC-16 and one 0402 missing, one 0402 shifted
    by 0.29 mm)."""
    from smdinspect.inspect._features import FeaturePair, refine_with_features

    T = rigid2d(3.5, 1.2, -0.8)
    board = {"U2": (8.2, 9.9), "R1": (1.6, 8.6), "C1": (3.7, 8.6), "R2": (1.6, 10.3),
             "C2": (2.8, 10.3), "R3": (3.3, 11.55)}
    bias_um = {"U2": (-44.5, 22.9), "R1": (24.4, 49.3), "C1": (25.7, -8.4),
               "R2": (28.7, 4.2), "C2": (286.4, 26.2), "R3": (27.3, -34.3)}
    pairs = []
    for ref, xy in board.items():
        world = apply2d(T, np.array([xy]))[0] + np.array(bias_um[ref]) / 1000.0
        pairs.append(FeaturePair("body", ref, xy, tuple(world), 0.05))
    T_fit, info = refine_with_features(pairs, rigid2d(3.3, 1.25, -0.75))
    assert info["used"] == ["body:U2", "body:R1", "body:C1", "body:R2", "body:R3"]
    angle = np.degrees(np.arctan2(T_fit[1, 0], T_fit[0, 0]))
    assert abs(angle - 3.5) < 0.1, angle


def test_an_unambiguous_body_layout_locates_a_board_without_fiducials_whose_parts_are_mostly_defective():
    # Two good bodies of six vouch for the placement (too few for the majority rule),
    # and the missing SOIC-8 takes most of the reference coverage with it. No other
    # placement is supported by two bodies and the measured raised points lie on the
    # reference, so the layout's placement stands (tuning seed 202 through shape from
    # focus: both boards were lost this way).
    surface, labels, board = truth_surface(
        DEMO, "U1.1:component_missing,R2.1:component_missing,R1.1:tombstone,"
              "C1.1:component_missing", seed=3, offset_mm=(1.0, -0.8), rotate_deg=2.5,
        fiducials=False)
    result = inspect_surface(surface, board)
    reg = result.registration
    layout = reg.meta["body_layout"]
    assert reg.meta["located_by_layout"], layout
    assert layout["support"] == ["C2", "R3"] and layout["rival_support"] < 2
    T_true = np.array(labels["placement"]["board_to_world"])
    assert _corner_error_mm(reg.transform, T_true, board) < 0.01
    verdicts = {j.component: j.verdict.value for j in result.joints}
    assert verdicts["U1"] == verdicts["R2"] == verdicts["C1"] == "component_missing"
    assert verdicts["R1"] == "tombstone" and verdicts["C2"] == verdicts["R3"] == "ok"


def test_a_body_layout_with_an_equally_supported_rival_placement_does_not_locate_the_board():
    # The same board with R1 shifted instead of tombstoned: its body pairs with a good
    # one into a second placement that two bodies support as well. The layout alone
    # cannot tell them apart, so without fiducials the board stays not located.
    surface, _, board = truth_surface(
        DEMO, "U1.1:component_missing,R2.1:component_missing,R1.2:component_shifted,"
              "C1.1:component_missing", seed=3, offset_mm=(1.0, -0.8), rotate_deg=2.5,
        fiducials=False)
    reg = register_board(surface.height_mm, surface.reliable, board,
                         pixel_size_mm=surface.pixel_size_mm, aif=surface.aif)
    assert reg.meta["body_layout"]["rival_support"] == 2
    assert not reg.converged and not reg.meta["located_by_layout"]


def test_fiducials_locate_a_board_whose_raised_points_are_mostly_defects():
    # Test seed demo 10064 as true heights: the SOIC-8 missing, the 1206 stood at 50°,
    # a bulging excess fillet. Three fiducials and three bodies agree with the
    # placement, but under half the measured raised points lie on the reference: what
    # stands off it is for the verdicts to name, not a reason to lose the board.
    surface, labels, board = truth_surface(
        DEMO, "U1.1:component_missing,C1.1:tombstone,R1.1:excess", seed=3,
        offset_mm=(-1.2, 1.8), rotate_deg=-1.0,
        params={"C1.1": {"tilt_deg": 50.0}, "R1.1": {"over_mm": 0.17, "style": "convex"}})
    result = inspect_surface(surface, board)
    reg = result.registration
    assert reg.meta["located_by_fiducials"] and reg.meta["forward_fitness"] < 0.6
    T_true = np.array(labels["placement"]["board_to_world"])
    assert _corner_error_mm(reg.transform, T_true, board) < 0.01
    verdicts = {j.id: j.verdict.value for j in result.joints}
    assert verdicts["U1.1"] == "component_missing" and verdicts["C1.1"] == "tombstone"
    assert verdicts["R1.1"] == "excess"


def _caps_unmeasured(surface, labels, board):
    """The surface with every chip's metal end caps unreliable (clipped glints)."""
    import dataclasses

    reliable = surface.reliable.copy()
    for comp in board.components:
        if comp.kind != "chip":
            continue
        hl, hw, t = comp.body_length_mm / 2, comp.body_width_mm / 2, comp.termination_length_mm
        for a, b in ((hl - t, hl + 0.02), (-hl - 0.02, -hl + t)):
            box = np.array([[a, -hw - 0.02], [b, -hw - 0.02], [b, hw + 0.02], [a, hw + 0.02]])
            reliable &= ~placed_mask(surface, labels, comp.to_board(box))
    return dataclasses.replace(surface, reliable=reliable,
                               confidence=reliable.astype(np.float32))


def test_chips_seen_without_their_end_caps_still_give_the_body_layout(monkeypatch):
    """Specular end caps clipped white leave a chip's blob its ceramic middle (test seed
    demo 10087: an 0805 read 1.4 x 1.2 mm, an 0402 0.54 x 0.51 mm); with the SOIC-8
    missing and no fiducials, the layout must come from such middles."""
    from smdinspect.inspect import _features

    surface, labels, board = truth_surface(DEMO, "U1.1:component_missing", seed=3,
                                           offset_mm=(1.5, -1.0), rotate_deg=-4.5,
                                           fiducials=False)
    surface = _caps_unmeasured(surface, labels, board)
    T_true = np.array(labels["placement"]["board_to_world"])
    reg = inspect_surface(surface, board).registration
    assert reg.method.startswith("bodies"), reg.meta.get("body_layout")
    assert _corner_error_mm(reg.transform, T_true, board) < 0.02
    # whole bodies only: no body matches, the correlation locks off, nothing is located
    monkeypatch.setattr(_features, "_body_shapes",
                        lambda comp: [(comp.body_length_mm, comp.body_width_mm)])
    with pytest.raises(BoardNotLocatedError):
        inspect_surface(surface, board)


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(angle=st.floats(-20, 20), tx=st.floats(-5, 5), ty=st.floats(-5, 5),
       n=st.integers(3, 7), seed=st.integers(0, 2 ** 31 - 1))
def test_fit_pairs_minimises_the_residuals_weighed_by_each_pairs_uncertainties(
        angle, tx, ty, n, seed):
    """With noisy pairs, each known along its chip to 1-30 times less than across, the
    fit is the minimum of Σ rᵢᵀ·Iᵢ·rᵢ: no small turn or shift of it, nor the plain
    Procrustes fit, does better; with exact pairs it is the placement itself."""
    from smdinspect.inspect._features import FeaturePair, fit_pairs, fit_rigid2d

    rng = np.random.default_rng(seed)
    T = rigid2d(angle, tx, ty)
    src = rng.uniform(0, 20, (n, 2))
    src[1] = src[0] + [3.0, 1.0]              # two pairs at least ~3 mm apart
    noise = rng.normal(0, 0.03, (n, 2))

    axes, sig = rng.uniform(0, np.pi, n), rng.uniform(1, 30, n)

    def pairs_for(dst):
        return [FeaturePair("body", "X", tuple(s), tuple(d), 0.05,
                            axis=(float(np.cos(a)), float(np.sin(a))), along_sigma=float(k))
                for s, d, a, k in zip(src, dst, axes, sig)]

    pairs = pairs_for(apply2d(T, src) + noise)

    def cost(A):
        return sum(float(r @ fp.information() @ r) for fp in pairs
                   for r in [apply2d(A, np.array([fp.board_xy]))[0] - fp.world_xy])

    T_fit = fit_pairs(pairs)
    c = cost(T_fit)
    for d in ([1e-4, 0, 0], [-1e-4, 0, 0], [0, 1e-3, 0], [0, -1e-3, 0], [0, 0, 1e-3],
              [0, 0, -1e-3]):
        step = rigid2d(np.degrees(d[0]), d[1], d[2])
        assert c <= cost(step @ T_fit) * (1 + 1e-9)
    assert c <= cost(fit_rigid2d(src, apply2d(T, src) + noise)) * (1 + 1e-9)
    exact = pairs_for(apply2d(T, src))
    assert np.abs(apply2d(fit_pairs(exact), src) - apply2d(T, src)).max() < 1e-7


@pytest.mark.parametrize("spread_mm", [1.0, 6.0])
def test_the_placements_covariance_is_the_scatter_of_its_fit(spread_mm):
    """placement_covariance predicts how far the fitted placement puts a distant part
    from its true place: over 400 noisy draws of five bodies (20 µm, some chips known
    loosely along their length) in a cluster ``spread_mm`` across, the scatter at a part
    8 mm away matches the prediction within 20 %; a compact cluster fixes it worse."""
    from smdinspect.inspect._features import (FeaturePair, fit_pairs, placement_covariance,
                                              position_covariance)
    from smdinspect.inspect._geometry import apply2d, rigid2d

    rng = np.random.default_rng(5)
    T = rigid2d(0.3, 1.0, -2.0)
    board = rng.uniform(0, spread_mm, (5, 2))
    world = apply2d(T, board)
    far = (8.0 + spread_mm, 4.0)
    hits, predicted = [], []
    for _ in range(400):
        pairs = []
        for i, (b, w) in enumerate(zip(board, world)):
            axis, along = ((1.0, 0.0), 2.0) if i % 2 else (None, 1.0)
            noise = rng.normal(0, 0.02, 2)
            if axis:
                noise[0] *= along
            pairs.append(FeaturePair("body", f"P{i}", tuple(b), tuple(w + noise), 1.0,
                                     axis=axis, along_sigma=along))
        T_fit = fit_pairs(pairs)
        cov, centre = placement_covariance(pairs, T_fit)
        predicted.append(position_covariance(cov, centre, T_fit, far))
        hits.append(apply2d(T_fit, np.array([far]))[0] - apply2d(T, np.array([far]))[0])
    hits = np.array(hits)
    R = T[:2, :2]
    seen = R.T @ np.cov(hits.T) @ R
    want = np.mean(predicted, axis=0)
    np.testing.assert_allclose(np.sqrt(np.diag(seen)), np.sqrt(np.diag(want)), rtol=0.2)
    if spread_mm < 2:
        assert np.sqrt(np.max(np.diag(want))) > 0.06     # a compact cluster: ±60 µm or worse
