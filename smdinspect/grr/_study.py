"""A gauge R&R study of the joints of one board: repeated sweeps → per joint and type.

:func:`inspect_for_grr` inspects every sweep (or takes its existing report), one
``report.json`` per sweep; :func:`read_records` reads them back as :class:`GrrRecord`;
:func:`analyse_grr` groups the values per joint and per package/joint type and runs
:func:`~smdinspect.grr.gauge_rr` on each for max height, volume and area.

In gauge R&R terms a sweep is one *trial*; the *operator* is whoever or whatever changes
between groups of sweeps (operators, fixtures, days); the *parts* of a type study are
the joints of that package/joint type. A joint study has one part: its repeatability σ
and %GR&R against its own band; with several operators the reproducibility is the
one-way ANOVA's between-operator component. A type study is the AIAG crossed design
(joints × operators × sweeps) with the part variation between the type's joints and
the number of distinct categories.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import BoardNotLocatedError, InputError
from ..inspect._spc_report import METRICS as SPC_METRICS
from ._anova import GaugeRR, gauge_rr, rating

__all__ = [
    "GRR_METRICS",
    "GrrRecord",
    "GrrRow",
    "GrrStudy",
    "analyse_grr",
    "inspect_for_grr",
    "read_records",
]

log = logging.getLogger(__name__)

#: metric → (key in report.json "measured", unit, label): the metrics SPC charts. Only
#: the max height has a tolerance band (the joint's min/max height), so only it gets
#: %GR&R of tolerance.
GRR_METRICS = SPC_METRICS


@dataclass(frozen=True)
class GrrRecord:
    """One sweep's inspection, as the study needs it."""

    label: str
    operator: str
    report_dir: Path
    source: str
    board_name: str
    joints: tuple[dict[str, Any], ...]
    packages: dict[str, str]


@dataclass(frozen=True)
class GrrRow:
    """The gauge study of one joint or one package/joint type for one metric."""

    scope: str  # "joint" or "type"
    key: str
    metric: str
    component: str
    package: str
    termination: str
    lsl: float
    usl: float
    gauge: GaugeRR
    #: Readings left out because the joint was judged unreliable in that sweep.
    n_unreliable: int = 0
    #: Joints of the type (a type study), of which ``gauge.n_parts`` were complete.
    n_joints: int = 1

    @property
    def unit(self) -> str:
        return GRR_METRICS[self.metric][1]

    @property
    def tolerance(self) -> float:
        return self.gauge.tolerance

    @property
    def pct_grr(self) -> float:
        """%GR&R of the tolerance when there is one, else of the study variation."""
        t = self.gauge.pct_tolerance
        return t if math.isfinite(t) else self.gauge.pct_study

    @property
    def rating(self) -> str:
        return rating(self.pct_grr)

    @property
    def cv_pct(self) -> float:
        """``σ_GRR / |mean| × 100``: the gauge's relative spread (for metrics without a band)."""
        m = self.gauge.mean
        return 100.0 * self.gauge.sigma_grr / abs(m) if math.isfinite(m) and m != 0 else math.nan


@dataclass(frozen=True)
class GrrStudy:
    """Everything :func:`~smdinspect.grr.write_grr` writes."""

    records: tuple[GrrRecord, ...]
    rows: tuple[GrrRow, ...]
    board_name: str
    operators: tuple[str, ...]
    values: dict[str, dict[str, np.ndarray]] = field(repr=False)
    joint_meta: dict[str, dict[str, Any]] = field(repr=False)
    k_sigma: float = 6.0
    include_unreliable: bool = False

    def get(self, scope: str, key: str, metric: str = "max_height_mm") -> GrrRow:
        for r in self.rows:
            if (r.scope, r.key, r.metric) == (scope, key, metric):
                return r
        raise KeyError((scope, key, metric))

    def failing(self, max_pct: float) -> list[GrrRow]:
        """Max-height rows (joints and types) whose %GR&R of tolerance is above ``max_pct``."""
        return [r for r in self.rows if r.metric == "max_height_mm"
                and math.isfinite(r.gauge.pct_tolerance) and r.gauge.pct_tolerance > max_pct]


