"""Focal-plane calibration on rendered flat-target sweeps with known tilt and curvature.

A flat target seen through a tilted, curved field of best focus reconstructs exactly as a
tilted, curved target seen through a flat field, so the sweeps render a target whose
height is the focal-plane error: the calibration must find that shape, and a second
sweep (another texture, another noise seed) corrected with it must come out flat.
"""

import json
import re
import math

import numpy as np
import pytest

from smdinspect.calibrate import (FocalPlaneCalibration, apply_calibration, calibrate_flat,
                                  read_calibration)
from smdinspect.cli import main
from smdinspect.errors import InputError
from smdinspect.optics import Optics
from smdinspect.sff import reconstruct
from smdinspect.synth import Scene, band_limited_texture, render_stack

PIXEL = 0.015
STEP = 0.05
N = 256


def focal_error_mm(*, tilt_deg, azimuth_deg, sag_mm, shape=(N, N)):
    """Tilt (at the centre) plus a paraboloid with ``sag_mm`` from centre to corner."""
    h, w = shape
    rows, cols = np.indices(shape, dtype=np.float64)
    x = (cols - (w - 1) / 2) * PIXEL
    y = ((h - 1) / 2 - rows) * PIXEL
    a = math.radians(azimuth_deg)
    tilt = math.tan(math.radians(tilt_deg)) * (x * math.cos(a) + y * math.sin(a))
    r2 = (x ** 2 + y ** 2) / (x ** 2 + y ** 2).max()
    return tilt + sag_mm * r2


def flat_sweep(root, error_mm, *, seed):
    albedo = np.clip(band_limited_texture(error_mm.shape, seed=seed, contrast=0.25), 0, 1)
    scene = Scene(error_mm.astype(np.float32), albedo.astype(np.float32), PIXEL, name="flat")
    z = np.round(np.arange(error_mm.min() - 0.2, error_mm.max() + 0.2 + 1e-9, STEP) + 0.013, 6)
    return render_stack(scene, z, optics=Optics.for_pixel_size(PIXEL), seed=seed, out=root,
                        previews=False)


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    err = focal_error_mm(tilt_deg=0.8, azimuth_deg=30.0, sag_mm=0.045)
    root = tmp_path_factory.mktemp("flat")
    return err, flat_sweep(root / "a", err, seed=1), flat_sweep(root / "b", err, seed=2)


def test_tilt_and_curvature_are_found_and_removed(sweeps):
    err, first, second = sweeps
    cal = calibrate_flat(reconstruct(first))
    assert cal.tilt_deg == pytest.approx(0.8, abs=0.05)
    assert cal.tilt_azimuth_deg == pytest.approx(30.0, abs=3.0)
    assert cal.curvature_sag_mm == pytest.approx(0.045, abs=0.006)
    truth = err - err[(N - 1) // 2, (N - 1) // 2]
    model_err = cal.correction_mm() - truth
    assert np.sqrt(np.mean(model_err ** 2)) <= 0.1 * STEP
    # The second sweep, corrected: flat to within 0.1 Δd RMS (median-free: the mean shape).
    s2 = reconstruct(second)
    fixed = apply_calibration(s2, cal)
    ok = fixed.reliable
    before = s2.height_mm[ok] - np.median(s2.height_mm[ok])
    after = fixed.height_mm[ok] - np.median(fixed.height_mm[ok])
    shape_after = calibrate_flat(fixed)
    assert shape_after.tilt_deg < 0.02 and shape_after.curvature_sag_mm < 0.1 * STEP
    assert np.sqrt(np.mean(after ** 2)) < 0.5 * np.sqrt(np.mean(before ** 2))
    print(f"\ncalibration: {cal.summary()}\nmodel error RMS "
          f"{np.sqrt(np.mean(model_err ** 2)) / STEP:.3f} Δd; corrected second sweep: pixel "
          f"RMS {np.sqrt(np.mean(after ** 2)) / STEP:.3f} Δd (was "
          f"{np.sqrt(np.mean(before ** 2)) / STEP:.3f} Δd)")


def test_calibration_round_trips_and_checks_the_shape(sweeps, tmp_path):
    err, first, _ = sweeps
    cal = calibrate_flat(reconstruct(first), degree=1)
    back = FocalPlaneCalibration.from_dict(json.loads(json.dumps(cal.to_dict())))
    assert back == cal
    s = reconstruct(first)
    from dataclasses import replace
    small = replace(s, height_mm=s.height_mm[:100, :100])
    with pytest.raises(InputError, match=r"calibration is for 256x256 px images; this "
                                         r"reconstruction is 100x100 px"):
        apply_calibration(small, cal)
    with pytest.raises(InputError, match="degree must be an integer in 1..4; got 7"):
        calibrate_flat(s, degree=7)


def test_cli_flat_then_reconstruct_with_the_calibration(sweeps, tmp_path, capsys):
    import tifffile

    err, first, second = sweeps
    rig = tmp_path / "rig.toml"
    rig.write_text('[camera]\nkind = "opencv"\npixel_size_mm = 0.015\n')
    assert main(["calibrate", "flat", str(first.root), "--rig", str(rig)]) == 0
    out = capsys.readouterr().out
    assert re.search(r"tilt 0\.(79|8)\d*° towards 3\d°", out) and "field curvature sag" in out
    cal_path = tmp_path / "rig.cal.json"
    assert read_calibration(cal_path)["focal_plane"].degree == 2
    plain, fixed = tmp_path / "plain", tmp_path / "fixed"
    assert main(["reconstruct", str(second.root), "--out", str(plain)]) == 0
    assert main(["reconstruct", str(second.root), "--out", str(fixed), "--calibration",
                 str(cal_path)]) == 0
    h0 = tifffile.imread(plain / "height_mm.tiff")
    h1 = tifffile.imread(fixed / "height_mm.tiff")
    corr = read_calibration(cal_path)["focal_plane"].correction_mm()
    assert np.allclose(h0 - h1, corr, atol=1e-6)
