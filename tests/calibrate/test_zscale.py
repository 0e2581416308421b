"""z scale and direction from rendered sweeps of a step target whose stage lies about its z.

The frames are rendered at the heights the stage really reached (a step 4 % longer than
it reports) and the stack records the nominal ones: the reconstruction reads the step
4 % short, the calibration must find the scale, and the corrected reconstruction (through
``reconstruct --calibration``) must read the known step.
"""

import json

import numpy as np
import pytest
import tifffile

from smdinspect.calibrate import (ZScaleCalibration, apply_z_scale, calibrate_z_scale,
                                  read_calibration, write_calibration)
from smdinspect.cli import main
from smdinspect.errors import InputError
from smdinspect.optics import Optics
from smdinspect.sff import reconstruct
from smdinspect.stack import FocalStack
from smdinspect.synth import Scene, band_limited_texture, render_stack

PIXEL = 0.015
STEP = 0.05
N = 160
BLOCK_MM = 0.40
TRUE_SCALE = 1.04  # the stage's real step over the one it reports


def step_scene(seed, *, block=BLOCK_MM, tilt=0.0):
    rows, cols = np.indices((N, N), dtype=np.float64)
    height = np.where((rows > 35) & (rows < 125) & (cols > 30) & (cols < 115), block, 0.0)
    height = height + tilt * (cols - N / 2) * PIXEL  # a tilted stage: both faces alike
    albedo = np.clip(band_limited_texture((N, N), seed=seed, contrast=0.25), 0, 1)
    return Scene(height.astype(np.float32), albedo.astype(np.float32), PIXEL, name="step")


def sweep(root, scene, *, seed, flip=False):
    """Frames rendered at the true z, the stack.json written with the nominal z."""
    nominal = np.round(np.arange(-0.2, BLOCK_MM + 0.25 + 1e-9, STEP) + 0.013, 6)
    true = nominal[0] + TRUE_SCALE * (nominal - nominal[0])
    render_stack(scene, true, optics=Optics.for_pixel_size(PIXEL), seed=seed, out=root,
                 previews=False)
    manifest = root / "stack.json"
    doc = json.loads(manifest.read_text())
    by_true = {round(f["z_mm"], 6): f for f in doc["frames"]}
    for zt, zn in zip(true, nominal):
        by_true[round(float(zt), 6)]["z_mm"] = float(-zn if flip else zn)
    doc["frames"] = sorted(doc["frames"], key=lambda f: f["z_mm"])
    manifest.write_text(json.dumps(doc))
    return FocalStack.open(root)


@pytest.fixture(scope="module")
def step_sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("zstep") / "s"
    return sweep(root, step_scene(3, tilt=0.004), seed=3)


def test_the_scale_is_found_and_the_corrected_step_reads_true(step_sweep):
    surface = reconstruct(step_sweep)
    cal = calibrate_z_scale(surface, step_height_mm=BLOCK_MM)
    assert cal.measured_step_mm == pytest.approx(BLOCK_MM / TRUE_SCALE, rel=0.01)
    assert cal.scale == pytest.approx(TRUE_SCALE, abs=0.01)  # measured 1.04
    assert 0 < cal.scale_sigma < 0.01
    assert 0.2 < cal.top_share < 0.6
    fixed = apply_z_scale(surface, cal)
    again = calibrate_z_scale(fixed, step_height_mm=BLOCK_MM)
    assert again.measured_step_mm == pytest.approx(BLOCK_MM, rel=0.005)
    # the lowest frame keeps its z; widths and the frames' z scale alike
    assert fixed.z_mm[0] == pytest.approx(surface.z_mm[0])
    np.testing.assert_allclose(np.diff(fixed.z_mm), np.diff(surface.z_mm) * cal.scale)