# ---------------------------------------------------------------------------------
# Inputs: sweeps → reports.
# ---------------------------------------------------------------------------------


def _labels_for(paths: Sequence[Path]) -> list[str]:
    names = [p.resolve().name or str(p) for p in paths]
    if len(set(names)) == len(names):
        return names
    return [f"{i + 1:02d}_{n}" for i, n in enumerate(names)]


def inspect_for_grr(stacks: Sequence[str | os.PathLike], board, out_dir: str | os.PathLike, *,
                    labels: Sequence[str] | None = None, focus_config=None, inspect_config=None,
                    pixel_size_mm: float | None = None, html: bool = False,
                    reinspect: bool = False, calibration: str | os.PathLike | None = None,
                    progress: Callable[[int, int], None] | None = None,
                    frame_progress: Callable[[str], Callable[[int, int], None]] | None = None
                    ) -> list[tuple[str, Path]]:
    """Inspect every sweep into ``out_dir/inspections/LABEL/``; existing reports are reused.

    Parameters
    ----------
    stacks : sequence of path
        Inspection report folders (holding ``report.json``, e.g. ``smdinspect inspect``
        or ``batch`` outputs; taken as they are), stack directories (``stack.json``,
        reconstructed with ``focus_config``) or reconstruction directories.
    board : Board
    out_dir : path
    labels : sequence of str, optional
        One per stack (default: the folder names, numbered when two are alike).
    pixel_size_mm : float, optional
        Overrides the stacks' pixel size.
    html : bool
        Write each sweep's ``report.html`` too.
    reinspect : bool
        Inspect a reconstruction again even when it holds a ``report.json``.
    calibration : path, optional
        Rig calibration file applied to the sweeps this inspects (report folders are
        taken as they are).
    progress : callable(done, total), optional
        Called after each sweep.
    frame_progress : callable(label) -> progress, optional
        A per-frame progress callback for each sweep's reconstruction.

    Returns
    -------
    list of (label, report folder)

    Raises
    ------
    BoardNotLocatedError
        A sweep in which the board was not found (names the sweep).
    InputError
        A path that is neither a stack, a reconstruction nor a report folder.
    """
    from .. import _atomic
    from ..inspect._board import check_board_in_field
    from ..pipeline import (inspect_stack, inspection_outputs, is_reconstruction,
                            load_reconstruction)
    from ..stack import MANIFEST, open_stack

    paths = [Path(s) for s in stacks]
    labels = list(labels) if labels is not None else _labels_for(paths)
    if len(labels) != len(paths):
        raise InputError(f"labels must give one label per stack; got {len(labels)} for "
                         f"{len(paths)} stacks")
    out = Path(out_dir) / "inspections"
    found: list[tuple[str, Path]] = []
    for i, (label, path) in enumerate(zip(labels, paths)):
        if not path.is_dir():
            raise InputError(f"no such folder: {path}")
        if (path / "report.json").is_file() and not (reinspect and is_reconstruction(path)):
            found.append((label, path))
            if progress is not None:
                progress(i + 1, len(paths))
            continue
        if (path / MANIFEST).is_file():
            stack = open_stack([path], pixel_size_mm=pixel_size_mm)
            shape = stack.read_frame(0).shape[:2]
        elif is_reconstruction(path):
            stack = load_reconstruction(path, pixel_size_mm=pixel_size_mm)
            shape = stack.shape
        else:
            raise InputError(f"{path} is neither a stack ({MANIFEST}), a reconstruction nor "
                             "an inspection report folder (report.json)")
        if stack.pixel_size_mm is None:
            raise InputError(f"{path}: inspection needs the pixel size in mm; give "
                             "--pixel-size-mm")
        check_board_in_field(board, shape, stack.pixel_size_mm)
        log.info("inspecting %s (%d/%d)", path, i + 1, len(paths))
        not_located = None
        with _atomic.replace_dir(out / label, replaces=inspection_outputs()) as tmp:
            try:
                inspect_stack(stack, board, tmp, focus_config=focus_config,
                              inspect_config=inspect_config, html=html, source=str(path),
                              calibration=calibration,
                              progress=frame_progress(label) if frame_progress else None)
            except BoardNotLocatedError as exc:
                not_located = exc
        if not_located is not None:
            raise BoardNotLocatedError(f"{path}: {not_located} (a different board, or not "
                                       "in the field of view?)") from not_located
        found.append((label, out / label))
        if progress is not None:
            progress(i + 1, len(paths))
    return found


