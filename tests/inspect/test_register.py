"""Locating the board: masked NCC, plane fit, coarse + fine registration, not-located."""

import numpy as np
import pytest

from smdinspect.inspect import fit_board_plane, load_board, masked_ncc, register_board
from smdinspect.inspect._geometry import apply2d, decompose2d

from ._synthetic import DEMO, DENSE, truth_surface


def test_masked_ncc_finds_a_known_shift_despite_holes():
    rng = np.random.default_rng(0)
    fixed = rng.normal(size=(60, 70))
    fmask = rng.random(fixed.shape) > 0.2
    moving = np.zeros((50, 50))
    mmask = np.zeros((50, 50), bool)
    moving[10:40, 12:45] = fixed[5:35, 4:37]
    mmask[10:40, 12:45] = True
    ncc, overlap = masked_ncc(fixed, fmask, moving, mmask, min_overlap=100)
    u, v = np.unravel_index(np.argmax(ncc), ncc.shape)
    assert (u - 59, v - 69) == (5, 8)
    assert ncc.max() == pytest.approx(1.0, abs=1e-9)


def test_plane_fit_recovers_a_tilted_board_with_parts_on_it():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 10, (2, 20000))
    z = 0.01 * x - 0.005 * y + 0.3 + rng.normal(0, 0.003, x.size)
    z[:6000] += 0.8                                    # bodies standing on the board
    plane = fit_board_plane(np.column_stack([x, y, z]), distance_mm=0.01, seed=0)
    assert plane.a == pytest.approx(0.01, abs=5e-4)
    assert plane.b == pytest.approx(-0.005, abs=5e-4)
    assert plane.c == pytest.approx(0.3, abs=3e-3)
    assert plane.inlier_fraction == pytest.approx(0.7, abs=0.03)


def _corner_error_mm(T, T_true, board):
    w, h = board.size_mm
    c = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    return float(np.max(np.hypot(*(apply2d(T, c) - apply2d(T_true, c)).T)))


@pytest.mark.parametrize("offset, angle", [((2.0, -2.0), 5.0), ((-1.9, 1.6), -4.7), ((0.4, 0.3), 0.8)])
def test_registration_recovers_shift_and_rotation(offset, angle):
    surface, labels, board = truth_surface(DEMO, "R3.1:tombstone,C2.1:component_shifted",
                                           seed=3, offset_mm=offset, rotate_deg=angle)
    reg = register_board(surface.height_mm, surface.reliable, board,
                         pixel_size_mm=surface.pixel_size_mm, aif=surface.aif)
    T_true = np.array(labels["placement"]["board_to_world"])
    assert reg.converged, reg.reason
    # (at 0.8° every board seed tried reads 0.014-0.022° short, at ±5° within 0.006°:
    # under 5 µm at the board's corners either way, asserted next)
    assert abs(decompose2d(np.linalg.inv(T_true) @ reg.transform)[0]) < 0.03
    assert _corner_error_mm(reg.transform, T_true, board) < 0.005   # 5 µm, a quarter pixel
    assert reg.offset_mm == pytest.approx(offset, abs=0.005)
    assert reg.fitness > 0.8 and reg.rmse_mm < 0.04
    # The shifted part is an outlier of the feature fit, the fiducials carry it.
    assert "body:C2" in reg.meta["features"]["rejected"]
    assert sum(f.startswith("fiducial:") for f in reg.meta["features"]["used"]) == 3


def test_the_wrong_board_is_not_located():
    surface, _, _ = truth_surface(DEMO, "", seed=4)
    reg = register_board(surface.height_mm, surface.reliable, load_board(DENSE),
                         pixel_size_mm=surface.pixel_size_mm, aif=surface.aif)
    assert not reg.converged
    assert "fitness" in reg.reason or "correlate" in reg.reason
