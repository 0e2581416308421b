"""KiCad board import: files of KiCad 6, 7, 8 and 9 written in the test, checked against
the board files they describe, hand-computed placements, and the loader."""

import json
import math

import numpy as np
import pytest

from smdinspect.cad import import_board, load_any_board, read_kicad_pcb
from smdinspect.cli import main
from smdinspect.errors import InputError
from smdinspect.inspect import load_board

from ._kicad_files import (FOOTPRINT, ORIGIN, board_to_kicad, footprint, header, outline,
                           pad)

DEMO = "references/demo_board.json"
DENSE = "references/dense_board.json"
TOL_MM = 1e-6   # 1 nm: far inside the 1 µm goal


def _write(tmp_path, text, name="board.kicad_pcb"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


def _assert_same_board(got, want, *, tol=TOL_MM, exact_polygons=True):
    assert got.size_mm == pytest.approx(want.size_mm, abs=tol)
    assert [f.id for f in got.fiducials] == [f.id for f in want.fiducials]
    for f0, f1 in zip(want.fiducials, got.fiducials):
        assert (f1.x_mm, f1.y_mm, f1.diameter_mm) == pytest.approx(
            (f0.x_mm, f0.y_mm, f0.diameter_mm), abs=tol)
    assert sorted(c.ref for c in got.components) == sorted(c.ref for c in want.components)
    for c0 in want.components:
        c1 = got.component(c0.ref)
        assert (c1.package, c1.kind, c1.style) == (c0.package, c0.kind, c0.style)
        assert (c1.x_mm, c1.y_mm) == pytest.approx((c0.x_mm, c0.y_mm), abs=tol)
        assert abs((c1.rotation_deg - c0.rotation_deg + 180) % 360 - 180) < 1e-6
        assert (c1.body_length_mm, c1.body_width_mm, c1.body_height_mm) == \
            (c0.body_length_mm, c0.body_width_mm, c0.body_height_mm)
        assert [j.id for j in c1.joints] == [j.id for j in c0.joints]
        for j0, j1 in zip(c0.joints, c1.joints):
            assert j1.center_mm == pytest.approx(j0.center_mm, abs=tol)
            if exact_polygons:
                assert len(j1.polygon_mm) == len(j0.polygon_mm)
                # same corners (the loader may start the outline at another corner)
                d = np.linalg.norm(j1.polygon_mm[:, None] - j0.polygon_mm[None], axis=2)
                assert d.min(axis=1).max() <= tol
            for lo_hi in ((0, 1),):
                for k in lo_hi:
                    assert j1.polygon_mm[:, k].min() == pytest.approx(j0.polygon_mm[:, k].min(), abs=tol)
                    assert j1.polygon_mm[:, k].max() == pytest.approx(j0.polygon_mm[:, k].max(), abs=tol)
            assert (j1.min_height_mm, j1.max_height_mm) == (j0.min_height_mm, j0.max_height_mm)
            assert j1.outward == pytest.approx(j0.outward, abs=1e-9)


@pytest.mark.parametrize("version", [6, 7, 8, 9])
@pytest.mark.parametrize("board_file", [DEMO, DENSE])
def test_each_kicad_version_reproduces_the_board_file(tmp_path, version, board_file):
    path = _write(tmp_path, board_to_kicad(board_file, version, seed=version))
    result = import_board(path)
    assert result.skipped == ()
    assert result.info["kicad_version"] == str(version)
    _assert_same_board(result.board, load_board(board_file))


@pytest.mark.parametrize("version", [6, 9])
def test_roundrect_pads_rotated_in_the_footprint(tmp_path, version):
    # Rounded pads written at 90° in the footprint with their size swapped: same centres
    # and extents, outlines that are polygons.
    text = board_to_kicad(DEMO, version, shape="roundrect", pad_local_angle=90.0,
                          outline_style="rect")
    result = import_board(_write(tmp_path, text))
    _assert_same_board(result.board, load_board(DEMO), exact_polygons=False)
    j = result.board.joint("R1.1")
    assert "polygon_mm" in j.spec and len(j.polygon_mm) == 36


def test_written_file_loads_with_the_loader_and_lists_the_source(tmp_path):
    path = _write(tmp_path, board_to_kicad(DEMO, 8))
    out = tmp_path / "b.json"
    import_board(path).write(out)
    doc = json.loads(out.read_text())
    assert doc["schema"] == "smdinspect-board" and doc["version"] == 1
    assert doc["import"]["format"] == "kicad_pcb" and doc["import"]["kicad_version"] == "8"
    board = load_board(out)
    _assert_same_board(board, load_board(DEMO))
    # Board.to_dict() of the loaded file is the file minus the import record.
    doc.pop("import")
    assert board.to_dict() == doc
    assert load_any_board(path).to_dict() == doc


def test_rotated_footprint_against_hand_computed_positions(tmp_path):
    # An 0805 at 30° and an SOIC-8 at 120° (screen angles, y down), off the board origin.
    rng = np.random.default_rng(1)
    x0, y0 = ORIGIN
    lines = header(8) + outline(8, 20.0, 15.0, rng)
    r_pads = [pad(8, "1", "rect", -0.95, 0.0, 30.0, (1.0, 1.4), rng),
              pad(8, "2", "rect", 0.95, 0.0, 30.0, (1.0, 1.4), rng)]
    lines += footprint(8, "Resistor_SMD:R_0805_2012Metric", "R7", x0 + 5.0, y0 + 4.0, 30.0,
                       r_pads, rng)
    u_pads = []
    for k in range(8):
        col = -2.7 if k < 4 else 2.7
        row = (-1.905 + 1.27 * k) if k < 4 else (1.905 - 1.27 * (k - 4))
        u_pads.append(pad(8, str(k + 1), "rect", col, row, 120.0, (1.55, 0.6), rng))
    lines += footprint(8, "Package_SO:SOIC-8_3.9x4.9mm_P1.27mm", "U3", x0 + 12.0, y0 + 8.0,
                       120.0, u_pads, rng)
    lines.append(")")
    board = import_board(_write(tmp_path, "\n".join(lines))).board

    def kicad_to_board(fx, fy, angle, px, py):
        # KiCad: screen CCW rotation in a y-down frame, then y flipped about the top edge.
        a = math.radians(angle)
        kx = fx + px * math.cos(a) + py * math.sin(a)
        ky = fy - px * math.sin(a) + py * math.cos(a)
        return kx - x0, (y0 + 15.0) - ky

    assert board.component("R7").rotation_deg == pytest.approx(30.0)
    assert board.component("U3").rotation_deg == pytest.approx(30.0)   # 120° − 90°
    assert board.joint("R7.2").center_mm == pytest.approx(
        kicad_to_board(x0 + 5, y0 + 4, 30, 0.95, 0.0), abs=1e-9)
    assert board.joint("U3.1").center_mm == pytest.approx(
        kicad_to_board(x0 + 12, y0 + 8, 120, -2.7, -1.905), abs=1e-9)
    assert board.joint("U3.6").center_mm == pytest.approx(
        kicad_to_board(x0 + 12, y0 + 8, 120, 2.7, 0.635), abs=1e-9)
    # the pad's long side runs along the lead (outward), in the board frame
    u1 = board.joint("U3.1")
    edges = np.diff(np.vstack([u1.polygon_mm, u1.polygon_mm[:1]]), axis=0)
    longest = edges[np.argmax(np.linalg.norm(edges, axis=1))]
    assert abs(np.dot(longest / np.linalg.norm(longest), u1.outward)) == pytest.approx(1.0)


def _mixed_board(version: int) -> str:
    rng = np.random.default_rng(5)
    x0, y0 = ORIGIN
    lines = header(version) + outline(version, 30.0, 20.0, rng)
    chip = [pad(version, "1", "roundrect", -0.825, 0, 0, (0.8, 0.95), rng),
            pad(version, "2", "roundrect", 0.825, 0, 0, (0.8, 0.95), rng)]
    lines += footprint(version, "Resistor_SMD:R_0603_1608Metric", "R1", x0 + 3, y0 + 3, 0,
                       chip, rng)
    bottom = [pad(version, "1", "rect", -0.825, 0, 0, (0.8, 0.95), rng, layers='"B.Cu"'),
              pad(version, "2", "rect", 0.825, 0, 0, (0.8, 0.95), rng, layers='"B.Cu"')]
    lines += footprint(version, "Resistor_SMD:R_0603_1608Metric", "R2", x0 + 6, y0 + 3, 0,
                       bottom, rng, layer="B.Cu")
    tht = [pad(version, str(k + 1), "oval", 0, 2.54 * k, 0, (1.7, 1.7), rng, kind="thru_hole",
               layers='"*.Cu" "*.Mask"', extra=" (drill 1)") for k in range(2)]
    lines += footprint(version, "Connector_PinHeader_2.54mm:PinHeader_1x02_P2.54mm_Vertical",
                       "J1", x0 + 20, y0 + 5, 0, tht, rng, attr="through_hole")
    qfn = [pad(version, str(k + 1), "roundrect", -2.4, -1.25 + 0.5 * k, 0, (0.8, 0.25), rng)
           for k in range(6)]
    lines += footprint(version, "Package_DFN_QFN:QFN-24-1EP_4x4mm_P0.5mm", "U2", x0 + 12,
                       y0 + 12, 0, qfn, rng)
    odd = [pad(version, "1", "rect", 0, 0, 0, (1, 1), rng)]
    lines += footprint(version, "MyLib:WeirdThing", "X1", x0 + 25, y0 + 15, 0, odd, rng)
    lines.append(")")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("version", [7, 9])
def test_unmodelled_footprints_are_listed_with_reasons(tmp_path, version):
    result = import_board(_write(tmp_path, _mixed_board(version)))
    assert [c.ref for c in result.board.components] == ["R1"]
    reasons = {s.ref: s.reason for s in result.skipped}
    assert set(reasons) == {"R2", "J1", "U2", "X1"}
    assert "bottom side" in reasons["R2"]
    assert "through-hole" in reasons["J1"]
    assert "bottom-terminated" in reasons["U2"]
    assert "matches no known package" in reasons["X1"]
    assert all(s.line and s.line > 1 for s in result.skipped)
    # R1: a roundrect pad of 0.8 x 0.95 mm with 25 % rounding keeps its centre and extent
    j = result.board.joint("R1.1")
    assert j.center_mm == pytest.approx((3 - 0.825, 17.0), abs=1e-9)
    assert np.ptp(j.polygon_mm, axis=0) == pytest.approx([0.8, 0.95], abs=1e-9)
    r = 0.25 * 0.8
    area = 0.8 * 0.95 - (4 - math.pi) * r * r
    x, y = j.polygon_mm[:, 0], j.polygon_mm[:, 1]
    poly_area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert poly_area == pytest.approx(area, rel=5e-3)


def test_pad_shapes_oval_circle_trapezoid_custom(tmp_path):
    rng = np.random.default_rng(2)
    x0, y0 = ORIGIN
    lines = header(9) + outline(9, 20.0, 10.0, rng)
    custom = (' (options (clearance outline) (anchor rect)) (primitives (gr_poly (pts (xy -0.5 -0.4) '
              '(xy 0.5 -0.4) (xy 0.5 0.4) (xy -0.2 0.4) (xy -0.5 0.1)) (width 0) (fill yes)))')
    pads = [pad(9, "1", "custom", -1.0, 0, 0, (0.2, 0.2), rng, extra=custom),
            pad(9, "2", "oval", 1.0, 0, 0, (1.0, 0.6), rng)]
    lines += footprint(9, "Capacitor_SMD:C_0805_2012Metric", "C9", x0 + 5, y0 + 5, 0, pads, rng)
    trap = [pad(9, "1", "trapezoid", -0.9, 0, 0, (1.0, 1.2), rng, extra=" (rect_delta 0 0.4)"),
            pad(9, "2", "circle", 0.9, 0, 0, (0.9, 0.9), rng)]
    lines += footprint(9, "Resistor_SMD:R_0805_2012Metric", "R9", x0 + 12, y0 + 5, 0, trap, rng)
    lines.append(")")
    board = import_board(_write(tmp_path, "\n".join(lines))).board
    c1 = board.joint("C9.1")  # the polygon itself, y flipped, at (-1, 0) of (5, 5)
    want = np.array([[-0.5, 0.4], [0.5, 0.4], [0.5, -0.4], [-0.2, -0.4], [-0.5, -0.1]]) + [4.0, 5.0]
    d = np.linalg.norm(c1.polygon_mm[:, None] - want[None], axis=2)
    assert d.min(axis=1).max() < 1e-9 and len(c1.polygon_mm) == 5
    c2 = board.joint("C9.2")
    assert np.ptp(c2.polygon_mm, axis=0) == pytest.approx([1.0, 0.6], abs=1e-9)
    assert c2.center_mm == pytest.approx((6.0, 5.0), abs=1e-9)
    r1 = board.joint("R9.1")  # trapezoid: a y delta of 0.4 mm makes the edges across y
    ys = r1.polygon_mm[:, 1]  # 1.0 ± 0.4 mm long (KiCad's rect_delta)
    low = np.ptp(r1.polygon_mm[np.isclose(ys, ys.min()), 0])
    high = np.ptp(r1.polygon_mm[np.isclose(ys, ys.max()), 0])
    assert sorted([low, high]) == pytest.approx([0.6, 1.4], abs=1e-9)
    assert np.ptp(ys) == pytest.approx(1.2, abs=1e-9)
    r2 = board.joint("R9.2")
    assert np.ptp(r2.polygon_mm, axis=0) == pytest.approx([0.9, 0.9], abs=1e-9)


def test_kicad_file_name_a_line_for_each_error(tmp_path):
    good = board_to_kicad(DEMO, 7).splitlines()
    # a ')' missing at the end: the file is truncated
    bad = _write(tmp_path, "\n".join(good[:-1]) + "\n", "trunc.kicad_pcb")
    with pytest.raises(InputError, match=r"trunc\.kicad_pcb:\d+: '\(' opened here is never closed"):
        import_board(bad)
    # a pad with a size that is not a number, on a known line
    k = next(i for i, ln in enumerate(good) if '(pad "2"' in ln and "R1" not in ln)
    broken = list(good)
    broken[k] = broken[k].replace("(size ", "(size x")
    with pytest.raises(InputError, match=rf"size\.kicad_pcb:{k + 1}: .*size x must be a number"):
        import_board(_write(tmp_path, "\n".join(broken), "size.kicad_pcb"))
    old = "\n".join(good).replace("(version 20221018)", "(version 20171130)")
    with pytest.raises(InputError, match=r"old\.kicad_pcb:1: board format 20171130 is older than KiCad 6"):
        import_board(_write(tmp_path, old, "old.kicad_pcb"))
    with pytest.raises(InputError, match=r"sch\.kicad_pcb:1: not a KiCad board file"):
        import_board(_write(tmp_path, "(kicad_sch (version 20230121))", "sch.kicad_pcb"))
    no_edge = "\n".join(ln for ln in good if "Edge.Cuts\") (t" not in ln and "gr_line" not in ln)
    with pytest.raises(InputError, match=r"edge\.kicad_pcb:1: no board outline"):
        import_board(_write(tmp_path, no_edge, "edge.kicad_pcb"))


def test_overlapping_pads_name_the_footprint_line(tmp_path):
    rng = np.random.default_rng(3)
    x0, y0 = ORIGIN
    lines = header(8) + outline(8, 10.0, 10.0, rng)
    for ref, x in (("R1", 4.0), ("R2", 5.2)):
        pads = [pad(8, "1", "rect", -0.825, 0, 0, (0.8, 0.95), rng),
                pad(8, "2", "rect", 0.825, 0, 0, (0.8, 0.95), rng)]
        lines += footprint(8, FOOTPRINT[("0603", "resistor")], ref, x0 + x, y0 + 5, 0, pads, rng)
    lines.append(")")
    text = "\n".join(lines)
    line_r1 = text.splitlines().index(next(ln for ln in text.splitlines()
                                           if ln.startswith("  (footprint"))) + 1
    with pytest.raises(InputError, match=rf"ovl\.kicad_pcb:{line_r1}: pads of joints R1\.2 and "
                                         r"R2\.1 overlap"):
        import_board(_write(tmp_path, text, "ovl.kicad_pcb"))


def test_read_kicad_pcb_reports_versions(tmp_path):
    for version, release in ((6, "6"), (8, "8"), (9, "9")):
        data, skipped, info = read_kicad_pcb(_write(tmp_path, board_to_kicad(DEMO, version)))
        assert info["kicad_version"] == release and not skipped
        assert len(data["components"]) == 6


def test_imported_board_simulates_and_inspects_clean(tmp_path):
    from smdinspect.inspect import InspectConfig, Verdict
    from smdinspect.inspect._inspect import inspect_surface

    from ..inspect._synthetic import truth_surface

    board = import_board(_write(tmp_path, board_to_kicad(DENSE, 9, shape="roundrect"))).board
    surface, labels, _ = truth_surface(board, "", seed=4, offset_mm=(0.8, -0.6), rotate_deg=2.0)
    result = inspect_surface(surface, board, InspectConfig(side_fillet_ratio=0.8))
    assert {j.verdict for j in result.joints} == {Verdict.OK}
    assert result.exit_code == 0 and len(result.joints) == 36


def test_cli_board_import(tmp_path, capsys):
    src = _write(tmp_path, _mixed_board(8), "mixed.kicad_pcb")
    out = tmp_path / "refs" / "mixed.json"
    assert main(["board", "import", str(src), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "imported 1 components (2 joints)" in text and "KiCad 8" in text
    assert "skipped 4:" in text and "J1 Connector_PinHeader" in text
    assert load_board(out).joint("R1.2")
    bad = _write(tmp_path, "(kicad_pcb (version 20240108)\n  (footprint \"x\"\n", "bad.kicad_pcb")
    assert main(["board", "import", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bad.kicad_pcb:2:" in err and len(err.strip().splitlines()) == 1


def test_cli_inspect_accepts_a_kicad_board(tmp_path, capsys):
    from smdinspect.sff import write_reconstruction

    from ..inspect._synthetic import truth_surface

    kicad = _write(tmp_path, board_to_kicad(DEMO, 8, shape="roundrect"), "demo.kicad_pcb")
    surface, _, _ = truth_surface(import_board(kicad).board, "", seed=6, offset_mm=(0.5, 0.3),
                                  rotate_deg=-1.5)
    rec = tmp_path / "rec"
    write_reconstruction(surface, rec, previews=False)
    cfg = tmp_path / "ideal.json"
    cfg.write_text('{"side_fillet_ratio": 0.8}')
    out = tmp_path / "rep"
    code = main(["inspect", str(rec), "--board", str(kicad), "--out", str(out),
                 "--inspect-config", str(cfg), "--no-html"])
    assert code == 0, capsys.readouterr()
    report = json.loads((out / "report.json").read_text())
    ids = {j["id"] for j in report["joints"]}
    assert ids == {j.id for j in load_board(DEMO).joints()}
