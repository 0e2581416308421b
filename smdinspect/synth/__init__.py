"""Synthetic scenes rendered through the thin-lens optics into focal stacks.

Scenes with known heights (:func:`cone_scene`, :func:`staircase_scene`,
:func:`slanted_plane_scene`, :func:`half_textured_scene`) and boards built from a
reference board file with injected defects (:func:`board_scene`, :data:`DEFECTS`,
:func:`parse_defects`) become frames with
:func:`render_frame` / :func:`render_stack`: layered depth-dependent blur with occlusion
(:func:`render_optical`), then a noisy sensor (:class:`SensorConfig`). See
:mod:`smdinspect.synth._render` for the model.
"""

from ._board_scene import DEFECTS, board_scene, parse_defects
from ._render import (
    SensorConfig,
    default_layer_mm,
    frame_rng,
    render_frame,
    render_optical,
    render_stack,
)
from ._scene import Lighting, Scene, band_limited_texture, shade
from ._suite import (
    Case,
    GatherNoise,
    PSF_KINDS,
    SCENE_KINDS,
    TEST_SEEDS,
    TEXTURE_KINDS,
    TUNING_SEEDS,
    add_highlight,
    bore,
    case_stack,
    cone,
    half_textured,
    random_case,
    render_gather,
    slanted_plane,
    sphere_cap,
    steps,
    texture,
)
from ._scenes import (cone_scene, half_textured_scene, slanted_plane_scene, staircase_scene,
                      step_target_scene)

__all__ = [
    "Case",
    "DEFECTS",
    "GatherNoise",
    "Lighting",
    "PSF_KINDS",
    "SCENE_KINDS",
    "Scene",
    "SensorConfig",
    "TEST_SEEDS",
    "TEXTURE_KINDS",
    "TUNING_SEEDS",
    "add_highlight",
    "band_limited_texture",
    "board_scene",
    "bore",
    "case_stack",
    "cone",
    "cone_scene",
    "default_layer_mm",
    "frame_rng",
    "half_textured",
    "half_textured_scene",
    "parse_defects",
    "random_case",
    "render_frame",
    "render_gather",
    "render_optical",
    "render_stack",
    "shade",
    "slanted_plane",
    "slanted_plane_scene",
    "sphere_cap",
    "staircase_scene",
    "step_target_scene",
    "steps",
    "texture",
]
