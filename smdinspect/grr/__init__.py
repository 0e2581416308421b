"""Gauge repeatability and reproducibility (gauge R&R) of the joint measurements.

N sweeps of the same board (re-placed between sweeps, optionally by several operators
or fixturings) → per joint and per package/joint type the repeatability σ of max
height, volume and area, the reproducibility by the AIAG ANOVA method, %GR&R against
the joint's tolerance band and the number of distinct categories::

    sweeps ──inspect_for_grr──▶ report.json ──read_records──▶ GrrRecord
           ──analyse_grr──────▶ GrrStudy ──write_grr──▶ grr.csv, grr.json, grr.png

:func:`gauge_rr` is the statistics alone (values, parts, operators → :class:`GaugeRR`).
"""

from ._anova import ACCEPTABLE_PCT, MARGINAL_PCT, AnovaTerm, GaugeRR, gauge_rr, rating
from ._report import GRR_COLUMNS, GRR_FILES, grr_dict, write_grr
from ._study import (
    GRR_METRICS,
    GrrRecord,
    GrrRow,
    GrrStudy,
    analyse_grr,
    inspect_for_grr,
    read_records,
)

__all__ = [
    "ACCEPTABLE_PCT",
    "GRR_COLUMNS",
    "GRR_FILES",
    "GRR_METRICS",
    "MARGINAL_PCT",
    "AnovaTerm",
    "GaugeRR",
    "GrrRecord",
    "GrrRow",
    "GrrStudy",
    "analyse_grr",
    "gauge_rr",
    "grr_dict",
    "inspect_for_grr",
    "rating",
    "read_records",
    "write_grr",
]
