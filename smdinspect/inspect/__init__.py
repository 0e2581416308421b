"""Inspection: the reference board, registration, per-joint measurement, verdicts, reports.

Pipeline (pure functions on arrays and small dataclasses)::

    Surface ──fit_board_plane──▶ heights above the board
            ──register_board───▶ RegistrationResult (board → world placement)
            ──measure / judge──▶ JointResult, ComponentResult ──▶ InspectionResult
            ──write_reports────▶ report.json, joints.csv, junit.xml, report.html
            ──write_units_inspected──▶ cfx_units_inspected.json (IPC-CFX)

:func:`inspect_surface` runs all of it; :func:`smdinspect.pipeline.inspect_stack`
adds the reconstruction and the files.
"""

from typing import TYPE_CHECKING

# The names below load with their submodule on first use (PEP 562, as scikit-image's
# lazy loader): the CLI builds every subcommand's parser, and ``inspect``'s takes a
# default from InspectConfig, so a ``reconstruct`` run used to import the whole
# inspection package (about 80 ms) for one number.
_ORIGIN = {name: module for module, names in {
    "_board": ("Board", "Component", "Fiducial", "Joint", "load_board"),
    "_cfx": ("CFX_FILE", "collect_units_inspected", "units_inspected", "write_units_inspected"),
    "_config": ("FilletModel", "InspectConfig", "Verdict"),
    "_inspect": ("inspect_surface",),
    "_plane": ("BoardPlane", "fit_board_plane"),
    "_reference": ("body_top_mm", "reference_mesh", "reference_points", "reference_prisms",
                   "render_reference"),
    "_register": ("RegistrationResult", "masked_ncc", "register_board"),
    "_report": ("REPORT_FILES", "report_dict", "write_reports"),
    "_result": ("ComponentResult", "InspectionResult", "JointResult"),
    "_spc": ("RULES", "capability", "individuals_chart", "run_rules", "xbar_r_chart"),
    "_spc_report": ("SpcAnalysis", "analyse_reports", "write_spc"),
}.items() for name in names}

if TYPE_CHECKING:  # the same names, eagerly, for type checkers and IDEs
    from ._board import Board, Component, Fiducial, Joint, load_board
    from ._cfx import CFX_FILE, collect_units_inspected, units_inspected, write_units_inspected
    from ._config import FilletModel, InspectConfig, Verdict
    from ._inspect import inspect_surface
    from ._plane import BoardPlane, fit_board_plane
    from ._reference import (
        body_top_mm,
        reference_mesh,
        reference_points,
        reference_prisms,
        render_reference,
    )
    from ._register import RegistrationResult, masked_ncc, register_board
    from ._report import REPORT_FILES, report_dict, write_reports
    from ._result import ComponentResult, InspectionResult, JointResult
    from ._spc import RULES, capability, individuals_chart, run_rules, xbar_r_chart
    from ._spc_report import SpcAnalysis, analyse_reports, write_spc

__all__ = [
    "CFX_FILE",
    "REPORT_FILES",
    "RULES",
    "Board",
    "BoardPlane",
    "Component",
    "ComponentResult",
    "Fiducial",
    "FilletModel",
    "InspectConfig",
    "InspectionResult",
    "Joint",
    "JointResult",
    "RegistrationResult",
    "SpcAnalysis",
    "Verdict",
    "analyse_reports",
    "body_top_mm",
    "capability",
    "collect_units_inspected",
    "fit_board_plane",
    "individuals_chart",
    "inspect_surface",
    "load_board",
    "masked_ncc",
    "reference_mesh",
    "reference_points",
    "reference_prisms",
    "register_board",
    "render_reference",
    "report_dict",
    "run_rules",
    "units_inspected",
    "write_reports",
    "write_spc",
    "write_units_inspected",
    "xbar_r_chart",
]


def __getattr__(name: str):
    module = _ORIGIN.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
