"""Pixel size and lens distortion from rendered targets of known pitch."""

import math

import cv2
import numpy as np
import pytest

from smdinspect.calibrate import (pixel_size_from_image, read_calibration, set_rig_pixel_size,
                                  write_calibration)
from smdinspect.cli import main
from smdinspect.errors import InputError


def render_target(kind, *, pixel_mm, pitch_mm, shape=(480, 640), angle_deg=0.0, k1=0.0,
                  seed=0, noise=2.0, ss=3):
    """A target photographed with object-side pixel ``pixel_mm`` and radial distortion
    ``k1`` (the model of smdinspect.calibrate._pixel), supersampled ``ss``² times."""
    h, w = shape
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h * ss, 0:w * ss].astype(np.float64)
    px, py = (xx + 0.5) / ss - 0.5, (yy + 0.5) / ss - 0.5
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    R = math.hypot(w / 2, h / 2)
    # invert p = c + (q - c)(1 + k1 |q - c|²/R²) for the ideal position q of each sample
    dx, dy = px - c[0], py - c[1]
    qx, qy = dx.copy(), dy.copy()
    for _ in range(8):
        f = 1 + k1 * (qx ** 2 + qy ** 2) / R ** 2
        qx, qy = dx / f, dy / f
    a = math.radians(angle_deg)
    u = (qx * math.cos(a) + qy * math.sin(a)) * pixel_mm / pitch_mm
    v = (-qx * math.sin(a) + qy * math.cos(a)) * pixel_mm / pitch_mm
    if kind == "dots":
        d = np.hypot(u - np.round(u), v - np.round(v))
        val = np.where(d < 0.3, 0.15, 0.9)
    else:
        val = np.where((np.floor(u + 0.5) + np.floor(v + 0.5)) % 2 == 0, 0.85, 0.1)
        val[(np.abs(u) > 6.5) | (np.abs(v) > 4.5)] = 0.5
    img = val.reshape(h, ss, w, ss).mean(axis=(1, 3)) * 255
    img = cv2.GaussianBlur(img, (0, 0), 0.8) + rng.normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("kind, angle, k1", [("dots", 0.0, 0.0), ("dots", 4.0, -0.01),
                                             ("checkerboard", -3.0, 0.008)])
def test_pixel_size_and_distortion_are_recovered(kind, angle, k1):
    pixel, pitch = 0.012, 0.5 if kind == "dots" else 0.6
    img = render_target(kind, pixel_mm=pixel, pitch_mm=pitch, angle_deg=angle, k1=k1, seed=3)
    res = pixel_size_from_image(img, pitch_mm=pitch)
    assert res.target == kind
    assert res.pixel_size_mm == pytest.approx(pixel, rel=2e-3)
    assert res.pixel_size_x_mm == pytest.approx(res.pixel_size_y_mm, rel=3e-3)
    assert ((res.grid_angle_deg - angle + 45) % 90 - 45) == pytest.approx(0, abs=0.1)
    assert res.k1 == pytest.approx(k1, abs=1.5e-3)
    assert res.residual_rms_px < 0.15
    assert res.n_points >= 60
    if k1:
        assert res.affine_residual_rms_px > 2 * res.residual_rms_px


def test_no_target_is_an_input_error():
    img = np.random.default_rng(0).integers(100, 110, (200, 200)).astype(np.uint8)
    with pytest.raises(InputError, match="no checkerboard or dot grid target found"):
        pixel_size_from_image(img, pitch_mm=0.5)
    with pytest.raises(InputError, match="pitch_mm must be > 0; got -1"):
        pixel_size_from_image(img, pitch_mm=-1)


def test_cli_writes_the_calibration_and_the_rig(tmp_path, capsys):
    img = render_target("dots", pixel_mm=0.015, pitch_mm=0.5, angle_deg=2.0, seed=1)
    target = tmp_path / "target.png"
    cv2.imwrite(str(target), img)
    rig = tmp_path / "rig.toml"
    rig.write_text('[camera]\nkind = "folder"  # frames\npath = "frames"\npixel_size_mm = 0.02\n\n'
                   '[sweep]\nz_start_mm = 0.0\nz_stop_mm = 1.0\nstep_mm = 0.05\n')
    assert main(["calibrate", "pixel-size", str(target), "--pitch-mm", "0.5", "--rig", str(rig),
                 "--update-rig"]) == 0
    out = capsys.readouterr().out
    assert "pixel size 15.0" in out and "rig.toml: [camera] pixel_size_mm 0.02 →" in out
    cal = read_calibration(tmp_path / "rig.cal.json")
    assert cal["pixel_size_mm"] == pytest.approx(0.015, rel=2e-3)
    import tomllib
    doc = tomllib.loads(rig.read_text())
    assert doc["camera"]["pixel_size_mm"] == pytest.approx(0.015, rel=2e-3)
    assert doc["camera"]["path"] == "frames" and doc["sweep"]["step_mm"] == 0.05
    # setting it where the rig has none adds the line under [camera]
    rig2 = tmp_path / "rig2.toml"
    rig2.write_text('[camera]\nkind = "opencv"\n')
    set_rig_pixel_size(rig2, 0.0123)
    assert tomllib.loads(rig2.read_text())["camera"]["pixel_size_mm"] == 0.0123
    # the calibration file keeps its other sections when one is rewritten
    write_calibration(tmp_path / "rig.cal.json")
    assert read_calibration(tmp_path / "rig.cal.json")["pixel_size_mm"] == cal["pixel_size_mm"]
