"""benchmarks/inspection.py: the placement error against the truth it reports."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import inspection  # noqa: E402

from smdinspect.inspect import load_board  # noqa: E402
from smdinspect.inspect._geometry import rigid2d  # noqa: E402


def test_placement_error_is_the_rotation_and_the_worst_parts_displacement():
    board = load_board("demo_board")
    T_true = rigid2d(1.0, 5.0, 4.0)
    assert inspection.placement_error(T_true, T_true, board) == {"rotation_deg": 0.0,
                                                                 "worst_part_um": 0.0}
    # 0.5° about the board origin moves a part at distance r by r·0.5° (chord)
    T = rigid2d(1.5, 5.0, 4.0)
    e = inspection.placement_error(T, T_true, board)
    r = max(np.hypot(c.x_mm, c.y_mm) for c in board.components)
    assert e["rotation_deg"] == pytest.approx(0.5, abs=1e-4)
    assert e["worst_part_um"] == pytest.approx(1000 * 2 * r * np.sin(np.radians(0.25)), abs=0.1)
    # a rotation error across ±180° stays small
    e = inspection.placement_error(rigid2d(-179.9, 5, 4), rigid2d(179.9, 5, 4), board)
    assert e["rotation_deg"] == pytest.approx(0.2, abs=1e-4)


def test_placement_lines_split_boards_by_fiducials_and_count_far_parts():
    cases = [{"fiducials": False, "placement": {"rotation_deg": d, "worst_part_um": w}}
             for d, w in ((0.1, 20.0), (-0.3, 50.0), (0.2, 45.0))]
    cases += [{"fiducials": True, "placement": {"rotation_deg": 0.01, "worst_part_um": 2.0}},
              {"fiducials": True, "located": False}]
    lines = inspection.placement_lines(cases)
    assert len(lines) == 2
    assert "3 boards without fiducials" in lines[0] and "median 0.200" in lines[0]
    assert "max 0.300" in lines[0] and "2 boards > 40 um" in lines[0]
    assert "1 boards with fiducials" in lines[1] and "0 boards > 40 um" in lines[1]


def test_the_true_placement_moves_with_the_maps_origin_under_the_parallax_correction():
    # frames magnified about the image centre, output pixels 0.995 of the focused
    # plane's, coordinates from the corner: the board plane lands (1 - 0.995) * centre
    # lower; without the correction the truth is the scene's
    from types import SimpleNamespace

    labels = {"placement": {"board_to_world": rigid2d(2.0, 5.0, 4.0).tolist()}}
    h = np.zeros((101, 201), np.float32)
    par = {"corrected": True, "pixel_scale": 0.995}
    s = SimpleNamespace(height_mm=h, pixel_size_mm=0.02 * 0.995,
                        meta={"alignment": {"parallax": par}})
    T = inspection.map_placement(labels, s)
    assert np.allclose(T[:2, :2], rigid2d(2.0, 5.0, 4.0)[:2, :2])
    assert np.allclose(T[:2, 2], [5.0 - 0.005 * 0.02 * 100, 4.0 - 0.005 * 0.02 * 50])
    for meta in ({"alignment": {"parallax": {"corrected": False}}}, {}, None):
        s = SimpleNamespace(height_mm=h, pixel_size_mm=0.02, meta=meta)
        assert np.allclose(inspection.map_placement(labels, s), rigid2d(2.0, 5.0, 4.0))
