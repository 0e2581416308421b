"""Rig-file text for the tests: the simulated rig made fast, and variants."""

from __future__ import annotations

SIM_RIG = """
[stage]
protocol = "grbl"
boot_wait_s = 0.0
timeout_s = 1.0
z_min_mm = -10.0
z_max_mm = 0.0
feed_mm_min = 12000.0
poll_interval_s = 0.002

[stage.fake]
steps_per_mm = 400.0
max_rate_mm_s = 200.0
start_z_mm = 0.0
{faults}

[mapping]
focus_offset_mm = 5.0
direction = 1

[camera]
kind = "simulated"
scene = "cone"
seed = 7
sensor = "{sensor}"

[camera.scene_options]
size_px = {size}
pixel_size_mm = 0.015
height_mm = 0.6

[optics]
focal_length_mm = 50.0
aperture_mm = 50.0
pixel_pitch_mm = 0.015

[sweep]
z_start_mm = -0.15
z_stop_mm = {z_stop}
step_mm = 0.05
settle_s = {settle}
backlash_mm = 0.1
frames_per_step = {fps}
"""


def sim_rig(path, *, faults="", sensor="low", size=64, z_stop=0.75, settle=0.0, fps=1):
    """Write the fast simulated rig to ``path`` and return it."""
    path.write_text(SIM_RIG.format(faults=faults, sensor=sensor, size=size, z_stop=z_stop,
                                   settle=settle, fps=fps))
    return path
