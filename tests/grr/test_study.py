"""Gauge R&R studies of synthetic result sets with known variance components."""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.grr import GRR_COLUMNS, GrrRecord, analyse_grr, write_grr

BAND = (0.13, 0.572)
#: (joint id, component, package, termination, true max height mm)
JOINTS = [(f"U1.{k}", "U1", "SOIC-8", "gullwing_heel", 0.28 + 0.01 * k) for k in range(1, 9)] + [
    ("R1.1", "R1", "0603", "chip_end", 0.25), ("R1.2", "R1", "0603", "chip_end", 0.26),
    ("R3.1", "R3", "0603", "chip_end", 0.24), ("R3.2", "R3", "0603", "chip_end", 0.27)]
SD_E = 0.004                                      # repeatability (mm)
OPERATOR_OFFSET = {"A": -0.003, "B": 0.0, "C": 0.004}  # reproducibility (fixed, known)


def records(n_per_operator=10, operators=("A", "B", "C"), *, seed=0, board="demo_board",
            unreliable=(), joints=JOINTS):
    rng = np.random.default_rng(seed)
    out = []
    for o in operators:
        for t in range(n_per_operator):
            label = f"{o}{t}"
            js = []
            for jid, comp, _, term, h in joints:
                v = h + OPERATOR_OFFSET[o] + rng.normal(0, SD_E)
                js.append({"id": jid, "component": comp, "termination": term,
                           "verdict": "unreliable" if (label, jid) in unreliable else "ok",
                           "measured": {"max_height_mm": v, "volume_mm3": 0.01 * v / h,
                                        "area_mm2": 0.15 + rng.normal(0, 0.002)},
                           "expected": {"min_height_mm": BAND[0], "max_height_mm": BAND[1]}})
            out.append(GrrRecord(label=label, operator=o, report_dir=Path(label), source=label,
                                 board_name=board, joints=tuple(js),
                                 packages={c: p for _, c, p, _, _ in joints}))
    return out


def test_type_study_recovers_repeatability_and_reproducibility():
    study = analyse_grr(records(), board_name="demo_board")
    row = study.get("type", "SOIC-8/gullwing_heel")
    g = row.gauge
    assert g.method == "crossed" and (g.n_parts, g.n_operators, g.n_trials) == (8, 3, 10)
    assert g.sigma_repeatability == pytest.approx(SD_E, rel=0.1)
    offsets = np.array(list(OPERATOR_OFFSET.values()))
    assert math.sqrt(g.var_operator) == pytest.approx(offsets.std(ddof=1), rel=0.15)
    # no interaction in the data (seed 0's F test happens to reject at p = 0.03)
    assert g.var_interaction <= (0.3 * SD_E) ** 2
    # parts: the joints' true heights 0.29..0.36
    truth = np.array([h for *_, h in JOINTS[:8]])
    assert g.sigma_part == pytest.approx(truth.std(ddof=1), rel=0.1)
    assert row.tolerance == pytest.approx(BAND[1] - BAND[0])
    grr = math.hypot(SD_E, offsets.std(ddof=1))
    assert g.pct_tolerance == pytest.approx(600 * grr / (BAND[1] - BAND[0]), rel=0.12)
    assert row.rating == "acceptable" and g.ndc == math.floor(1.41 * g.sigma_part / g.sigma_grr)


def test_joint_study_with_operators():
    study = analyse_grr(records(n_per_operator=20, seed=1))
    g = study.get("joint", "R3.1").gauge
    assert g.method == "one-way" and g.n == 60 and g.n_parts == 1
    assert g.sigma_repeatability == pytest.approx(SD_E, rel=0.15)
    offsets = np.array(list(OPERATOR_OFFSET.values()))
    assert g.sigma_reproducibility == pytest.approx(offsets.std(ddof=1), rel=0.2)
    assert math.isnan(g.ndc)  # one part: no part variation
    # volume and area have no band: %GR&R of the tolerance is NaN, the CV is given
    v = study.get("joint", "R3.1", "volume_mm3")
    assert math.isnan(v.gauge.pct_tolerance) and v.rating == "n/a" and v.cv_pct > 0


