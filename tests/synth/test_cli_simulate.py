"""``smdinspect simulate``: writes a readable stack with its truth; refuses to overwrite."""

import json
from pathlib import Path

import numpy as np
import pytest

from smdinspect.cli import main
from smdinspect.stack import FocalStack
from smdinspect._cli.simulate import sweep_heights

DEMO = str(Path(__file__).resolve().parents[2] / "references" / "demo_board.json")


def test_simulate_staircase_writes_a_stack_and_truth(tmp_path, capsys):
    out = tmp_path / "stair"
    rc = main(["-q", "simulate", "staircase", "--out", str(out), "--size", "64", "--seed", "3",
               "--bit-depth", "16"])
    assert rc == 0
    stack = FocalStack.open(out)
    h = np.load(out / "truth" / "height_mm.npy")
    # frames cover the scene: 3 steps of 0.05 mm beyond its lowest and highest point
    assert stack.z_mm[0] <= h.min() - 0.15 + 1e-9 and stack.z_mm[-1] >= h.max() + 0.15 - 1e-9
    assert stack.step_mm == pytest.approx(0.05)
    assert stack.pixel_size_mm == pytest.approx(0.015)
    assert stack.read_frame(0).dtype == np.uint16
    assert stack.meta["seed"] == 3 and stack.meta["scene"] == "staircase"
    assert (out / "truth" / "height_mm.tiff").is_file()
    assert "wrote" in capsys.readouterr().out


