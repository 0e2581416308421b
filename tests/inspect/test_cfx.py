"""IPC-CFX UnitsInspected: the demo board's known defects as CFX defect records, the
message against a schema written from the standard's documentation, escaping, the
not-located board, and batch collection."""

import json
import uuid
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from smdinspect.errors import BoardNotLocatedError, InputError
from smdinspect.inspect import (
    CFX_FILE,
    InspectConfig,
    Verdict,
    collect_units_inspected,
    units_inspected,
    write_units_inspected,
)
from smdinspect.inspect._cfx import DEFECT_CATEGORIES
from smdinspect.inspect._inspect import inspect_surface
from smdinspect.inspect._report import report_dict
from smdinspect.pipeline import inspect_stack

from ._synthetic import ALL_DEFECTS, DEMO, DENSE, expected, truth_surface

SCHEMA = json.loads((Path(__file__).parent / "cfx_units_inspected.schema.json").read_text())
VALIDATOR = jsonschema.Draft202012Validator(SCHEMA)
IDEAL = InspectConfig(side_fillet_ratio=0.8)

#: The truth class of a joint -> the CFX DefectCategory its record must carry (the
#: standard's suggested values; CFX has no "missing solder": that is insufficient).
WANT_CATEGORY = {
    "missing": "InsufficientSolder",
    "insufficient": "InsufficientSolder",
    "excess": "ExcessiveSolder",
    "bridge": "Short",
    "lifted_lead": "LiftedLead",
    "tombstone": "Tombstone",
    "component_missing": "ComponentMissing",
    "component_shifted": "ComponentShifted",
}


def validate(message) -> None:
    errors = sorted(VALIDATOR.iter_errors(message), key=lambda e: list(e.path))
    assert not errors, "\n".join(f"{list(e.path)}: {e.message}" for e in errors[:10])


@pytest.fixture(scope="module")
def demo():
    """Demo board with one joint of every defect class; a textureless box leaves U1.3
    unreliable. Returns (report.json document, truth labels)."""
    surface, labels, board = truth_surface(DEMO, ALL_DEFECTS, seed=3, offset_mm=(0.8, -0.5),
                                           rotate_deg=2.0, dead_box=("U1.3", 0.5, 1.2))
    result = inspect_surface(surface, board, IDEAL)
    return report_dict(result, source="/line1/stacks/PANEL-0042"), labels


@pytest.fixture(scope="module")
def message(demo):
    return units_inspected(demo[0], source="ACME.SFF3D.SN1")


def _inspections(msg) -> dict[str, dict]:
    (unit,) = msg["MessageBody"]["InspectedUnits"]
    return {i["InspectionName"]: i for i in unit["Inspections"]}


def test_demo_message_round_trips_through_the_schema(demo, message, tmp_path):
    validate(message)
    path = write_units_inspected(demo[0], tmp_path)
    assert path == tmp_path / CFX_FILE
    doc = json.loads(path.read_text())
    validate(doc)
    assert json.loads(json.dumps(message)) == message  # JSON types only
    env = message
    assert env["MessageName"] == "CFX.Production.TestAndInspection.UnitsInspected"
    assert env["Source"] == "ACME.SFF3D.SN1" and env["Target"] is None and env["RequestID"] is None
    assert env["TimeStamp"] == demo[0]["created"]
    assert list(env) == ["MessageName", "Version", "TimeStamp", "UniqueID", "Source", "Target",
                         "RequestID", "MessageBody"]
    (unit,) = env["MessageBody"]["InspectedUnits"]
    assert unit["UnitIdentifier"] == "PANEL-0042"  # the stack folder's name
    assert unit["OverallResult"] == "Failed"
    assert env["MessageBody"]["InspectionMethod"] == "AOI"
    assert env["MessageBody"]["RecipeName"] == "demo_board"


def test_known_defects_map_to_the_expected_cfx_defect_records(demo, message):
    report, labels = demo
    want = expected(labels)
    verdicts = {j["id"]: j["verdict"] for j in report["joints"]}
    insp = _inspections(message)
    assert set(insp) == set(verdicts)  # one Inspection per joint
    seen = set()
    for lab in labels["joints"]:
        jid, cls = lab["id"], lab["class"]
        got = verdicts[jid]
        i = insp[jid]
        if got == "unreliable":
            assert jid == "U1.3"
            assert i["Result"] == "Error" and i["Error"] and i["DefectsFound"] == []
            continue
        assert got in want[jid], (jid, got, want[jid])  # the inspection found the truth
        if got == "ok":
            assert i["Result"] == "Passed" and i["DefectsFound"] == []
            continue
        truth = cls if cls != "ok" else "bridge"  # an ok joint may be a bridge's partner
        (d,) = i["DefectsFound"]
        assert i["Result"] == "Failed"
        assert d["DefectCategory"] == WANT_CATEGORY[truth], jid
        assert d["DefectCode"] == got
        assert d["ComponentOfInterest"]["ReferenceDesignator"] == jid
        assert d["Description"] == next(j["reason"] for j in report["joints"] if j["id"] == jid)
        pos = next(j["position_mm"] for j in report["joints"] if j["id"] == jid)
        assert (d["RegionOfInterest"]["StartPointX"], d["RegionOfInterest"]["StartPointY"]) == \
            (pos["x"], pos["y"])
        seen.add(d["DefectCategory"])
    # Every defect class of the demo shows up, and the defect count is report.json's.
    assert seen == set(WANT_CATEGORY.values())
    n = sum(len(i["DefectsFound"]) for i in insp.values())
    assert n == report["summary"]["defects"]


