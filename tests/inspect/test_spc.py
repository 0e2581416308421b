"""SPC across boards: capability and limits by hand, run rules on known series, a drift
injected into synthetic board reports flagged before the joint leaves its band."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.inspect import (
    RULES,
    analyse_reports,
    capability,
    individuals_chart,
    run_rules,
    write_spc,
    xbar_r_chart,
)
from smdinspect.inspect._spc_report import safe_cell

# -- the statistics, by hand ------------------------------------------------------------


def test_capability_by_hand():
    x = [0.20, 0.22, 0.21, 0.23, 0.19]
    cap = capability(x, lsl=0.10, usl=0.30)
    mean = sum(x) / 5                                   # 0.21
    mr_bar = (0.02 + 0.01 + 0.02 + 0.04) / 4            # moving ranges
    sw = mr_bar / 1.128
    s = math.sqrt(sum((v - mean) ** 2 for v in x) / 4)
    assert cap.n == 5 and cap.mean == pytest.approx(mean)
    assert cap.sigma_within == pytest.approx(sw) and cap.sigma == pytest.approx(s)
    assert cap.cp == pytest.approx(0.20 / (6 * sw))
    assert cap.cpk == pytest.approx((0.30 - mean) / (3 * sw))   # nearer the upper limit
    assert cap.pp == pytest.approx(0.20 / (6 * s))
    assert cap.ppk == pytest.approx((0.30 - mean) / (3 * s))
    one_sided = capability(x, lsl=0.10)
    assert math.isnan(one_sided.cp) and one_sided.cpk == pytest.approx((mean - 0.10) / (3 * sw))
    assert math.isnan(capability(x).cpk)                # no band: no capability
    assert math.isnan(capability([0.2]).sigma)
    with pytest.raises(InputError, match="usl must be >= lsl"):
        capability(x, lsl=0.3, usl=0.1)


def test_individuals_chart_limits_by_hand():
    x = np.array([1.0, 3.0, 2.0, 4.0, 2.0, np.nan, 3.0, 9.0])
    ch = individuals_chart(x, baseline=5)
    base = [1.0, 3.0, 2.0, 4.0, 2.0]
    mr = [2.0, 1.0, 2.0, 2.0]
    sigma = (sum(mr) / 4) / 1.128
    assert ch.cl == pytest.approx(2.4) and ch.sigma == pytest.approx(sigma)
    assert ch.ucl == pytest.approx(2.4 + 3 * sigma) and ch.lcl == pytest.approx(2.4 - 3 * sigma)
    assert ch.spread_ucl == pytest.approx(3.267 * sum(mr) / 4)
    # the moving range skips the missing board
    assert np.isnan(ch.spread[5]) and ch.spread[6] == pytest.approx(1.0)
    assert ch.baseline == 5 and ch.subgroup == 1
    assert [(h.index, h.rule) for h in ch.hits if h.rule == 1] == [(7, 1)]  # 9 > UCL 7.05
    assert ch.first_hit == 7
    with pytest.raises(InputError, match="baseline must be an integer >= 2"):
        individuals_chart(x, baseline=1)


def test_xbar_r_chart_limits_by_hand():
    g = np.array([[1.0, 2.0, 3.0], [2.0, 2.0, 2.0], [1.0, 3.0, 2.0], [0.0, 4.0, 2.0]])
    ch = xbar_r_chart(g)
    means, ranges = [2.0, 2.0, 2.0, 2.0], [2.0, 0.0, 2.0, 4.0]
    r_bar = sum(ranges) / 4
    assert ch.kind == "xbar-r" and ch.subgroup == 3
    assert np.allclose(ch.values, means) and np.allclose(ch.spread, ranges)
    assert ch.cl == pytest.approx(2.0) and ch.ucl == pytest.approx(2.0 + 1.023 * r_bar)
    assert ch.sigma == pytest.approx(r_bar / 1.693)
    assert ch.sigma_stat == pytest.approx(r_bar / 1.693 / math.sqrt(3))
    assert ch.spread_ucl == pytest.approx(2.574 * r_bar) and ch.spread_lcl == 0.0
    with pytest.raises(InputError, match="2 <= k <= 10"):
        xbar_r_chart(np.ones((5, 11)))


# -- run rules ------------------------------------------------------------------------


def _fired(z, rule):
    return [h.index for h in run_rules(np.asarray(z, float), cl=0.0, sigma=1.0, rules=[rule])]


def test_each_rule_fires_on_its_pattern_and_only_there():
    assert _fired([0, 0.5, -3.5, 0, 3.2], 1) == [2, 4]
    assert _fired([0.1] * 8 + [-0.1], 2) == []
    assert _fired([0.1] * 10, 2) == [8, 9]                     # 9th and 10th point
    assert _fired([0, 1, 2, 3, 4, 5], 3) == [5]                # six increasing
    assert _fired([0, 1, 2, 3, 4, 4], 3) == []                 # a tie breaks the run
    alt = [(-1) ** i * 0.5 for i in range(14)]
    assert _fired(alt, 4) == [13] and _fired(alt[:13], 4) == []
    assert _fired([2.5, 0, 2.1], 5) == [2]                     # two of three beyond 2σ
    assert _fired([2.5, 0, -2.1], 5) == []                     # not on the same side
    assert _fired([1.5, 1.2, 0, 1.1, 1.3], 6) == [4]           # four of five beyond 1σ
    assert _fired([0.5, -0.5] * 7 + [0.2], 7) == [14]          # fifteen within 1σ
    assert _fired([1.5, -1.5] * 4, 8) == [7]                   # eight beyond 1σ, both sides
    assert _fired([1.5] * 8, 8) == []                          # ... one side only is not 8
    # NaN points are skipped, the run goes on over the others
    assert _fired([0.1] * 4 + [np.nan] + [0.1] * 5, 2) == [9]
    assert run_rules([5.0, 6.0], cl=0.0, sigma=0.0) == []      # no spread, no rule
    with pytest.raises(InputError, match="unknown run rule 9"):
        run_rules([1.0], cl=0.0, sigma=1.0, rules=[9])
    assert sorted(RULES) == list(range(1, 9))


def test_false_alarm_rate_of_in_control_data_matches_theory():
    """Independent normal data, limits from the data: rule 1 fires on ~0.27 % of the
    points, rule 2 on ~2·0.5⁹ = 0.39 % (binomial tolerance, fixed seed)."""
    rng = np.random.default_rng(12)
    x = rng.normal(10.0, 0.5, 40000)
    ch = individuals_chart(x)
    n1 = sum(h.rule == 1 for h in ch.hits)
    n2 = sum(h.rule == 2 for h in ch.hits)
    assert 0.0027 * 40000 * 0.6 < n1 < 0.0027 * 40000 * 1.4
    assert 0.0039 * 40000 * 0.6 < n2 < 0.0039 * 40000 * 1.4
    assert abs(ch.sigma - 0.5) < 0.02 and abs(ch.cl - 10.0) < 0.02


# -- synthetic report folders ---------------------------------------------------------

#: joint id -> (component, package, termination, nominal, min, max) of a small board
JOINTS = {
    "R1.1": ("R1", "0603", "chip_end", 0.20, 0.10, 0.30),
    "R1.2": ("R1", "0603", "chip_end", 0.20, 0.10, 0.30),
    "R2.1": ("R2", "0603", "chip_end", 0.20, 0.10, 0.30),
    "R2.2": ("R2", "0603", "chip_end", 0.20, 0.10, 0.30),
    "U1.1": ("U1", "SOIC-8", "gullwing", 0.12, 0.06, 0.20),
    "U1.2": ("U1", "SOIC-8", "gullwing", 0.12, 0.06, 0.20),
}


def write_report(folder: Path, heights: dict[str, float], *, created="2026-01-01T00:00:00+00:00",
                 status="inspected") -> Path:
    """A ``report.json`` in the format of smdinspect.inspect._report with these max
    heights (volume and area follow the height; NaN gives null)."""
    joints = []
    for jid, h in heights.items():
        comp, pkg, term, nom, lo, hi = JOINTS[jid]
        ok = math.isfinite(h)
        verdict = "ok" if ok and lo <= h <= hi else ("unreliable" if not ok else
                                                     ("insufficient" if h < lo else "excess"))
        joints.append({
            "id": jid, "component": comp, "pad_number": jid.split(".")[1],
            "termination": term, "position_mm": {"x": 1.0, "y": 2.0},
            "world_mm": {"x": 1.0, "y": 2.0},
            "measured": {"max_height_mm": round(h, 6) if ok else None,
                         "volume_mm3": round(0.5 * h, 6) if ok else None,
                         "area_mm2": round(1.0 + h, 6) if ok else None},
            "expected": {"nominal_height_mm": nom, "min_height_mm": lo, "max_height_mm": hi},
            "verdict": verdict, "reason": "",
        })
    comps = [{"ref": r, "kind": "chip" if r.startswith("R") else "gullwing", "package": p,
              "verdict": "ok", "reason": ""}
             for r, p in sorted({(v[0], v[1]) for v in JOINTS.values()})]
    defects = sum(j["verdict"] not in ("ok", "unreliable") for j in joints)
    doc = {"schema": "smdinspect-report", "version": 1, "created": created,
           "status": status, "passed": defects == 0, "exit_code": int(defects > 0),
           "board": {"name": "spc_board", "source": "b.json", "size_mm": [10, 10]},
           "summary": {"joints": len(joints), "defects": defects},
           "components": comps, "joints": joints if status == "inspected" else []}
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "report.json").write_text(json.dumps(doc))
    return folder


def drift_heights(seed: int, n_boards: int = 20, *, drift_start: int = 6,
                  slope_mm: float = -0.009, sigma_mm: float = 0.008) -> list[dict[str, float]]:
    """Every joint at nominal + N(0, σ); R1.1 drifts down by |slope| per board from
    board ``drift_start`` (1-based) on."""
    rng = np.random.default_rng(seed)
    boards = []
    for k in range(1, n_boards + 1):
        hs = {jid: v[3] + rng.normal(0, sigma_mm) for jid, v in JOINTS.items()}
        if k >= drift_start:
            hs["R1.1"] += slope_mm * (k - drift_start + 1)
        boards.append(hs)
    return boards


def test_spc_of_known_heights_by_hand(tmp_path):
    heights = [0.20, 0.24, 0.18, 0.22, 0.21]
    for k, h in enumerate(heights):
        write_report(tmp_path / f"board_{k + 1}", {**{j: 0.2 for j in JOINTS}, "R2.2": h})
    a = analyse_reports([tmp_path])
    assert [b.label for b in a.boards] == [f"board_{k}" for k in range(1, 6)]
    s = a.get("joint", "R2.2")
    mean = sum(heights) / 5
    sw = (0.04 + 0.06 + 0.04 + 0.01) / 4 / 1.128
    assert s.capability.mean == pytest.approx(mean)
    assert s.capability.cpk == pytest.approx(min(0.30 - mean, mean - 0.10) / (3 * sw))
    assert s.capability.cp == pytest.approx(0.20 / (6 * sw))
    vol = a.get("joint", "R2.2", "volume_mm3")
    assert vol.capability.mean == pytest.approx(0.5 * mean) and math.isnan(vol.capability.cpk)
    # the type 0603/chip_end: X̄–R over its 4 joints per board
    t = a.get("type", "0603/chip_end")
    assert t.chart.kind == "xbar-r" and t.chart.subgroup == 4
    assert np.allclose(t.chart.values, [(0.6 + h) / 4 for h in heights])
    assert t.capability.n == 20 and t.capability.lsl == 0.10
    ranges = [abs(h - 0.2) for h in heights]
    assert t.chart.sigma == pytest.approx(np.mean(ranges) / 2.059)
    # the gull-wing type has 2 joints per board
    assert a.get("type", "SOIC-8/gullwing").chart.subgroup == 2


def test_drift_is_flagged_before_the_joint_leaves_its_band(tmp_path):
    """20 boards, R1.1 drifting down 9 µm per board from board 6 (σ 8 µm): from the
    drift's onset, a run rule fires at least 3 boards before its max height first
    leaves [0.10, 0.30] mm, for every seed tried, with the default baseline (first 10
    boards, drift included) and with the in-control boards 1-5 as baseline (then no
    rule fires before the onset either)."""
    onset = 5  # 0-based index of board 6
    for seed in range(10):
        root = tmp_path / f"seed{seed}"
        boards = drift_heights(seed)
        for k, hs in enumerate(boards):
            write_report(root / f"board_{k + 1:02d}", hs)
        leaves = next(i for i, hs in enumerate(boards) if not 0.10 <= hs["R1.1"] <= 0.30)
        for baseline in (None, 5):
            s = analyse_reports([root], baseline=baseline).get("joint", "R1.1")
            after = [h.index for h in s.chart.hits if h.index >= onset]
            assert after and leaves - min(after) >= 3, (seed, baseline, leaves, s.chart.hits)
            if baseline == 5:
                assert s.chart.first_hit >= onset, (seed, s.chart.hits)


def test_run_rules_tell_drift_from_stable_process():
    """400 seeded 20-board series of each kind through the default chart (limits from
    the first 10 boards): every drifting series is flagged after its onset; in-control
    series raise a false alarm somewhere in about a third of the cases (the known price
    of eight run rules on short baselines; the README quotes the rate)."""
    rng = np.random.default_rng(2)
    stable = drift = 0
    for _ in range(400):
        x = rng.normal(0.20, 0.008, 20)
        stable += bool(individuals_chart(x, baseline=10).hits)
        y = x - 0.009 * np.clip(np.arange(1, 21) - 5, 0, None)
        drift += any(h.index >= 5 for h in individuals_chart(y, baseline=10).hits)
    assert drift == 400
    assert 0.2 < stable / 400 < 0.45


def test_write_spc_files_charts_and_page(tmp_path):
    root = tmp_path / "reports"
    for k, hs in enumerate(drift_heights(3)):
        write_report(root / "line" / f"board_{k + 1}", hs)
    write_report(root / "line" / "board_99", {}, status="not_located")
    a = analyse_reports([root], baseline=10)
    assert a.skipped == ("line/board_99",) and len(a.boards) == 20 and a.baseline == 10
    out = tmp_path / "spc"
    written = write_spc(a, out)
    with open(written["spc.csv"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    n_types = 2
    assert len(rows) == (len(JOINTS) + n_types) * 3
    r = next(r for r in rows if (r["scope"], r["key"], r["metric"]) == ("joint", "R1.1",
                                                                        "max_height_mm"))
    s = a.get("joint", "R1.1")
    assert float(r["cpk"]) == pytest.approx(s.capability.cpk, rel=1e-3)
    assert int(r["flags"]) == len(s.chart.hits) > 0
    assert r["first_flag_board"] == a.boards[s.chart.first_hit].label
    assert r["chart_png"] == "charts/joint_R1.1.png" and r["baseline_boards"] == "10"
    with open(written["spc_flags.csv"], newline="") as fh:
        flags = list(csv.DictReader(fh))
    assert any(f["key"] == "R1.1" and f["meaning"] == RULES[int(f["rule"])] for f in flags)
    with open(written["spc_values.csv"], newline="") as fh:
        values = list(csv.DictReader(fh))
    assert len(values) == 20 * len(JOINTS)
    # every chart is a real, non-blank PNG
    import cv2

    pngs = sorted((out / "charts").glob("*.png"))
    assert len(pngs) == len(JOINTS) + n_types
    img = cv2.imread(str(out / "charts" / "joint_R1.1.png"))
    assert img is not None and img.shape[0] > 300 and img.std() > 10
    page = (out / "spc.html").read_text()
    assert "R1.1" in page and 'src="charts/joint_R1.1.png"' in page and "<script" not in page


def test_text_is_escaped_and_csv_cells_neutralised(tmp_path):
    assert safe_cell("=HYPERLINK(1)") == "'=HYPERLINK(1)" and safe_cell("-1") == "'-1"
    assert safe_cell(-1.5) == -1.5 and safe_cell("R1.1") == "R1.1"
    root = tmp_path / "r"
    for k in range(3):
        write_report(root / f"=cmd<b>{k}", {j: 0.2 + 0.01 * k for j in JOINTS})
    write_spc(analyse_reports([root]), tmp_path / "spc", charts=False)
    assert "<b>" not in (tmp_path / "spc" / "spc.html").read_text()
    with open(tmp_path / "spc" / "spc_values.csv", newline="") as fh:
        assert all(r["board"].startswith("'=") for r in csv.DictReader(fh))


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="report folder not found"):
        analyse_reports([tmp_path / "nope"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no report.json"):
        analyse_reports([tmp_path / "empty"])
    write_report(tmp_path / "one" / "b1", {j: 0.2 for j in JOINTS})
    with pytest.raises(InputError, match="at least 2 inspected boards; found 1"):
        analyse_reports([tmp_path / "one"])
    (tmp_path / "one" / "b2").mkdir()
    (tmp_path / "one" / "b2" / "report.json").write_text("{not json")
    with pytest.raises(InputError, match="b2.report.json is not valid JSON"):
        analyse_reports([tmp_path / "one"])
    with pytest.raises(InputError, match="order must be"):
        analyse_reports([tmp_path / "one"], order="random")


def test_order_of_boards(tmp_path):
    for name, created in (("b10", "2026-01-01T00:00:01"), ("b9", "2026-01-01T00:00:03"),
                          ("b2", "2026-01-01T00:00:02")):
        write_report(tmp_path / name, {j: 0.2 for j in JOINTS}, created=created)
    labels = lambda **kw: [b.label for b in analyse_reports(
        [tmp_path / "b9", tmp_path / "b10", tmp_path / "b2"], **kw).boards]
    assert labels() == ["b2", "b9", "b10"]                # natural sort
    assert labels(order="given") == ["b9", "b10", "b2"]
    assert labels(order="created") == ["b10", "b2", "b9"]


def test_spc_command(tmp_path, capsys):
    from smdinspect import cli

    root = tmp_path / "reports"
    for k, hs in enumerate(drift_heights(1)):
        write_report(root / f"board_{k + 1:02d}", hs)
    code = cli.main(["-q", "spc", str(root), "--out", str(tmp_path / "spc")])
    out = capsys.readouterr().out
    assert code == 1 and "joint R1.1 max_height_mm: rules" in out  # drift found: exit 1
    assert (tmp_path / "spc" / "spc.csv").is_file()
    assert cli.main(["-q", "spc", str(tmp_path / "nope"), "--out", str(tmp_path / "x")]) == 2