def test_one_operator_gives_repeatability_only():
    study = analyse_grr(records(n_per_operator=12, operators=("B",), seed=2))
    row = study.get("joint", "U1.3")
    g = row.gauge
    assert math.isnan(g.var_operator) and g.sigma_grr == g.sigma_repeatability
    assert g.sigma_repeatability == pytest.approx(SD_E, rel=0.35)
    t = study.get("type", "0603/chip_end").gauge
    assert t.method == "one-way" and t.n_parts == 4 and t.sigma_repeatability == pytest.approx(
        SD_E, rel=0.2)
    assert study.failing(30.0) == []
    assert {r.key for r in study.failing(1.0)} >= {"U1.3", "0603/chip_end"}


def test_unreliable_readings_are_left_out():
    recs = records(n_per_operator=4, unreliable={("A1", "R1.1"), ("B2", "R1.1")})
    study = analyse_grr(recs)
    row = study.get("joint", "R1.1")
    assert row.n_unreliable == 2 and row.gauge.n == 10
    t = study.get("type", "0603/chip_end")
    assert t.n_joints == 4 and t.gauge.n_parts == 3  # the crossed design needs every reading
    kept = analyse_grr(recs, include_unreliable=True).get("joint", "R1.1")
    assert kept.n_unreliable == 0 and kept.gauge.n == 12


def test_errors():
    with pytest.raises(InputError, match="at least 2 sweeps"):
        analyse_grr(records(n_per_operator=1, operators=("A",)))
    mixed = records(2, ("A",)) + records(1, ("B",), board="dense_board")
    with pytest.raises(InputError, match="different boards"):
        analyse_grr(mixed)
    with pytest.raises(InputError, match="inspected against board 'dense_board', not "
                                         "'demo_board'"):
        analyse_grr(mixed, board_name="demo_board")
    fewer = records(2, ("A",)) + records(1, ("B",), joints=JOINTS[:-1])
    with pytest.raises(InputError, match="different joints .*R3.2"):
        analyse_grr(fewer)
    with pytest.raises(InputError, match="other joints than the board"):
        analyse_grr(records(2, ("A",)), joint_ids=["U1.1"])
    with pytest.raises(InputError, match="same number of sweeps per operator; got A: 2, B: 1"):
        analyse_grr(records(2, ("A",)) + records(1, ("B",)))


def test_written_files(tmp_path):
    study = analyse_grr(records(n_per_operator=3, operators=("A", "B")))
    written = write_grr(study, tmp_path, max_pct=5.0)
    assert sorted(written) == ["grr.csv", "grr.json", "grr.png", "grr_values.csv"]
    rows = list(csv.DictReader(open(tmp_path / "grr.csv")))
    assert tuple(rows[0]) == GRR_COLUMNS
    assert len(rows) == (len(JOINTS) + 2) * 3
    soic = next(r for r in rows if r["key"] == "SOIC-8/gullwing_heel"
                and r["metric"] == "max_height_mm")
    assert soic["method"] == "crossed" and soic["n_operators"] == "2" and soic["ndc"] != ""
    assert float(soic["pct_grr_tolerance"]) == pytest.approx(
        study.get("type", "SOIC-8/gullwing_heel").gauge.pct_tolerance, rel=1e-4)
    doc = json.loads((tmp_path / "grr.json").read_text())
    assert doc["schema"] == "smdinspect-grr" and doc["operators"] == ["A", "B"]
    assert doc["exit_code"] == (1 if study.failing(5.0) else 0)
    type_doc = next(s for s in doc["studies"] if s["key"] == "SOIC-8/gullwing_heel")
    assert [t["source"] for t in type_doc["anova"]][-1] == "repeatability"
    values = list(csv.DictReader(open(tmp_path / "grr_values.csv")))
    assert len(values) == 6 * len(JOINTS)
    assert (tmp_path / "grr.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