def test_measurements_carry_values_units_and_band(demo, message):
    report, _ = demo
    insp = _inspections(message)
    for j in report["joints"]:
        i = insp[j["id"]]
        d = i["DefectsFound"]
        ms = d[0]["RelatedMeasurements"] if d else i["Measurements"]
        if d:
            assert i["Measurements"] == []  # related to the defect: recorded with it
        by = {m["MeasurementName"].rsplit(" ", 1)[-1]: m for m in ms}
        m, e = j["measured"], j["expected"]
        if m["max_height_mm"] is not None:
            h = by["height"]["MeasuredValue"]
            assert h == {"Value": m["max_height_mm"], "ValueUnits": "mm",
                         "ExpectedValue": e["nominal_height_mm"], "ExpectedValueUnits": "mm",
                         "MinimumAcceptableValue": e["min_height_mm"],
                         "MaximumAcceptableValue": e["max_height_mm"]}
            inside = e["min_height_mm"] <= m["max_height_mm"] <= e["max_height_mm"]
            assert by["height"]["Result"] == ("Passed" if inside else "Failed")
        else:
            assert "height" not in by  # unmeasured: left out, never NaN or null
        for name, key, units in (("volume", "volume_mm3", "mm3"), ("area", "area_mm2", "mm2")):
            if m[key] is None:
                assert name not in by
            else:
                assert by[name]["MeasuredValue"] == {"Value": m[key], "ValueUnits": units}
        assert all(x["CRDs"] == j["id"] for x in ms)
    # nearly every joint has all three (the missing component's pads have no volume)
    assert sum(j["measured"]["volume_mm3"] is not None for j in report["joints"]) >= 14
    # the insufficient joint's height fails its band
    u14 = insp["U1.4"]["DefectsFound"][0]["RelatedMeasurements"]
    assert next(x for x in u14 if x["MeasurementName"] == "U1.4 max height")["Result"] == "Failed"


def test_every_defect_verdict_has_a_suggested_cfx_category():
    allowed = set(SCHEMA["$defs"]["DefectCategory"]["enum"])
    for v in Verdict:
        if v.is_defect:
            assert DEFECT_CATEGORIES[v.value] in allowed, v
        else:
            assert v.value not in DEFECT_CATEGORIES


def test_unique_ids_are_fresh_uuids(message, demo):
    again = units_inspected(demo[0])
    ids = [message["UniqueID"], again["UniqueID"], message["MessageBody"]["TransactionId"]]
    ids += [i["UniqueIdentifier"] for i in _inspections(message).values()]
    assert len(set(ids)) == len(ids)
    assert all(str(uuid.UUID(x)) == x for x in ids)
    assert again["Source"].startswith("smdinspect.")  # default handle: this host


def test_text_is_escaped_and_unicode_survives(demo, tmp_path):
    evil = 'R"1\\\n<script>µ±Ω\u2028\x00'
    doc = json.loads(json.dumps(demo[0]))
    doc["joints"][0]["id"] = evil
    k = next(i for i, j in enumerate(doc["joints"]) if j["verdict"] not in ("ok", "unreliable"))
    doc["joints"][k]["reason"] = evil
    doc["board"]["name"] = evil
    path = write_units_inspected(doc, tmp_path, unit_id="Platine-Ä1 \"x\"", source="Ünit.ß")
    raw = path.read_bytes()
    raw.decode("ascii")  # every non-ASCII character escaped: readable in any encoding
    back = json.loads(raw)
    validate(back)
    (unit,) = back["MessageBody"]["InspectedUnits"]
    assert unit["UnitIdentifier"] == "Platine-Ä1 \"x\"" and back["Source"] == "Ünit.ß"
    assert back["MessageBody"]["RecipeName"] == evil
    insp = _inspections(back)
    assert evil in insp
    assert any(i["DefectsFound"] and i["DefectsFound"][0]["Description"] == evil
               for i in insp.values())


