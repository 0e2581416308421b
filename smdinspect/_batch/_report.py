"""Batch-level outputs: the summary (CSV and JSON) and one merged JUnit file."""

from __future__ import annotations

import csv
import io
import logging
import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any, Sequence

from .. import _atomic
from ._job import BoardResult, BoardStatus

__all__ = ["SUMMARY_COLUMNS", "merge_junit", "write_summary_csv", "write_summary_json"]

log = logging.getLogger(__name__)

SUMMARY_COLUMNS = ("stack", "status", "exit_code", "joints", "defects", "unreliable",
                   "reason", "seconds", "skipped", "report_dir")


def write_summary_csv(path: str | os.PathLike, results: Sequence[BoardResult]) -> Path:
    """One row per board (columns :data:`SUMMARY_COLUMNS`), written atomically.

    Booleans are ``true``/``false``; unknown counts (errored boards) are empty.
    """
    from ..inspect._spc_report import safe_cell

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in results:
        row = r.to_row()
        row["skipped"] = "true" if row["skipped"] else "false"
        # board names and error texts come from files: no spreadsheet formulas
        w.writerow({k: ("" if v is None else safe_cell(v)) for k, v in row.items()})
    return _atomic.write_text(path, buf.getvalue())


def write_summary_json(path: str | os.PathLike, results: Sequence[BoardResult],
                       header: dict[str, Any]) -> Path:
    """``header`` (batch facts) plus ``"boards"``: the rows of the CSV, atomically."""
    return _atomic.write_json(path, {**header, "boards": [r.to_row() for r in results]})


def _board_suite(result: BoardResult) -> ET.Element:
    """The board's test cases as one ``<testsuite>`` named after the stack."""
    suite = ET.Element("testsuite", name=result.stack)
    props = ET.SubElement(suite, "properties")
    for k, v in (("status", result.status.value), ("exit_code", str(result.exit_code)),
                 ("report_dir", result.out_dir), ("skipped_rerun", str(result.skipped).lower())):
        ET.SubElement(props, "property", name=k, value=v)
    cases: list[ET.Element] = []
    if result.status is BoardStatus.ERROR:
        case = ET.Element("testcase", classname=result.stack, name="inspection", time="0")
        ET.SubElement(case, "error", message=result.reason,
                      type=f"exit code {result.exit_code}").text = result.reason
        cases.append(case)
    else:
        path = Path(result.out_dir) / "junit.xml"
        try:
            root = ET.parse(path).getroot()
            cases = list(root.iter("testcase"))
            for prop in root.iter("property"):  # the board's own facts (registration...)
                props.append(prop)
        except (OSError, ET.ParseError) as exc:
            case = ET.Element("testcase", classname=result.stack, name="junit.xml")
            ET.SubElement(case, "error", message=f"cannot read {path}: {exc}")
            cases.append(case)
        for case in cases:
            cls = case.get("classname")
            case.set("classname", f"{result.stack}.{cls}" if cls else result.stack)
    counts = {"failures": 0, "errors": 0, "skipped": 0}
    for case in cases:
        suite.append(case)
        counts["failures"] += case.find("failure") is not None
        counts["errors"] += case.find("error") is not None
        counts["skipped"] += case.find("skipped") is not None
    suite.set("tests", str(len(cases)))
    for k, v in counts.items():
        suite.set(k, str(v))
    suite.set("time", f"{result.seconds:.3f}")
    return suite


def merge_junit(path: str | os.PathLike, results: Sequence[BoardResult], *,
                name: str = "smdinspect batch") -> Path:
    """One JUnit XML for the whole batch, written atomically.

    ``<testsuites>`` holds one ``<testsuite name="STACK">`` per board with the test
    cases of that board's ``junit.xml`` (``classname`` prefixed with the stack name, so
    equal joint ids on different boards stay apart). A board that errored is one test
    case ``inspection`` with an ``<error>`` giving the reason.
    """
    root = ET.Element("testsuites", name=name)
    totals = {"tests": 0, "failures": 0, "errors": 0, "skipped": 0}
    seconds = 0.0
    for r in results:
        suite = _board_suite(r)
        root.append(suite)
        for k in totals:
            totals[k] += int(suite.get(k, "0"))
        seconds += r.seconds
    for k, v in totals.items():
        root.set(k, str(v))
    root.set("time", f"{seconds:.3f}")
    ET.indent(root)
    text = ET.tostring(root, encoding="unicode", xml_declaration=False)
    return _atomic.write_text(path, '<?xml version="1.0" encoding="UTF-8"?>\n' + text + "\n")
