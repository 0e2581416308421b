"""Shape from focus: focus measures, peak fit, confidence, alignment, surfaces.

``import smdinspect.sff`` does not import Open3D or trimesh; the cloud and mesh writers
load them when called.
"""

from ._align import Alignment, estimate_alignment
from ._config import FitMethod, FocusConfig
from ._confidence import (borrowed_mask, confidence_map, depth_edge_mask, precision_steps,
                          unsupported_mask)
from ._depth import PeakFit, PeakTracker, centroid_correction, fit_peaks, local_plane
from ._export import (
    height_field_mesh,
    render_height_png,
    render_view3d_png,
    surface_point_cloud,
    write_point_cloud,
    write_reconstruction,
)
from ._focus import (OPERATORS, FocusOperator, band_powers, focus_measure, focus_measure_moments,
                     magnification_exponent, noise_sigma, prefilter_sigma)
from ._reasonpng import render_reason_map
from ._reconstruct import reconstruct, to_gray
from ._surface import (UNRELIABLE_REASONS, Surface, clipped_white, pixel_to_xy_mm,
                       xy_mm_to_pixel)

__all__ = [
    "OPERATORS",
    "Alignment",
    "FitMethod",
    "FocusConfig",
    "FocusOperator",
    "PeakFit",
    "PeakTracker",
    "Surface",
    "UNRELIABLE_REASONS",
    "band_powers",
    "borrowed_mask",
    "centroid_correction",
    "clipped_white",
    "confidence_map",
    "depth_edge_mask",
    "estimate_alignment",
    "fit_peaks",
    "focus_measure",
    "focus_measure_moments",
    "height_field_mesh",
    "local_plane",
    "magnification_exponent",
    "noise_sigma",
    "pixel_to_xy_mm",
    "precision_steps",
    "prefilter_sigma",
    "reconstruct",
    "render_height_png",
    "render_reason_map",
    "render_view3d_png",
    "surface_point_cloud",
    "to_gray",
    "unsupported_mask",
    "write_point_cloud",
    "write_reconstruction",
    "xy_mm_to_pixel",
]
