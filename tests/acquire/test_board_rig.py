"""A simulated board rig (needs smdinspect.synth.board_scene from the board helper)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from smdinspect.acquire import acquire
from smdinspect.errors import InputError

from .rigs import sim_rig


def test_board_scene_rig(tmp_path):
    """A simulated board from the shipped reference (needs the board renderer)."""
    from smdinspect import synth

    if not hasattr(synth, "board_scene"):
        pytest.fail("smdinspect.synth.board_scene is missing: board rigs cannot work")
    text = sim_rig(tmp_path / "rig.toml").read_text()
    board = (Path(__file__).parents[2] / "references" / "demo_board.json")
    text = text.replace('scene = "cone"', f'board = "{board}"\ndefects = "R1.1:insufficient"')
    text = text.replace("size_px = 64\n", "shape = [128, 128]\noffset_mm = [0.0, 0.0]\n"
                        "rotate_deg = 0.0\n").replace("height_mm = 0.6\n", "")
    text = text.replace("pixel_size_mm = 0.015", "pixel_size_mm = 0.1")
    rig = tmp_path / "board.toml"
    rig.write_text(text.replace("z_stop_mm = 0.75", "z_stop_mm = 0.0"))
    res = acquire(rig, tmp_path / "s")
    assert res.n_frames == 4
    doc = json.loads((tmp_path / "s" / "stack.json").read_text())
    assert doc["pixel_size_mm"] == 0.1
    assert doc["optics"]["pixel_size_mm"] == pytest.approx(0.1)
    from smdinspect.optics import Optics
    from smdinspect.stack import FocalStack

    scene, labels = synth.board_scene(board, defects={"R1.1": "insufficient"},
                                      pixel_size_mm=0.1, shape=(128, 128), offset_mm=(0.0, 0.0),
                                      rotate_deg=0.0, seed=7)
    optics = Optics.for_pixel_size(0.1, focal_length_mm=50.0, aperture_mm=50.0,
                                   pixel_pitch_mm=0.015)
    stack = FocalStack.open(tmp_path / "s")
    for _, z, frame in stack.iter_frames():
        ref = synth.render_frame(scene, z, optics=optics,
                                 sensor=synth.SensorConfig.preset("low"), rng=7)
        np.testing.assert_array_equal(frame, ref)
    # a defect on a joint the board does not have is one clear error, before any motion
    rig.write_text(rig.read_text().replace("R1.1:insufficient", "Z9.1:bridge"))
    with pytest.raises(InputError, match="unknown joint 'Z9.1' on board"):
        acquire(rig, tmp_path / "s2")
