"""A simulated board rig (needs smdinspect.synth.board_scene from the board helper)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from smdinspect.acquire import acquire

from .rigs import sim_rig


def test_board_scene_rig(tmp_path):
    """A simulated board from the shipped reference (needs the board renderer)."""
    from smdinspect import synth

    if not hasattr(synth, "board_scene"):
        pytest.fail("smdinspect.synth.board_scene is missing: board rigs cannot work")
    text = sim_rig(tmp_path / "rig.toml").read_text()
    board = (Path(__file__).parents[2] / "references" / "demo_board.json")
    text = text.replace('scene = "cone"', f'board = "{board}"\ndefects = ""')
    text = text.replace("size_px = 64\n", "shape = [96, 96]\noffset_mm = [0.0, 0.0]\n"
                        "rotate_deg = 0.0\n").replace("height_mm = 0.6\n", "")
    rig = tmp_path / "board.toml"
    rig.write_text(text.replace("z_stop_mm = 0.75", "z_stop_mm = 0.0"))
    res = acquire(rig, tmp_path / "s")
    assert res.n_frames == 4
    doc = json.loads((tmp_path / "s" / "stack.json").read_text())
    assert doc["pixel_size_mm"] == 0.015