def test_bad_input_is_refused():
    with pytest.raises(InputError, match="smdinspect-report"):
        units_inspected({"joints": []})
    with pytest.raises(InputError, match="status"):
        units_inspected({"schema": "smdinspect-report", "status": "pending"})
    with pytest.raises(InputError, match="unit_id must be a non-empty string"):
        units_inspected({"schema": "smdinspect-report", "status": "inspected"}, unit_id=" ")
    with pytest.raises(InputError, match="no such report.json"):
        write_units_inspected("/nonexistent/folder")


def test_not_located_board_gets_an_error_message(tmp_path):
    surface, _, _ = truth_surface(DEMO, "", seed=6)
    with pytest.raises(BoardNotLocatedError) as info:
        inspect_stack(surface, DENSE, tmp_path / "out", source="stacks/b7", html=False)
    doc = json.loads((tmp_path / "out" / CFX_FILE).read_text())
    validate(doc)
    (unit,) = doc["MessageBody"]["InspectedUnits"]
    assert unit["UnitIdentifier"] == "b7" and unit["OverallResult"] == "Error"
    (i,) = unit["Inspections"]
    assert i["Result"] == "Error" and i["Error"] == str(info.value) and i["DefectsFound"] == []


def test_pipeline_writes_the_message_beside_report_json(tmp_path):
    surface, _, board = truth_surface(DEMO, "C1.1:missing", seed=4)
    result = inspect_stack(surface, board, tmp_path / "out", source="PANEL-7", html=False,
                           inspect_config=IDEAL)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    doc = json.loads((tmp_path / "out" / CFX_FILE).read_text())
    validate(doc)
    assert doc["TimeStamp"] == report["created"]
    (unit,) = doc["MessageBody"]["InspectedUnits"]
    assert unit["UnitIdentifier"] == "PANEL-7"
    assert unit["OverallResult"] == ("Passed" if result.passed else "Failed")
    c11 = _inspections(doc)["C1.1"]["DefectsFound"]
    assert [d["DefectCategory"] for d in c11] == ["InsufficientSolder"]


def test_collect_gathers_boards_in_order_and_skips_missing(demo, tmp_path):
    dirs = []
    for name in ("b2", "b1", "b3"):
        d = tmp_path / name
        d.mkdir()
        if name != "b3":
            write_units_inspected(demo[0], d, unit_id=name)
        dirs.append(d)
    path, n = collect_units_inspected(dirs, tmp_path / "all.json")
    msgs = json.loads(path.read_text())
    assert n == 2 and [m["MessageBody"]["InspectedUnits"][0]["UnitIdentifier"] for m in msgs] \
        == ["b2", "b1"]
    for m in msgs:
        validate(m)


# ---------------------------------------------------------------------- batch collection


def truth_inspect(stack, board, out_dir, **kwargs):
    """``inspect_fn`` of the batch test: the stack's ``meta.scene`` names a truth surface
    (no focus sweep to reconstruct); the real pipeline writes the reports."""
    scene = stack.meta["scene"]
    surface, _, _ = truth_surface(DEMO if scene == "demo" else DENSE, stack.meta["defects"],
                                  seed=5)
    return inspect_stack(surface, board, out_dir, source=str(stack.root),
                         inspect_config=kwargs.get("inspect_config"), html=False)


def test_batch_collects_every_boards_message(tmp_path):
    from smdinspect.batch import run_batch
    from smdinspect.stack import StackWriter

    for name, scene, defects in (("PANEL-1", "demo", ""), ("PANEL-2", "demo", "R3.1:tombstone"),
                                 ("PANEL-3", "dense", "")):
        w = StackWriter(tmp_path / "stacks" / name, pixel_size_mm=0.02,
                        meta={"scene": scene, "defects": defects})
        for k in range(3):
            w.add_frame(np.zeros((8, 8), np.uint8), 0.05 * k)
    res = run_batch(tmp_path / "stacks", DEMO, tmp_path / "reports", workers=1, spc=False,
                    html=False, inspect_config=IDEAL,
                    inspect_fn="tests.inspect.test_cfx:truth_inspect")
    msgs = json.loads((tmp_path / "reports" / CFX_FILE).read_text())
    units = [m["MessageBody"]["InspectedUnits"][0] for m in msgs]
    assert [u["UnitIdentifier"] for u in units] == ["PANEL-1", "PANEL-2", "PANEL-3"]
    for m in msgs:
        validate(m)
    assert units[1]["OverallResult"] == "Failed" and units[2]["OverallResult"] == "Error"
    # each board's own message is the one collected
    for b, m in zip(res.boards, msgs):
        assert json.loads((Path(b.out_dir) / CFX_FILE).read_text()) == m
