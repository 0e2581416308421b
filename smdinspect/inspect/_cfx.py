"""IPC-CFX: a board's inspection as a ``CFX.Production.TestAndInspection.UnitsInspected``.

IPC-2591 (Connected Factory Exchange) is the SMT line's message standard: JSON
messages in a :data:`CFX envelope <ENVELOPE_FIELDS>`, sent over AMQP 1.0. This module
builds the message of one inspected board from its ``report.json`` document (see
:mod:`._report`), so the message and the report always say the same thing, and writes
it as ``cfx_units_inspected.json`` beside ``report.json``. Sending it to a broker is
left to the line's integration (the file is the message, byte for byte).

What the message holds (CFX 1.7 names; the parts of the standard used, in the
structure its SDK serialises):

- the envelope: ``MessageName``, ``Version``, ``TimeStamp`` (when the board was
  inspected: the report's ``created``, with its time zone), ``UniqueID``, ``Source``
  (the CFX handle of this station, default ``smdinspect.<host name>``), ``Target`` and
  ``RequestID`` (``null``: not a request), ``MessageBody``;
- the body: ``InspectionMethod`` ``"AOI"``, ``SamplingInformation`` (every board),
  ``RecipeName`` (the reference board's name), one ``InspectedUnit``: its
  ``UnitIdentifier`` (default: the name of the stack folder), ``OverallResult``
  (``Passed`` / ``Failed`` as the exit code; ``Error`` for a board not located);
- one ``Inspection`` per joint (``InspectionName`` = joint id): ``Result`` ``Passed``,
  ``Failed`` (a defect) or ``Error`` (``unreliable``: the joint could not be judged;
  ``Error`` says why), ``Comments`` = the verdict's reason, and the joint's
  ``NumericMeasurement``\\ s: max solder height (with its acceptance band and nominal),
  solder volume and area, in ``mm``, ``mm3``, ``mm2`` (UCUM spellings). A defective
  joint's measurements are its defect's ``RelatedMeasurements`` (the standard keeps
  ``Measurements`` for those not related to a defect);
- for a defective joint one ``Defect``: ``DefectCode`` = the verdict
  (``"bridge"``...), ``DefectCategory`` from the standard's suggested values
  (:data:`DEFECT_CATEGORIES`), ``Description`` = the reason, ``ComponentOfInterest``
  (``"R3.1"``: component R3, pin 1) and
  ``RegionOfInterest`` (the pad centre, board frame, mm). Component-level verdicts
  (component missing or shifted, tombstone) are on every joint of the part, as in
  ``report.json``: the message's defects are ``report.json``'s ``summary.defects``.

A board that was not located gets a message too: ``OverallResult`` ``Error`` and a
single ``Inspection`` ``"locate board"`` with the reason in ``Error``.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
import socket
import uuid
from pathlib import Path
from typing import Any, Iterable

from .. import _atomic
from .._json import read_json
from ..errors import InputError

__all__ = [
    "CFX_FILE",
    "CFX_VERSION",
    "DEFECT_CATEGORIES",
    "MESSAGE_NAME",
    "collect_units_inspected",
    "units_inspected",
    "write_units_inspected",
]

log = logging.getLogger(__name__)

#: The message's file, beside ``report.json`` (and, in a batch folder, every board's).
CFX_FILE = "cfx_units_inspected.json"
MESSAGE_NAME = "CFX.Production.TestAndInspection.UnitsInspected"
#: Version of the standard whose structures the message uses.
CFX_VERSION = "1.7"
#: The envelope's fields, in the standard's order.
ENVELOPE_FIELDS = ("MessageName", "Version", "TimeStamp", "UniqueID", "Source", "Target",
                   "RequestID", "MessageBody")

#: smdinspect verdict -> CFX ``DefectCategory`` (the standard's suggested values).
#: ``missing`` is no solder at all: CFX has no "missing solder", its category is
#: InsufficientSolder (the ``DefectCode`` keeps "missing").
DEFECT_CATEGORIES = {
    "missing": "InsufficientSolder",
    "insufficient": "InsufficientSolder",
    "excess": "ExcessiveSolder",
    "bridge": "Short",
    "lifted_lead": "LiftedLead",
    "tombstone": "Tombstone",
    "component_missing": "ComponentMissing",
    "component_shifted": "ComponentShifted",
}
#: Verdicts that are not defects.
_NOT_DEFECTS = ("ok", "unreliable")
_NUMERIC = "CFX.Structures.NumericMeasurement, CFX"


def _default_source() -> str:
    host = socket.gethostname().strip() or "localhost"
    return f"smdinspect.{host}"


def _default_unit(report: dict[str, Any]) -> str:
    measured = report.get("measurement") or {}
    src = measured.get("source")
    if isinstance(src, str) and src.strip() and not src.startswith("<"):
        name = Path(src.rstrip("/\\")).name
        if name:
            return name
    return str((report.get("board") or {}).get("name") or "unit")


def _uid() -> str:
    return str(uuid.uuid4())


def _text(value: Any) -> str:
    return "" if value is None else str(value)


def units_inspected(report: dict[str, Any], *, source: str | None = None,
                    unit_id: str | None = None) -> dict[str, Any]:
    """The CFX envelope of a ``UnitsInspected`` message for one board.

    Parameters
    ----------
    report : dict
        A ``report.json`` document (``status`` ``"inspected"`` or ``"not_located"``).
    source : str, optional
        The CFX handle of this station (``Source``); default ``smdinspect.<host name>``.
    unit_id : str, optional
        The board's ``UnitIdentifier`` (serial number, barcode); default the name of the
        measured stack's folder (``measurement.source``), else the board name.

    Returns
    -------
    dict
        The envelope (JSON types only), ``MessageBody`` holding the message.

    Raises
    ------
    InputError
        ``report`` is not a report.json document.
    """
    if not isinstance(report, dict) or report.get("schema") != "smdinspect-report":
        got = report.get("schema") if isinstance(report, dict) else type(report).__name__
        raise InputError(f"report must be a report.json document (schema "
                         f"'smdinspect-report'); got {got!r}")
    status = report.get("status")
    if status not in ("inspected", "not_located"):
        raise InputError(f"report status must be 'inspected' or 'not_located'; got {status!r}")
    for name, value in (("source", source), ("unit_id", unit_id)):
        if value is not None and (not isinstance(value, str) or not value.strip()):
            raise InputError(f"{name} must be a non-empty string; got {value!r}")

    timestamp = report.get("created")
    if not isinstance(timestamp, str) or not timestamp:
        timestamp = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()
    if status == "not_located":
        inspections = [{
            "UniqueIdentifier": _uid(),
            "InspectionName": "locate board",
            "Result": "Error",
            "Error": _text(report.get("reason")) or "board not located",
            "DefectsFound": [],
            "Measurements": [],
        }]
        overall = "Error"
    else:
        inspections = [_joint_inspection(j, timestamp) for j in report.get("joints") or []]
        overall = "Passed" if report.get("passed") else "Failed"
    body = {
        "$type": f"{MESSAGE_NAME}, CFX",
        "TransactionId": _uid(),
        "InspectionMethod": "AOI",
        "SamplingInformation": {"SamplingMethod": "NoSampling", "LotSize": None,
                                "SampleSize": None},
        "RecipeName": _text((report.get("board") or {}).get("name")),
        "InspectedUnits": [{
            "UnitIdentifier": unit_id if unit_id is not None else _default_unit(report),
            "UnitPositionNumber": 1,
            "OverallResult": overall,
            "Inspections": inspections,
        }],
    }
    return {
        "MessageName": MESSAGE_NAME,
        "Version": CFX_VERSION,
        "TimeStamp": timestamp,
        "UniqueID": _uid(),
        "Source": source if source is not None else _default_source(),
        "Target": None,
        "RequestID": None,
        "MessageBody": body,
    }


def _joint_inspection(j: dict[str, Any], timestamp: str | None) -> dict[str, Any]:
    jid = _text(j.get("id"))
    verdict = _text(j.get("verdict"))
    reason = _text(j.get("reason"))
    measurements = _measurements(j, timestamp)
    out: dict[str, Any] = {"UniqueIdentifier": _uid(), "InspectionName": jid,
                           "Comments": reason}
    if verdict == "ok":
        out.update(Result="Passed", DefectsFound=[], Measurements=measurements)
    elif verdict == "unreliable":
        out.update(Result="Error", Error=reason or "not enough reliable pixels to judge",
                   DefectsFound=[], Measurements=measurements)
    else:
        category = DEFECT_CATEGORIES.get(verdict)
        if category is None:  # a verdict this module does not know yet: still a defect
            log.warning("joint %s: verdict %r has no CFX defect category; using "
                        "SolderDefect", jid, verdict)
            category = "SolderDefect"
        defect: dict[str, Any] = {
            "UniqueIdentifier": _uid(),
            "DefectCode": verdict,
            "DefectCategory": category,
            "Description": reason,
            # No PartNumber: board files name the package, not the part number.
            "ComponentOfInterest": {"ReferenceDesignator": jid},
        }
        pos = j.get("position_mm") or {}
        if _finite(pos.get("x")) and _finite(pos.get("y")):
            defect["RegionOfInterest"] = {"StartPointX": pos["x"], "StartPointY": pos["y"],
                                          "RegionSegments": []}
        defect["RelatedMeasurements"] = measurements
        out.update(Result="Failed", DefectsFound=[defect], Measurements=[])
    return out


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v \
        and abs(v) != float("inf")


def _measurements(j: dict[str, Any], timestamp: str | None) -> list[dict[str, Any]]:
    """Max height (with its band), volume and area; unmeasured ones are left out."""
    jid = _text(j.get("id"))
    m = j.get("measured") or {}
    e = j.get("expected") or {}
    out = []
    h = m.get("max_height_mm")
    if _finite(h):
        value: dict[str, Any] = {"Value": h, "ValueUnits": "mm"}
        if _finite(e.get("nominal_height_mm")):
            value.update(ExpectedValue=e["nominal_height_mm"], ExpectedValueUnits="mm")
        lo, hi = e.get("min_height_mm"), e.get("max_height_mm")
        if _finite(lo):
            value["MinimumAcceptableValue"] = lo
        if _finite(hi):
            value["MaximumAcceptableValue"] = hi
        ok = (not _finite(lo) or h >= lo) and (not _finite(hi) or h <= hi)
        out.append(_numeric(f"{jid} max height", jid, value, "Passed" if ok else "Failed",
                            timestamp))
    # Volume and area have no acceptance limits of their own: recorded, not judged.
    for key, name, units in (("volume_mm3", "volume", "mm3"), ("area_mm2", "area", "mm2")):
        if _finite(m.get(key)):
            out.append(_numeric(f"{jid} {name}", jid, {"Value": m[key], "ValueUnits": units},
                                "Passed", timestamp))
    return out


def _numeric(name: str, crds: str, value: dict[str, Any], result: str,
             timestamp: str | None) -> dict[str, Any]:
    return {"$type": _NUMERIC, "UniqueIdentifier": _uid(), "MeasurementName": name,
            "TimeRecorded": timestamp, "Result": result, "CRDs": crds,
            "MeasuredValue": value}


def _dumps(message: Any) -> str:
    # ASCII-only JSON (non-ASCII as \\u escapes): valid for every consumer, whatever
    # it assumes the encoding to be; NaN never reaches it (unmeasured values are left out).
    return json.dumps(message, indent=2, ensure_ascii=True, allow_nan=False) + "\n"


def write_units_inspected(report: dict[str, Any] | str | os.PathLike,
                          out_dir: str | os.PathLike | None = None, *,
                          source: str | None = None, unit_id: str | None = None) -> Path:
    """Write ``cfx_units_inspected.json`` (atomically) and return its path.

    ``report`` is a ``report.json`` document, the file, or the folder holding it;
    ``out_dir`` defaults to that folder (required for a document). ``source`` and
    ``unit_id`` as in :func:`units_inspected`; call this again on an inspection folder
    to write the message with the line's own station handle and board serial.
    """
    if isinstance(report, dict):
        if out_dir is None:
            raise InputError("out_dir is needed when report is a document, not a path")
        doc = report
    else:
        path = Path(report)
        if path.is_dir():
            path = path / "report.json"
        if not path.is_file():
            raise InputError(f"{path}: no such report.json")
        doc = read_json(path)
        out_dir = path.parent if out_dir is None else out_dir
    message = units_inspected(doc, source=source, unit_id=unit_id)
    return _atomic.write_text(Path(out_dir) / CFX_FILE, _dumps(message))


def collect_units_inspected(report_dirs: Iterable[str | os.PathLike],
                            path: str | os.PathLike) -> tuple[Path, int]:
    """Gather the boards' messages into one JSON list of envelopes at ``path``.

    The list is the standard SDK's format for several envelopes
    (``CFXEnvelope.FromJsonList``), in the order of ``report_dirs``; folders without a
    readable message (a board whose worker crashed) are skipped with a warning.
    Returns the path and the number of messages.
    """
    messages = []
    for d in report_dirs:
        f = Path(d) / CFX_FILE
        if not f.is_file():
            log.warning("%s: no %s; board left out of the collected CFX messages", d, CFX_FILE)
            continue
        try:
            messages.append(read_json(f))
        except InputError as exc:
            log.warning("%s; board left out of the collected CFX messages", exc)
    return _atomic.write_text(path, _dumps(messages)), len(messages)