def test_simulate_refuses_a_non_empty_out(tmp_path, capsys):
    out = tmp_path / "s"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    rc = main(["-q", "simulate", "plane", "--out", str(out), "--size", "32"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "is not empty; pass --force" in err
    assert not (out / "stack.json").exists()
    rc = main(["-q", "simulate", "plane", "--out", str(out), "--size", "32", "--force",
               "--frames", "5"])
    assert rc == 0
    assert len(FocalStack.open(out)) == 5
    assert (out / "notes.txt").read_text() == "keep me"


@pytest.mark.parametrize("argv, message", [
    (["--z-range-mm", "1,0"], "--z-range-mm needs LO < HI"),
    (["--z-range-mm", "a,b"], "--z-range-mm must be two numbers"),
    (["--step-mm", "-0.1"], "--step-mm must be > 0"),
    (["--defects", "R1.1:bridge"], "--defects is only for 'simulate board'"),
    (["--frames", "2"], "--frames must be >= 3"),
    (["--fillet-curvature", "0.5,1"], "--fillet-curvature is only for 'simulate board'"),
])
def test_simulate_bad_arguments(tmp_path, capsys, argv, message):
    rc = main(["-q", "simulate", "cone", "--out", str(tmp_path / "c"), "--size", "32", *argv])
    assert rc == 2
    assert message in capsys.readouterr().err


def test_sweep_heights():
    z = sweep_heights((0.0, 1.0), step_mm=0.1)
    assert z[0] > z[-1]  # the camera moves down: h_n = d - (d_f + n*step)
    np.testing.assert_allclose(np.diff(z), -0.1)
    assert z[-1] <= -0.3 + 1e-9 and z[0] >= 1.3 - 1e-9
    np.testing.assert_allclose(sweep_heights((0, 1), step_mm=0.05, z_range=(0.0, 0.5)),
                               np.linspace(0.5, 0.0, 11))
    z = sweep_heights((0, 1), step_mm=0.05, frames=40)       # spans the scene: centred
    assert len(z) == 40 and abs(z[0] + z[-1] - 1.0) < 1e-9
    # Too few frames for a tall scene (an upright part): the board stays in range.
    z = sweep_heights((0, 3.2), step_mm=0.05, frames=40)
    np.testing.assert_allclose([z[-1], z[0]], [-0.15, -0.15 + 39 * 0.05])


def test_simulate_cone_has_about_forty_frames(tmp_path):
    rc = main(["-q", "simulate", "cone", "--out", str(tmp_path / "c"), "--size", "48",
               "--noise", "off"])
    assert rc == 0
    doc = json.loads((tmp_path / "c" / "stack.json").read_text())
    assert 36 <= len(doc["frames"]) <= 42
    assert doc["meta"]["sensor"]["read_noise_e"] == 0 and not doc["meta"]["sensor"]["shot_noise"]


def test_simulate_board_writes_labels(tmp_path):
    out = tmp_path / "b"
    rc = main(["-q", "simulate", "board", "--board", DEMO,
               "--defects", "R1.1:insufficient,U1.4:bridge", "--seed", "7",
               "--pixel-size-mm", "0.05", "--step-mm", "0.25", "--offset-mm", "0.5,-0.25",
               "--rotate-deg", "3", "--out", str(out)])
    assert rc == 0
    stack = FocalStack.open(out)
    labels = json.loads((out / "truth" / "labels.json").read_text())
    h = np.load(out / "truth" / "height_mm.npy")
    assert list(h.shape) == labels["image_shape"] == list(stack.read_frame(0).shape[:2])
    assert labels["placement"]["offset_mm"] == pytest.approx([0.5, -0.25])
    assert labels["placement"]["rotate_deg"] == pytest.approx(3.0)
    classes = {j["id"]: j["class"] for j in labels["joints"]}
    assert classes["R1.1"] == "insufficient" and classes["U1.4"] == "bridge"
    assert sum(c == "ok" for c in classes.values()) == len(classes) - 2
    # the sweep runs from below the board to above the tallest part
    assert stack.z_mm[0] < min(0.0, h.min()) and stack.z_mm[-1] > h.max()
    scene_doc = json.loads((out / "truth" / "scene.json").read_text())
    assert scene_doc["labels"] == "labels.json"


def test_simulate_board_with_arc_fillets(tmp_path, capsys):
    """--fillet-curvature renders the chip fillets as arcs: the same board and seed
    keep their fillet heights but change the fillets' profile; a bad range is one line
    and exit 2, with nothing written."""
    args = ["-q", "simulate", "board", "--board", DEMO, "--seed", "7", "--pixel-size-mm",
            "0.05", "--step-mm", "0.25", "--offset-mm", "0,0", "--rotate-deg", "0"]
    assert main(args + ["--out", str(tmp_path / "p")]) == 0
    assert main(args + ["--out", str(tmp_path / "a"), "--fillet-curvature", "1,1"]) == 0
    lab = {n: {j["id"]: j for j in json.loads((tmp_path / n / "truth" / "labels.json")
                                               .read_text())["joints"]} for n in "pa"}
    h = {n: np.load(tmp_path / n / "truth" / "height_mm.npy") for n in "pa"}
    for jid in ("R2.1", "C1.2"):
        # the label is the highest pixel: at 50 µm/px the arc, vertical at the end face,
        # has fallen by the pixel next to it (R2.1: 0.23 against the parabola's 0.28 mm)
        assert 0.75 < lab["a"][jid]["true_height_mm"] / lab["p"][jid]["true_height_mm"] <= 1.0
    assert np.abs(h["a"] - h["p"]).max() > 0.05
    capsys.readouterr()
    rc = main(args + ["--out", str(tmp_path / "x"), "--fillet-curvature", "0.5,2"])
    err = capsys.readouterr().err
    assert rc == 2 and "fillet_curvature must satisfy 0 <= lo <= hi <= 1" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_simulate_board_rejects_unknown_joint(tmp_path, capsys):
    rc = main(["-q", "simulate", "board", "--board", DEMO,
               "--defects", "Q9.1:bridge", "--out", str(tmp_path / "b")])
    assert rc == 2
    assert "Q9.1" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_noise_seed_sweeps_the_same_scene_again(tmp_path):
    args = ["-q", "simulate", "plane", "--size", "48", "--seed", "4", "--frames", "5"]
    for name, extra in (("a", []), ("b", ["--noise-seed", "9"]), ("c", ["--noise-seed", "4"])):
        assert main(args + ["--out", str(tmp_path / name)] + extra) == 0
    frames = {n: FocalStack.open(tmp_path / n).read_frame(2).astype(int) for n in "abc"}
    truth = {n: np.load(tmp_path / n / "truth" / "height_mm.npy") for n in "abc"}
    assert np.array_equal(truth["a"], truth["b"])  # the same scene ...
    assert not np.array_equal(frames["a"], frames["b"])  # ... other sensor noise
    assert np.array_equal(frames["a"], frames["c"])  # --noise-seed defaults to --seed
    assert main(args + ["--out", str(tmp_path / "d"), "--noise-seed", "-1"]) == 2