def read_records(found: Sequence[tuple[str, str | os.PathLike]], *,
                 operators: Sequence[str] | None = None) -> list[GrrRecord]:
    """Read the sweeps' ``report.json`` files (see :func:`inspect_for_grr`).

    Parameters
    ----------
    found : sequence of (label, report folder)
    operators : sequence of str, optional
        The operator (fixturing, day...) of each sweep; default one operator, ``"A"``.

    Raises
    ------
    InputError
        An unreadable report, a board that was not located, or ``operators`` of the
        wrong length.
    """
    from ..inspect._spc_report import _read_board

    if operators is not None and len(operators) != len(found):
        raise InputError(f"operators must give one operator per stack; got {len(operators)} "
                         f"for {len(found)} stacks")
    out = []
    for i, (label, folder) in enumerate(found):
        b = _read_board(str(label), Path(folder))
        if b.status != "inspected" or not b.joints:
            raise InputError(f"{label}: the board was not located in this sweep "
                             f"({Path(folder) / 'report.json'} status {b.status!r})")
        out.append(GrrRecord(label=str(label), operator=str(operators[i]) if operators else "A",
                             report_dir=Path(folder), source=str(folder),
                             board_name=b.board_name, joints=b.joints, packages=b.packages))
    return out


# ---------------------------------------------------------------------------------
# Analysis.
# ---------------------------------------------------------------------------------


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f if math.isfinite(f) else math.nan


