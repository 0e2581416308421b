"""The simulated rig end to end: fake GRBL on a pty + simulated camera -> stack -> SFF."""

from __future__ import annotations

import numpy as np
import pytest

from smdinspect.acquire import Rig, SimulatedCamera, acquire, load_rig
from smdinspect.errors import InputError
from smdinspect.optics import Optics
from smdinspect.sff import FocusConfig, reconstruct
from smdinspect.stack import FocalStack
from smdinspect.synth import SensorConfig, cone_scene, render_frame, render_stack

from .rigs import sim_rig


def cone(size):
    return cone_scene(size_px=size, pixel_size_mm=0.015, height_mm=0.6, seed=7)


OPTICS = Optics.for_pixel_size(0.015, focal_length_mm=50.0, aperture_mm=50.0,
                               pixel_pitch_mm=0.015)


def test_sim_sweep_reconstructs_the_cone(tmp_path):
    rig = sim_rig(tmp_path / "rig.toml", size=128)
    res = acquire(rig, tmp_path / "s")
    assert res.complete and res.n_frames == 19
    stack = FocalStack.open(tmp_path / "s")
    np.testing.assert_allclose(stack.z_mm, -0.15 + 0.05 * np.arange(19), atol=1e-9)
    assert stack.pixel_size_mm == 0.015
    assert stack.optics["pixel_size_mm"] == pytest.approx(0.015)
    surface = reconstruct(stack, FocusConfig())
    truth = cone(128).height_mm
    err = np.abs(surface.height_mm - truth)[surface.reliable]
    assert surface.reliable.mean() > 0.8
    # the acceptance: median |error| on confident pixels <= 0.1 step
    assert np.median(err) <= 0.1 * 0.05, np.median(err)


def test_sim_frames_equal_directly_rendered_frames(tmp_path):
    acquire(sim_rig(tmp_path / "rig.toml"), tmp_path / "s")
    stack = FocalStack.open(tmp_path / "s")
    sensor = SensorConfig.preset("low")
    direct = render_stack(cone(64), stack.z_mm, optics=OPTICS, sensor=sensor, seed=7)
    for (i, z, frame), ref in zip(stack.iter_frames(), direct):
        np.testing.assert_array_equal(frame, ref, err_msg=f"frame {i} at z {z}")


def test_sim_camera_renders_at_the_z_the_stage_reports(tmp_path):
    with Rig(load_rig(sim_rig(tmp_path / "rig.toml"))) as rig:
        rig.stage.move_to(-4.7)  # mapping: z_mm = 5 + machine z = 0.3
        frame, meta = rig.camera.capture()
        assert meta["z_rendered_mm"] == pytest.approx(0.3, abs=1e-9)
        ref = render_frame(cone(64), 0.3, optics=OPTICS, sensor=SensorConfig.preset("low"),
                           rng=7)
        np.testing.assert_array_equal(frame, ref)
        # the fake moves (not the camera): nudge it behind the rig's back
        rig.fake.inject("error", at_move=99)  # no effect; just touching the controller
        rig.stage.move_to(-4.6525)  # 0.3475: the camera follows the reported position
        _, meta = rig.camera.capture()
        assert meta["z_rendered_mm"] in (pytest.approx(0.347, abs=1e-9),
                                          pytest.approx(0.348, abs=1e-9))


def test_frames_per_step_averaging_cuts_noise(tmp_path):
    scene = cone(64)
    sensor = SensorConfig.preset("high", flicker=0.0)
    noiseless = SensorConfig.preset("high", flicker=0.0, read_noise_e=0.0, shot_noise=False)
    clean = render_frame(scene, 0.3, optics=OPTICS, sensor=noiseless, rng=0).astype(np.float64)
    z = [0.3]
    cam = SimulatedCamera(scene, optics=OPTICS, sensor=sensor, seed=3, z_source=lambda: z[0])
    from smdinspect.acquire import capture_average

    one, _ = capture_average(cam, 1)
    z[0] = 0.35
    cam.capture()
    z[0] = 0.3
    four, meta = capture_average(cam, 4)
    assert meta["n_averaged"] == 4
    noise1 = np.std(one - clean)
    noise4 = np.std(four - clean)
    assert 0.4 < noise4 / noise1 < 0.62, (noise1, noise4)  # ~ 1/sqrt(4)
    # the first capture at a height is the renderer's frame for that height
    np.testing.assert_array_equal(one, render_frame(scene, 0.3, optics=OPTICS, sensor=sensor,
                                                    rng=3))


def test_simulated_camera_config_errors(tmp_path):
    text = sim_rig(tmp_path / "rig.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('scene = "cone"', 'scene = "sphere"'))
    with pytest.raises(InputError, match="scene must be one of cone, staircase"):
        acquire(bad, tmp_path / "s1")
    bad.write_text(text.replace('scene = "cone"', ""))
    with pytest.raises(InputError, match="exactly one of scene"):
        load_rig(bad)
    bad.write_text(text.replace("focal_length_mm = 50.0", "focal_length_mm = 50.0\n"
                                "magnification = 2.0"))
    with pytest.raises(InputError, match="object pixel of 0.0075 mm .* scene has 0.015 mm"):
        acquire(bad, tmp_path / "s2")
    assert not (tmp_path / "s2" / "stack.json").exists()
