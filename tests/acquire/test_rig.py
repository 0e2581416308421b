"""Rig files: parsing, validation with one-line errors, travel checks, the fingerprint."""

from __future__ import annotations

from pathlib import Path

import pytest

from smdinspect.acquire import CameraKind, acquire, load_rig, parse_rig
from smdinspect.errors import InputError

from .rigs import sim_rig

EXAMPLES = Path(__file__).parents[2] / "examples"

FOLDER_RIG = """
[stage]
port = "/dev/ttyUSB0"
z_min_mm = -10.0
z_max_mm = 0.0
[mapping]
focus_offset_mm = 5.0
[camera]
kind = "folder"
path = "frames"
pixel_size_mm = 0.01
[sweep]
z_start_mm = 0.0
z_stop_mm = 0.2
step_mm = 0.02
backlash_mm = 0.1
"""


def test_examples_parse():
    sim = load_rig(EXAMPLES / "sim_rig.toml")
    assert sim.stage.fake and sim.camera.kind is CameraKind.SIMULATED
    assert sim.sweep.n_frames == 19
    board = load_rig(EXAMPLES / "sim_board_rig.toml")
    assert board.resolve(board.camera.options["board"]).is_file()
    real = load_rig(EXAMPLES / "grbl_usb_rig.toml")
    assert not real.stage.fake and real.camera.kind is CameraKind.OPENCV
    assert real.stage.home


def test_folder_rig_parses_and_resolves_relative_to_the_file(tmp_path):
    rig = parse_rig(FOLDER_RIG, base_dir=tmp_path, source="r.toml")
    assert rig.stage.port == "/dev/ttyUSB0" and rig.stage.baud == 115200
    assert rig.resolve(rig.camera.options["path"]) == tmp_path / "frames"
    assert rig.machine_plan_mm()[0] == pytest.approx(-5.0)
    assert len(rig.sha256) == 64


@pytest.mark.parametrize("edit, match", [
    (("[sweep]", "[sweeps]"), r"unknown table\(s\) sweeps"),
    (("step_mm = 0.02", "step_mm = 0.02\nstepp_mm = 1"), r"unknown key\(s\) stepp_mm in \[sweep\]"),
    (("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyUSB0\"\nbaudrate = 9600"),
     r"unknown key\(s\) baudrate in \[stage\]"),
    (("kind = \"folder\"", "kind = \"webcam\""), "camera kind must be one of opencv, folder, "
                                                 "simulated, genicam; got 'webcam'"),
    (("path = \"frames\"", "path = \"frames\"\ndevice = 0"), r"unknown key\(s\) device in "
                                                             r"\[camera\] for kind 'folder'"),
    (("step_mm = 0.02", "step_mm = -0.02"), "sweep step_mm must be > 0; got -0.02"),
    (("z_stop_mm = 0.2", "z_stop_mm = 6.0"), r"sweep z_mm 5.0\d* needs machine Z 0.0\d* mm|"
                                             r"needs machine Z \d"),
    (("backlash_mm = 0.1", "backlash_mm = 5.5"), "backlash overshoot before the first frame "
                                                 r"needs machine Z -10.5000 mm, outside"),
    (("z_start_mm = 0.0", ""), r"\[sweep\] needs z_start_mm"),
    (("[mapping]", "[mapping]\ndirection = 0"), "direction must be 1 or -1; got 0"),
    (("z_max_mm = 0.0", "z_max_mm = \"high\""), "z_max_mm must be a finite number"),
    (("[stage]", "[stage]\nprotocol = \"marlin\""), "protocol must be one of grbl"),
    (("step_mm = 0.02", "step_mm = 0.02 0.03"), "is not valid TOML"),
])
def test_rig_errors_are_one_clear_line(edit, match, tmp_path):
    text = FOLDER_RIG.replace(*edit)
    with pytest.raises(InputError, match=match) as ei:
        parse_rig(text, base_dir=tmp_path)
    assert "\n" not in str(ei.value)


def test_sweep_leaving_soft_limits(tmp_path):
    text = FOLDER_RIG.replace("z_stop_mm = 0.2", "z_stop_mm = 5.2")
    with pytest.raises(InputError, match=r"sweep z_mm 5.0200 needs machine Z 0.0200 mm, outside "
                                         r"the stage soft limits -10.0 .. 0.0 mm"):
        parse_rig(text, base_dir=tmp_path)


def test_missing_rig_file(tmp_path):
    with pytest.raises(InputError, match="rig file not found: .*nope.toml"):
        load_rig(tmp_path / "nope.toml")


def test_fake_options_checked(tmp_path):
    text = sim_rig(tmp_path / "rig.toml").read_text().replace("start_z_mm = 0.0",
                                                                "start_z = 0.0")
    with pytest.raises(InputError, match=r"unknown key\(s\) start_z in \[stage.fake\]"):
        parse_rig(text)


def test_fingerprint_covers_content_not_connection(tmp_path):
    base = parse_rig(FOLDER_RIG).sha256
    same = [("port = \"/dev/ttyUSB0\"", "port = \"/dev/ttyACM1\"\nbaud = 250000\n"
                                        "timeout_s = 9.0\nhome = true"),
            ("pixel_size_mm = 0.01", "pixel_size_mm = 0.01  # a comment")]
    for edit in same:
        assert parse_rig(FOLDER_RIG.replace(*edit)).sha256 == base, edit
    different = [("step_mm = 0.02", "step_mm = 0.04"),
                 ("focus_offset_mm = 5.0", "focus_offset_mm = 5.1"),
                 ("pixel_size_mm = 0.01", "pixel_size_mm = 0.011"),
                 ("[sweep]", "[optics]\nmagnification = 2.0\n[sweep]"),
                 ("z_min_mm = -10.0", "z_min_mm = -9.0")]
    for edit in different:
        assert parse_rig(FOLDER_RIG.replace(*edit)).sha256 != base, edit
    sim = sim_rig(tmp_path / "a.toml").read_text()
    faulty = sim.replace("start_z_mm = 0.0", "start_z_mm = 0.0\nfaults = [{kind = \"alarm\", "
                                             "at_move = 3}]")
    assert parse_rig(sim).sha256 == parse_rig(faulty).sha256


def test_resume_refuses_a_changed_rig_before_touching_the_stage(tmp_path):
    rig = sim_rig(tmp_path / "rig.toml", faults='faults = [{kind = "error", at_move = 6}]')
    with pytest.raises(Exception, match="error:33"):
        acquire(rig, tmp_path / "s")
    changed = tmp_path / "changed.toml"
    changed.write_text(rig.read_text().replace("seed = 7", "seed = 8"))
    with pytest.raises(InputError, match="cannot resume .*: the rig file .* changed since this "
                                         "stack was started"):
        acquire(changed, tmp_path / "s", resume=True)
    changed.write_text(rig.read_text().replace("height_mm = 0.6", "height_mm = 0.5"))
    with pytest.raises(InputError, match="changed since"):
        acquire(changed, tmp_path / "s", resume=True)
    # the same rig without its injected fault (faults do not count) resumes
    rig.write_text(rig.read_text().replace('faults = [{kind = "error", at_move = 6}]', ""))
    assert acquire(rig, tmp_path / "s", resume=True).complete