def analyse_grr(records: Sequence[GrrRecord], *, board_name: str | None = None,
                joint_ids: Sequence[str] | None = None, include_unreliable: bool = False,
                k_sigma: float = 6.0, interaction_alpha: float = 0.05) -> GrrStudy:
    """Gauge R&R per joint and per package/joint type for max height, volume and area.

    Parameters
    ----------
    records : sequence of GrrRecord
        At least 2 sweeps of one board. With several operators, each operator must
        have the same number of sweeps (the AIAG crossed design).
    board_name : str, optional
        The board every sweep must have been inspected against.
    joint_ids : sequence of str, optional
        That board's joints, which every sweep must have.
    include_unreliable : bool
        Keep the readings of joints judged unreliable in a sweep (default: left out,
        as no verdict was based on them; they are counted in ``n_unreliable``).
    k_sigma : float
        Gauge spread in σ for %GR&R (6, AIAG 4th edition).
    interaction_alpha : float
        See :func:`~smdinspect.grr.gauge_rr`.

    Returns
    -------
    GrrStudy

    Raises
    ------
    InputError
        Fewer than 2 sweeps, sweeps of different boards (name or joints), operators with
        different numbers of sweeps.
    """
    recs = list(records)
    if len(recs) < 2:
        raise InputError(f"a gauge R&R study needs at least 2 sweeps of the board; got "
                         f"{len(recs)}")
    names = {r.board_name for r in recs}
    if board_name is not None:
        other = [r.label for r in recs if r.board_name != board_name]
        if other:
            bad = next(r for r in recs if r.board_name != board_name)
            raise InputError(f"sweep {bad.label} was inspected against board "
                             f"{bad.board_name!r}, not {board_name!r} ({len(other)} of "
                             f"{len(recs)} sweeps)")
    elif len(names) > 1:
        raise InputError(f"the sweeps were inspected against different boards: "
                         f"{', '.join(sorted(repr(n) for n in names))}")
    ids0 = [str(j.get("id")) for j in recs[0].joints]
    for r in recs[1:]:
        ids = [str(j.get("id")) for j in r.joints]
        if set(ids) != set(ids0):
            diff = sorted(set(ids) ^ set(ids0))
            raise InputError(f"sweeps {recs[0].label} and {r.label} have different joints "
                             f"(e.g. {', '.join(diff[:4])}): not the same board")
    if joint_ids is not None and set(map(str, joint_ids)) != set(ids0):
        diff = sorted(set(map(str, joint_ids)) ^ set(ids0))
        raise InputError(f"sweep {recs[0].label} has other joints than the board "
                         f"{board_name or ''} (e.g. {', '.join(diff[:4])}): another board or "
                         "another version of it")
    ops = tuple(r.operator for r in recs)
    counts = {o: ops.count(o) for o in dict.fromkeys(ops)}
    if len(counts) > 1 and len(set(counts.values())) > 1:
        raise InputError("the ANOVA method needs the same number of sweeps per operator; got "
                         + ", ".join(f"{o}: {c}" for o, c in counts.items()))

    n = len(recs)
    meta: dict[str, dict[str, Any]] = {}
    for j in recs[0].joints:
        jid = str(j.get("id"))
        comp = str(j.get("component", ""))
        exp = j.get("expected") or {}
        meta[jid] = {"component": comp, "package": recs[0].packages.get(comp, ""),
                     "termination": str(j.get("termination", "")),
                     "lsl": _num(exp.get("min_height_mm")), "usl": _num(exp.get("max_height_mm"))}
    values = {m: {jid: np.full(n, np.nan) for jid in meta} for m in GRR_METRICS}
    unreliable = {jid: np.zeros(n, bool) for jid in meta}
    for i, r in enumerate(recs):
        for j in r.joints:
            jid = str(j.get("id"))
            unreliable[jid][i] = j.get("verdict") == "unreliable"
            if unreliable[jid][i] and not include_unreliable:
                continue
            measured = j.get("measured") or {}
            for m, (key, _, _) in GRR_METRICS.items():
                values[m][jid][i] = _num(measured.get(key))

    def tol(lsl: float, usl: float, metric: str) -> float | None:
        if metric != "max_height_mm" or not (math.isfinite(lsl) and math.isfinite(usl)) \
                or usl <= lsl:
            return None
        return usl - lsl

    opts = dict(k_sigma=k_sigma, interaction_alpha=interaction_alpha)
    rows: list[GrrRow] = []
    for jid, info in meta.items():
        n_unrel = 0 if include_unreliable else int(unreliable[jid].sum())
        for m in GRR_METRICS:
            g = gauge_rr(values[m][jid], operators=ops,
                         tolerance=tol(info["lsl"], info["usl"], m), **opts)
            rows.append(GrrRow(scope="joint", key=jid, metric=m, component=info["component"],
                               package=info["package"], termination=info["termination"],
                               lsl=info["lsl"], usl=info["usl"], gauge=g, n_unreliable=n_unrel))
    types: dict[str, list[str]] = {}
    for jid, info in meta.items():
        types.setdefault(f"{info['package'] or '?'}/{info['termination'] or '?'}", []).append(jid)
    for tkey, jids in types.items():
        info = meta[jids[0]]
        # the narrowest band of the type's joints: the type's %GR&R is its worst joint's
        widths = [(meta[j]["usl"] - meta[j]["lsl"], meta[j]["lsl"], meta[j]["usl"]) for j in jids
                  if math.isfinite(meta[j]["usl"] - meta[j]["lsl"])]
        _, lsl, usl = min(widths) if widths else (math.nan, math.nan, math.nan)
        n_unrel = 0 if include_unreliable else int(sum(unreliable[j].sum() for j in jids))
        for m in GRR_METRICS:
            x = np.stack([values[m][j] for j in jids])  # (joints, sweeps)
            if len(counts) > 1:  # crossed design: only joints read in every sweep
                x = x[np.all(np.isfinite(x), axis=1)]
            parts = np.repeat(np.arange(len(x)), n)
            g = gauge_rr(x.ravel(), parts=parts, operators=np.tile(ops, len(x)),
                         tolerance=tol(lsl, usl, m), **opts)
            rows.append(GrrRow(scope="type", key=tkey, metric=m, component="",
                               package=info["package"], termination=info["termination"],
                               lsl=lsl, usl=usl, gauge=g, n_unreliable=n_unrel,
                               n_joints=len(jids)))
    return GrrStudy(records=tuple(recs), rows=tuple(rows),
                    board_name=board_name or next(iter(names)), operators=tuple(counts),
                    values=values, joint_meta=meta, k_sigma=float(k_sigma),
                    include_unreliable=include_unreliable)
