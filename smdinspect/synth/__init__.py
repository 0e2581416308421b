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
from ._scenes import cone_scene, half_textured_scene, slanted_plane_scene, staircase_scene

__all__ = [
    "DEFECTS",
    "Lighting",
    "Scene",
    "SensorConfig",
    "band_limited_texture",
    "board_scene",
    "cone_scene",
    "default_layer_mm",
    "frame_rng",
    "half_textured_scene",
    "parse_defects",
    "render_frame",
    "render_optical",
    "render_stack",
    "shade",
    "slanted_plane_scene",
    "staircase_scene",
]
