"""``smdinspect grr`` end to end on simulated re-placed sweeps of the demo board.

Three small sweeps (30 µm/px, 511 × 511 px, 38 frames), each with its own seed: its own
placement (offset within ±2 mm, rotation within ±5°) and sensor noise.
"""

import csv
import json
import math

import pytest

from smdinspect.cli import main

DEMO = "references/demo_board.json"
DENSE = "references/dense_board.json"


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    root = tmp_path_factory.mktemp("grr")
    stacks = []
    for seed, noise in ((1, "normal"), (2, "normal"), (3, "low")):
        out = root / f"sweep{seed}"
        assert main(["-q", "simulate", "board", "--out", str(out), "--seed", str(seed),
                     "--noise", noise, "--pixel-size-mm", "0.03"]) == 0
        stacks.append(str(out))
    return root, stacks


@pytest.fixture(scope="module")
def study(sweeps):
    root, stacks = sweeps
    code = main(["-q", "grr", *stacks, "--board", DEMO, "--out", str(root / "grr")])
    return root, code


def test_grr_of_three_sweeps(study, capsys):
    root, code = study
    out = root / "grr"
    doc = json.loads((out / "grr.json").read_text())
    assert code == doc["exit_code"] and code in (0, 1)
    assert [s["label"] for s in doc["sweeps"]] == ["sweep1", "sweep2", "sweep3"]
    rows = {(r["scope"], r["key"], r["metric"]): r
            for r in csv.DictReader(open(out / "grr.csv"))}
    soic = rows[("type", "SOIC-8/gullwing_heel", "max_height_mm")]
    assert soic["n_parts"] == "8" and soic["n"] == "24" and soic["method"] == "one-way"
    pct = float(soic["pct_grr_tolerance"])
    sigma = float(soic["sigma_repeatability"])
    assert math.isfinite(pct) and 0 < pct < 100 and 0 < sigma < 0.05  # below one step
    assert pct == pytest.approx(600 * sigma / (0.572 - 0.13), rel=1e-3)
    joint = rows[("joint", "U1.1", "max_height_mm")]
    assert joint["n"] == "3" and float(joint["pct_grr_tolerance"]) > 0
    assert (out / "grr.png").read_bytes()[:4] == b"\x89PNG"
    assert all((out / "inspections" / f"sweep{k}" / "report.json").is_file() for k in (1, 2, 3))


def test_the_same_study_again_into_the_same_folder(study, sweeps, capsys):
    """A second run replaces the first one's outputs, each sweep's inspection folder
    included (it failed on the IPC-CFX file the inspection writes there), and says why a
    joint has no figure."""
    root, code = study
    _, stacks = sweeps
    capsys.readouterr()
    again = main(["grr", *stacks, "--board", DEMO, "--out", str(root / "grr")])
    out = capsys.readouterr().out
    assert again == code, out
    assert (root / "grr" / "inspections" / "sweep1" / "cfx_units_inspected.json").is_file()
    rows = list(csv.DictReader(open(root / "grr" / "grr.csv")))
    short = [r["key"] for r in rows if r["scope"] == "joint" and r["metric"] == "max_height_mm"
             and not r["pct_grr_tolerance"]]
    assert short  # at 30 µm/px the 1206's fillet tops are not measured
    for key in short:
        assert f"    {key}: unreliable in " in out or f"    {key}: no max height read" in out, out


def test_report_folders_and_operators_from_a_manifest(study, capsys):
    root, _ = study
    capsys.readouterr()
    manifest = root / "sweeps.csv"
    reports = root / "grr" / "inspections"
    manifest.write_text("stack,operator\n" + "".join(
        f"{reports / s},{o}\n" for s, o in (("sweep1", "A"), ("sweep2", "A"), ("sweep3", "B"),
                                           ("sweep1", "B"))))
    code = main(["grr", "--manifest", str(manifest), "--board", DEMO,
                 "--out", str(root / "grr2"), "--fail-above", "100"])
    printed = capsys.readouterr().out
    assert code == 0 and "4 sweeps of demo_board, 2 operator(s) (A, B)" in printed
    assert "SOIC-8/gullwing_heel" in printed and "grr.csv" in printed
    rows = {(r["scope"], r["key"], r["metric"]): r
            for r in csv.DictReader(open(root / "grr2" / "grr.csv"))}
    soic = rows[("type", "SOIC-8/gullwing_heel", "max_height_mm")]
    assert soic["method"] == "crossed" and soic["n_operators"] == "2"
    assert math.isfinite(float(soic["pct_grr_tolerance"]))
    assert not (root / "grr2" / "inspections").exists()  # reports were taken as they are


@pytest.mark.parametrize("argv, code, message", [
    (lambda s: [s[0]], 2, "at least 2 sweeps of the board; got 1"),
    (lambda s: [s[0], s[1], "--operators", "A"], 2, "one operator per STACK"),
    (lambda s: [s[0], s[1], "--operators", "A,A", "--manifest", "m.csv"], 2, "not both"),
    (lambda s: [s[0], s[1], "--calibration", "none.cal.json"], 2,
     "calibration file 'none.cal.json' does not exist"),
])
def test_argument_errors_are_one_line(sweeps, capsys, argv, code, message, tmp_path):
    _, stacks = sweeps
    assert main(["grr", *argv(stacks), "--board", DEMO, "--out", str(tmp_path / "g")]) == code
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and err.startswith("smdinspect grr: error:")
    assert not (tmp_path / "g").exists()


def test_mismatched_board_is_one_line(study, capsys, tmp_path):
    root, _ = study
    reports = [str(root / "grr" / "inspections" / f"sweep{k}") for k in (1, 2)]
    capsys.readouterr()
    assert main(["grr", *reports, "--board", DENSE, "--out", str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err
    assert "inspected against board 'demo_board', not 'dense_board'" in err
    assert err.count("\n") == 1
