"""SFF on a synthetic SMD board: the confidence must keep the right depths only.

Real boards have weak solder-mask texture, specular metal and component edges whose
defocused blur bleeds over their surroundings; the default synthetic board has all of
them. Issue criteria: on confident pixels median |error| <= 0.1 step and RMSE <= 1 step
at a coverage >= 0.8.
"""

import numpy as np
import pytest

from smdinspect.optics import Optics
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.synth import board_scene, render_stack

STEP = 0.05


BOARDS = {
    "demo": ("references/demo_board.json",
             {"R3.1": "insufficient", "U1.4": "bridge", "C1.2": "excess"}),
    "dense": ("references/dense_board.json", {}),
}


@pytest.fixture(scope="module", params=sorted(BOARDS))
def board(request, tmp_path_factory):
    path, defects = BOARDS[request.param]
    scene, labels = board_scene(path, pixel_size_mm=0.02, seed=11, defects=defects)
    top = float(scene.height_mm.max())
    z = np.round(np.arange(-3 * STEP, top + 3 * STEP, STEP) - 0.0123, 6)[::-1]  # sweep down
    root = tmp_path_factory.mktemp("board")
    stack = render_stack(scene, z, optics=Optics.for_pixel_size(0.02), seed=4, out=root,
                         previews=False)
    return scene, stack


def test_board_heights_on_confident_pixels(board):
    scene, stack = board
    s = reconstruct(stack, FocusConfig())
    err = (s.height_mm - scene.height_mm)[s.reliable] / STEP
    assert s.coverage >= 0.8, s.coverage
    assert np.median(np.abs(err)) <= 0.1
    assert np.sqrt(np.mean(err**2)) <= 1.0


def test_edge_check_is_what_removes_bleeding(board):
    """Without the depth-edge check, component edges leave wrong depths behind."""
    scene, stack = board
    s = reconstruct(stack, FocusConfig(edge_jump_steps=0))
    err = (s.height_mm - scene.height_mm)[s.reliable] / STEP
    assert np.mean(np.abs(err) > 3) > 0.003
