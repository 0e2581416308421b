"""benchmarks/solder_slopes.py: solder pixels binned by true slope, with their errors."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import solder_slopes  # noqa: E402

from smdinspect.synth import Scene  # noqa: E402


def _ramp_scene():
    """Two ramps 0.1-0.7 mm high, rising 30° (left) and 60° (right); solder is shiny."""
    p = 0.01
    x = np.arange(200) * p
    z = np.empty((40, 200), np.float32)
    z[:, :100] = 0.1 + np.tan(np.radians(30)) * x[:100] * 0.5
    z[:, 100:] = 0.1 + np.tan(np.radians(60)) * (x[100:] - x[100]) * 0.5
    # the right ramp rises from 0.1 mm at its first column: ~0.1 + 0.866·1.0 > 0.8 at its end
    spec = np.ones_like(z)
    spec[:20] = 0.0  # the top half matte: never solder
    return Scene(height_mm=z, albedo=np.full(z.shape, 0.5, np.float32), pixel_size_mm=p,
                 specular=spec)


def test_pixels_are_binned_by_true_slope_with_their_reasons_and_errors():
    scene = _ramp_scene()
    solder, slope = solder_slopes.solder_pixels(scene)
    assert not solder[:20].any()            # matte: not solder
    inner = slope[25:35, 5:95]
    assert np.allclose(inner, np.degrees(np.arctan(0.5 * np.tan(np.radians(30)))), atol=0.1)
    err = np.zeros(scene.height_mm.shape)
    err[:, :100] = 0.010                    # left ramp reads 10 µm high
    reason = np.zeros(scene.height_mm.shape, np.uint8)
    reason[30:, 100:] = 6                   # half the right ramp's solder: a halo
    surface = SimpleNamespace(height_mm=scene.height_mm + err, reason=reason)
    t = solder_slopes.tally([(scene, surface)])
    low = next(b for b in solder_slopes.BINS if b[0] <= 16.1 < b[1])
    steep = next(b for b in solder_slopes.BINS if b[0] <= 40.9 < b[1])
    assert t[low]["n"] > 0 and set(t[low]["err"]) == {0}
    assert np.allclose(np.concatenate(t[low]["err"][0]), 10.0, atol=1e-3)
    assert set(t[steep]["err"]) == {0, 6}
    text = solder_slopes.report(t)
    assert "halo" in text and "100%" in text