def test_the_command_writes_the_scale_and_reconstruct_applies_it(step_sweep, tmp_path, capsys):
    cal_path = tmp_path / "rig.cal.json"
    write_calibration(cal_path)  # an existing file: its other sections are kept
    doc = json.loads(cal_path.read_text())
    doc["pixel_size"] = {"pixel_size_mm": PIXEL}
    cal_path.write_text(json.dumps(doc))
    assert main(["-q", "calibrate", "z-scale", str(step_sweep.root), "--step-height-mm",
                 str(BLOCK_MM), "--out", str(cal_path)]) == 0
    out = capsys.readouterr().out
    assert "z scale 1.0" in out and "after the correction the step reads" in out
    cal = read_calibration(cal_path)
    assert cal["pixel_size_mm"] == PIXEL
    assert cal["z_scale"].scale == pytest.approx(TRUE_SCALE, abs=0.01)
    assert main(["-q", "reconstruct", str(step_sweep.root), "--calibration", str(cal_path),
                 "--out", str(tmp_path / "r"), "--outputs", "height_mm.tiff,confidence.tiff"]) == 0
    h = tifffile.imread(tmp_path / "r" / "height_mm.tiff")
    ok = tifffile.imread(tmp_path / "r" / "confidence.tiff") >= 0.5
    top = np.median(h[40:120, 35:110][ok[40:120, 35:110]])
    base = np.median(h[:, 125:][ok[:, 125:]])
    # the stage's tilt (0.004 mm/mm) moves the two medians' columns apart by ~0.01 mm
    assert top - base == pytest.approx(BLOCK_MM, abs=0.015)
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["z_scale_calibration"]["scale"] == pytest.approx(TRUE_SCALE, abs=0.01)


def test_a_z_axis_running_the_wrong_way_is_an_error(tmp_path, capsys):
    stack = sweep(tmp_path / "f", step_scene(5), seed=5, flip=True)
    with pytest.raises(InputError, match="runs the wrong way"):
        calibrate_z_scale(reconstruct(stack), step_height_mm=BLOCK_MM)
    code = main(["-q", "calibrate", "z-scale", str(stack.root), "--step-height-mm", "0.4",
                 "--out", str(tmp_path / "c.json")])
    err = capsys.readouterr().err
    assert code == 2 and "flip the sign of --step-mm" in err.lower()
    assert not (tmp_path / "c.json").exists()


def test_a_target_without_a_step_or_a_bad_height_is_refused(step_sweep, tmp_path):
    surface = reconstruct(step_sweep)
    flat = type(surface)(**{**surface.__dict__,
                            "height_mm": np.full_like(surface.height_mm, 0.1)})
    with pytest.raises(InputError, match="no step|one level"):
        calibrate_z_scale(flat, step_height_mm=BLOCK_MM)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputError, match="positive"):
            calibrate_z_scale(surface, step_height_mm=bad)
    with pytest.raises(InputError, match="no stage error"):
        calibrate_z_scale(surface, step_height_mm=400.0)  # µm given as mm
    with pytest.raises(InputError, match="outside"):
        calibrate_z_scale(surface, step_height_mm=BLOCK_MM, top_at=(500, 3))
    # --top-at on the base: the named level reads below the other, as a flipped axis would
    with pytest.raises(InputError, match="BELOW"):
        calibrate_z_scale(surface, step_height_mm=BLOCK_MM, top_at=(150, 150))


def test_the_calibration_file_round_trips_and_rejects_nonsense(tmp_path):
    cal = ZScaleCalibration(scale=1.03, known_step_mm=0.5, measured_step_mm=0.4854,
                            scale_sigma=0.002, step_mm=0.05, top_share=0.4,
                            residual_rms_mm=0.004, coverage=0.9)
    path = write_calibration(tmp_path / "c.json", z_scale=cal)
    assert read_calibration(path)["z_scale"] == cal
    doc = json.loads(path.read_text())
    doc["z_scale"]["scale"] = -2
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="z scale must be"):
        read_calibration(path)
    doc["z_scale"] = {"scale": 1.0}
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="missing or bad field"):
        read_calibration(path)


def test_simulate_step_with_a_lying_stage_then_calibrate(tmp_path, capsys):
    """The README's try-it path: `simulate step --stage-scale` renders the frames at the
    stage's true z and records the nominal one; `calibrate z-scale` finds the scale."""
    out = tmp_path / "step"
    assert main(["-q", "simulate", "step", "--size", "128", "--stage-scale", "0.97",
                 "--block-mm", "0.3", "--out", str(out)]) == 0
    assert json.loads((out / "truth" / "scene.json").read_text())["stage_scale"] == 0.97
    capsys.readouterr()
    assert main(["-q", "calibrate", "z-scale", str(out), "--step-height-mm", "0.3",
                 "--out", str(tmp_path / "c.json")]) == 0
    cal = read_calibration(tmp_path / "c.json")["z_scale"]
    assert cal.scale == pytest.approx(0.97, abs=0.003)
    assert abs(cal.scale - 0.97) <= 3 * cal.scale_sigma  # within the uncertainty it states
    assert main(["-q", "simulate", "cone", "--block-mm", "0.3", "--out", str(tmp_path / "x")]) == 2
    assert main(["-q", "simulate", "step", "--stage-scale", "0", "--out", str(tmp_path / "y")]) == 2
