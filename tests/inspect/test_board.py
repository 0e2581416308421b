"""Reference board files: loader, package defaults, validation, round trip."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.inspect._board import (
    PACKAGES,
    Board,
    board_from_dict,
    joint_band,
    load_board,
    package_defaults,
    polygons_overlap,
)

REFS = Path(__file__).resolve().parents[2] / "references"


def _tiny() -> dict:
    """A valid one-resistor board, written explicitly."""
    return {
        "schema": "smdinspect-board", "version": 1, "name": "tiny", "units": "mm",
        "size_mm": [4.0, 3.0], "thickness_mm": 1.6,
        "fiducials": [{"id": "F1", "x_mm": 0.4, "y_mm": 0.4, "diameter_mm": 0.5}],
        "components": [{
            "ref": "R1", "package": "0603", "kind": "chip", "x_mm": 2.0, "y_mm": 1.5,
            "rotation_deg": 90.0,
            "body": {"length_mm": 1.6, "width_mm": 0.8, "height_mm": 0.45,
                     "standoff_mm": 0.03, "termination_length_mm": 0.3},
            "pads": [
                {"number": "1", "x_mm": -0.78, "y_mm": 0.0, "length_mm": 0.8,
                 "width_mm": 0.95},
                {"number": "2", "x_mm": 0.78, "y_mm": 0.0, "length_mm": 0.8,
                 "width_mm": 0.95},
            ],
        }],
    }


def _write(tmp_path: Path, data, name: str = "b.json") -> Path:
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else json.dumps(data))
    return p


@pytest.mark.parametrize("name, n_comp, n_joints", [("demo_board", 6, 18),
                                                     ("dense_board", 8, 36)])
def test_shipped_boards_load(name, n_comp, n_joints):
    b = load_board(REFS / f"{name}.json")
    assert isinstance(b, Board)
    assert b.name == name
    assert len(b.components) == n_comp
    assert len(b.joints()) == n_joints
    assert len(b.fiducials) >= 2
    kinds = {c.kind for c in b.components}
    assert kinds == {"chip", "gullwing"}
    w, h = b.size_mm
    for j in b.joints():
        assert j.min_height_mm < j.nominal_height_mm < j.max_height_mm
        assert j.polygon_mm.shape[1] == 2
        assert 0 <= j.polygon_mm[:, 0].min() and j.polygon_mm[:, 0].max() <= w
        assert 0 <= j.polygon_mm[:, 1].min() and j.polygon_mm[:, 1].max() <= h
        assert j.id == f"{j.component}.{j.pad_number}"
    # Demo board must fit ~9.5 mm so ±2 mm placement stays inside 15.4 mm of view.
    if name == "demo_board":
        assert max(b.size_mm) <= 9.5
    assert b.source.endswith(f"{name}.json")


def test_demo_geometry_and_bands():
    b = load_board(REFS / "demo_board.json")
    r1 = b.component("R1")
    assert r1.package == "0603" and r1.kind == "chip" and r1.style == "resistor"
    j1, j2 = r1.joints
    # Rotation 0: pad 1 on the left at x - 0.78, polygon 0.8 long along x, 0.95 wide.
    assert j1.center_mm == pytest.approx((r1.x_mm - 0.78, r1.y_mm))
    assert np.ptp(j1.polygon_mm[:, 0]) == pytest.approx(0.8)
    assert np.ptp(j1.polygon_mm[:, 1]) == pytest.approx(0.95)
    assert j1.outward == pytest.approx((-1.0, 0.0))
    assert j2.outward == pytest.approx((1.0, 0.0))
    # IPC-A-610 class 2 chip: min G + 25 % H, max G + H.
    assert j1.min_height_mm == pytest.approx(0.03 + 0.25 * 0.45)
    assert j1.max_height_mm == pytest.approx(0.03 + 0.45)
    assert j1.termination == "chip_end"
    # C1 rotated 90°: pad 1 below the centre, pad long along y.
    c1 = b.component("C1")
    j = c1.joints[0]
    assert j.center_mm == pytest.approx((c1.x_mm, c1.y_mm - 1.45))
    assert np.ptp(j.polygon_mm[:, 1]) == pytest.approx(1.15)
    assert j.outward == pytest.approx((0.0, -1.0), abs=1e-12)
    # Gull-wing: pins counter-clockwise from pin 1 at lower-left; heel band G + T/2.
    u1 = b.component("U1")
    assert u1.kind == "gullwing" and len(u1.joints) == 8
    xs = [j.center_mm[0] for j in u1.joints[:4]]
    assert xs == sorted(xs)
    assert u1.joints[0].center_mm[1] < u1.y_mm < u1.joints[4].center_mm[1]
    assert u1.joints[4].center_mm[0] > u1.joints[7].center_mm[0]
    assert u1.joints[0].min_height_mm == pytest.approx(0.03 + 0.5 * 0.2)
    assert u1.joints[0].termination == "gullwing_heel"
    assert u1.joints[0].outward == pytest.approx((0.0, -1.0), abs=1e-12)
    # Body and termination outlines.
    body = u1.body_polygon_mm()
    assert np.ptp(body[:, 0]) == pytest.approx(4.9) and np.ptp(body[:, 1]) == pytest.approx(3.9)
    lead = u1.termination_polygon_mm("U1.1")
    assert lead[:, 1].min() == pytest.approx(u1.y_mm - 3.0)       # toe at span/2
    assert lead[:, 1].max() == pytest.approx(u1.y_mm - 1.95)      # leaves the body
    cap = r1.termination_polygon_mm("R1.2")
    assert cap[:, 0].min() == pytest.approx(r1.x_mm + 0.5) and \
        cap[:, 0].max() == pytest.approx(r1.x_mm + 0.8)


def test_round_trip(tmp_path):
    for name in ("demo_board", "dense_board"):
        b = load_board(REFS / f"{name}.json")
        d = b.to_dict()
        p = _write(tmp_path, json.loads(json.dumps(d)), f"{name}.json")
        b2 = load_board(p)
        assert b2.to_dict() == d
        assert board_from_dict(d, source="mem").to_dict() == d
        for j, j2 in zip(b.joints(), b2.joints()):
            np.testing.assert_allclose(j.polygon_mm, j2.polygon_mm, atol=1e-12)
            assert j.max_height_mm == j2.max_height_mm


def test_package_defaults_fill_in(tmp_path):
    d = _tiny()
    comp = d["components"][0]
    del comp["body"], comp["pads"], comp["kind"]
    b = load_board(_write(tmp_path, d))
    r1 = b.component("R1")
    assert r1.body_height_mm == PACKAGES["0603"]["height_mm"]["resistor"]
    assert len(r1.joints) == 2
    # Capacitor style from the "C" prefix.
    comp["ref"] = "C7"
    assert load_board(_write(tmp_path, d)).component("C7").body_height_mm == 0.8
    for pkg in PACKAGES:
        pd = package_defaults(pkg)
        assert pd["pads"] and pd["body"]["height_mm"] > 0


def test_polygon_pad_and_overlap_helper(tmp_path):
    d = _tiny()
    # An L-shaped (non-convex) pad 1.
    d["components"][0]["pads"][0] = {
        "number": "1",
        "polygon_mm": [[-1.18, -0.475], [-0.38, -0.475], [-0.38, 0.0], [-0.78, 0.0],
                       [-0.78, 0.475], [-1.18, 0.475]]}
    b = load_board(_write(tmp_path, d))
    j = b.joint("R1.1")
    assert j.polygon_mm.shape == (6, 2)
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    assert polygons_overlap(sq, sq + [0.5, 0.5])
    assert not polygons_overlap(sq, sq + [1.0, 0.0])          # touching only
    ell = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float)
    assert not polygons_overlap(ell, sq + [1.2, 1.2])         # in the L's notch
    assert polygons_overlap(ell, sq + [0.8, 0.8])


def _mutate(fn):
    d = _tiny()
    fn(d)
    return d


def _set(path, value):
    def fn(d):
        node = d
        for k in path[:-1]:
            node = node[k]
        if value is KeyError:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return fn


def _second_component(d):
    c = copy.deepcopy(d["components"][0])
    c["x_mm"] = 2.3                                    # pads overlap R1's
    c["ref"] = "R2"
    d["components"].append(c)


def _duplicate_ref(d):
    c = copy.deepcopy(d["components"][0])
    c["x_mm"] = 3.5
    c["rotation_deg"] = 0.0
    c["y_mm"] = 0.5
    d["size_mm"] = [6.0, 3.0]
    c["x_mm"] = 4.5
    c["y_mm"] = 2.3
    d["components"].append(c)


@pytest.mark.parametrize("mutate, match", [
    (_set(["units"], "inch"), r"b\.json: unknown units 'inch'; only 'mm'"),
    (_set(["units"], KeyError), r"board: missing field 'units'"),
    (_set(["name"], KeyError), r"board: missing field 'name'"),
    (_set(["schema"], "other"), r"'schema' must be 'smdinspect-board'"),
    (_set(["size_mm"], [4.0, -3.0]), r"size_mm\[1\] \(height\) must be > 0; got -3\.0"),
    (_set(["thickness_mm"], 0), r"thickness_mm must be > 0; got 0"),
    (_set(["components", 0, "x_mm"], KeyError), r"component R1: missing field 'x_mm'"),
    (_set(["components", 0, "rotation_deg"], KeyError),
     r"component R1: missing field 'rotation_deg'"),
    (_set(["components", 0, "body", "height_mm"], -0.45),
     r"component R1: body height_mm must be > 0; got -0\.45"),
    (_set(["components", 0, "body", "width_mm"], 0.0),
     r"component R1: body width_mm must be > 0; got 0\.0"),
    (_set(["components", 0, "pads", 1, "width_mm"], -0.95),
     r"joint R1\.2: width_mm must be > 0; got -0\.95"),
    (_set(["components", 0, "pads", 0, "length_mm"], KeyError),
     r"joint R1\.1: missing field 'length_mm'"),
    (_set(["components", 0, "pads", 1, "x_mm"], -0.3), r"pads of joints R1\.1 and R1\.2 overlap"),
    (_set(["components", 0, "x_mm"], 3.8), r"joint R1\.\d: pad lies outside the board"),
    (_set(["components", 0, "y_mm"], 0.3), r"joint R1\.1: pad lies outside the board"),
    (_set(["components", 0, "kind"], "bga"), r"component R1: 'kind' must be one of chip, "),
    (lambda d: (d["components"][0].update(package="0201"), d["components"][0].pop("body")),
     r"component R1: missing field 'body' \(package '0201' has no defaults\)"),
    (_set(["components", 0, "pads", 0, "joint"], {"min_height_mm": 0.5}),
     r"joint R1\.1: min_height_mm \(0\.5\) must be < max_height_mm"),
    (_set(["fiducials", 0, "diameter_mm"], -1), r"fiducial F1: diameter_mm must be > 0"),
    (_set(["components", 0, "pads", 0, "polygon_mm"], [[0, 0], [1, 1], [1, 0], [0, 1]]),
     r"joint R1\.1: pad polygon intersects itself"),
    (_second_component, r"pads of joints R1\.\d and R2\.\d overlap"),
    (_duplicate_ref, r"duplicate component ref 'R1'"),
    (_set(["components"], []), r"'components' must be a non-empty list"),
])
def test_validation_errors(tmp_path, mutate, match):
    p = _write(tmp_path, _mutate(mutate))
    with pytest.raises(InputError, match=match) as info:
        load_board(p)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(str(p))


def test_bad_json_and_missing_file(tmp_path):
    p = _write(tmp_path, '{"schema": "smdinspect-board", "version": 1,,}')
    with pytest.raises(InputError, match=r"b\.json: not valid JSON: .* line 1 column"):
        load_board(p)
    with pytest.raises(InputError, match="does not exist"):
        load_board(tmp_path / "nope.json")
    with pytest.raises(InputError, match="top level must be a JSON object"):
        load_board(_write(tmp_path, "[1, 2]"))


def test_lookup_errors_and_band_rules():
    b = load_board(REFS / "demo_board.json")
    with pytest.raises(InputError, match=r"no component 'X9'; components: U1, C1"):
        b.component("X9")
    with pytest.raises(InputError, match=r"no joint 'R1\.7'"):
        b.joint("R1.7")
    nominal, lo, hi = joint_band("chip", body_height_mm=3.0, standoff_mm=0.05)
    assert lo == pytest.approx(0.55)           # G + 0.5 mm cap when 25 % H is larger
    assert hi == pytest.approx(3.05)
    with pytest.raises(InputError, match="unknown package 'DIP-8'"):
        package_defaults("DIP-8")
