"""Centroid files (KiCad .pos, Altium and EasyEDA/JLC CSV) and package matching."""

import pytest

from smdinspect.cad import import_board, land_pattern, load_package_table, match_package
from smdinspect.cli import main
from smdinspect.errors import InputError
from smdinspect.inspect import load_board
from smdinspect.inspect._board import package_defaults

DEMO = "references/demo_board.json"


def _pos_rows(board, *, unit_mm=1.0):
    """(ref, value, footprint, x, y, rot) of each part in the file's conventions: IPC-7351
    zero orientation, so a gull-wing part's rotation is the model's + 90°."""
    names = {"0603": "R_0603_1608Metric", "0805": "R_0805_2012Metric",
             "1206": "C_1206_3216Metric", "0402": "C_0402_1005Metric",
             "SOIC-8": "SOIC-8_3.9x4.9mm_P1.27mm"}
    rows = [(f.id, "FID", "Fiducial_0.6mm_Mask1.2mm", f.x_mm / unit_mm, f.y_mm / unit_mm, 0.0)
            for f in board.fiducials]
    for c in board.components:
        rot = (c.rotation_deg + (90.0 if c.kind == "gullwing" else 0.0)) % 360
        rows.append((c.ref, "v", names[c.package], c.x_mm / unit_mm, c.y_mm / unit_mm, rot))
    return rows


def test_kicad_pos_reproduces_the_demo_board(tmp_path):
    board = load_board(DEMO)
    lines = ["### Footprint positions - created on 2024-05-01 ###",
             "## Unit = mm, Angle = deg.", "## Side : top",
             "# Ref     Val       Package                PosX       PosY       Rot  Side"]
    for ref, val, pkg, x, y, rot in _pos_rows(board):
        lines.append(f"{ref:8s} {val:8s} {pkg:28s} {x + 50:10.4f} {y - 80:10.4f} {rot:8.4f}  top")
    lines.append("J1       CONN     PinHeader_1x02_P2.54mm   60.0000  -70.0000   0.0000  top")
    lines.append("R9       10k      R_0603_1608Metric        55.0000  -75.0000   0.0000  bottom")
    lines.append("## End")
    path = tmp_path / "demo-top.pos"
    path.write_text("\n".join(lines) + "\n")
    # Pads come from the package table: the demo board uses the built-in land patterns.
    result = import_board(path, origin_mm=(50.0, -80.0), size_mm=(9.5, 9.5))
    got = result.board
    assert {s.ref: s.reason.split(" ")[0] for s in result.skipped} == {"J1": "not", "R9": "bottom"}
    assert [f.id for f in got.fiducials] == ["FID1", "FID2", "FID3"]
    for c0 in board.components:
        c1 = got.component(c0.ref)
        assert (c1.package, c1.kind, c1.style) == (c0.package, c0.kind, c0.style)
        assert (c1.x_mm, c1.y_mm) == pytest.approx((c0.x_mm, c0.y_mm), abs=1e-6)
        assert abs((c1.rotation_deg - c0.rotation_deg + 180) % 360 - 180) < 1e-9
        for j0, j1 in zip(c0.joints, c1.joints):
            assert j1.id == j0.id
            assert j1.center_mm == pytest.approx(j0.center_mm, abs=1e-6)


def test_kicad_pos_in_inches_and_default_extent(tmp_path):
    board = load_board(DEMO)
    lines = ["## Unit = inches, Angle = deg.", "# Ref Val Package PosX PosY Rot Side"]
    for ref, val, pkg, x, y, rot in _pos_rows(board, unit_mm=25.4):
        lines.append(f"{ref} {val} {pkg} {x:.8f} {y:.8f} {rot:.4f} top")
    path = tmp_path / "inch.pos"
    path.write_text("\n".join(lines) + "\n")
    got = import_board(path, margin_mm=0.5).board
    # no outline in a centroid file: the extent of pads and fiducials plus the margin
    xs = [p for j in got.joints() for p in j.polygon_mm[:, 0]]
    xs += [f.x_mm - f.diameter_mm / 2 for f in got.fiducials]
    ys = [p for j in got.joints() for p in j.polygon_mm[:, 1]]
    ys += [f.y_mm + f.diameter_mm / 2 for f in got.fiducials]
    assert min(xs) == pytest.approx(0.5, abs=1e-6)
    assert max(ys) == pytest.approx(got.size_mm[1] - 0.5, abs=1e-6)
    c0, c1 = board.component("U1"), got.component("U1")
    shift = (c1.x_mm - c0.x_mm, c1.y_mm - c0.y_mm)
    for c in board.components:
        g = got.component(c.ref)
        assert (g.x_mm - c.x_mm, g.y_mm - c.y_mm) == pytest.approx(shift, abs=1e-6)


def test_jlc_and_altium_csv(tmp_path):
    jlc = tmp_path / "cpl.csv"
    jlc.write_text("Designator,Footprint,Mid X,Mid Y,Ref X,Ref Y,Pad X,Pad Y,Layer,Rotation,Comment\n"
                   "R1,R0603,10.0mm,5.0mm,0,0,0,0,T,90,10k\n"
                   "C1,C0805,14mm,5mm,0,0,0,0,T,0,1u\n"
                   "U1,SOIC-8_3.9x4.9mm_P1.27mm,20mm,8mm,0,0,0,0,B,0,x\n")
    r = import_board(jlc)
    assert [c.ref for c in r.board.components] == ["R1", "C1"]
    assert r.board.component("C1").style == "capacitor"
    assert r.board.component("R1").rotation_deg == pytest.approx(90)
    assert [s.ref for s in r.skipped] == ["U1"]
    altium = tmp_path / "pnp.csv"
    altium.write_text('Altium Designer Pick and Place Locations\n\n'
                      '"Designator","Comment","Layer","Footprint","Center-X(mil)","Center-Y(mil)",'
                      '"Rotation","Description"\n'
                      '"U1","x","TopLayer","SOIC127P600X175-8N","500","400","0","d"\n'
                      '"R5","x","TopLayer","RESC1608X55N","200","400","180","d"\n')
    b = import_board(altium).board
    u1 = b.component("U1")
    assert u1.body_height_mm == pytest.approx(1.75) and u1.rotation_deg == pytest.approx(-90)
    assert b.component("R5").body_height_mm == pytest.approx(0.55)
    d = (u1.x_mm - b.component("R5").x_mm)
    assert d == pytest.approx(300 * 0.0254, abs=1e-9)


def test_package_table(tmp_path):
    table = tmp_path / "packages.toml"
    table.write_text('''
[package."MYSOIC*"]
package = "SOIC-8_3.9x4.9mm_P1.27mm"
[package."CHIPX"]
kind = "chip"
style = "capacitor"
body = {length_mm = 2.0, width_mm = 1.25, height_mm = 1.0, standoff_mm = 0.03, termination_length_mm = 0.4}
pad = {length_mm = 1.0, width_mm = 1.4, center_mm = 1.0}
[package."TP*"]
skip = "test point"
''')
    pos = tmp_path / "p.csv"
    pos.write_text("Ref,Val,Package,PosX,PosY,Rot,Side\n"
                   "U7,x,MYSOIC-A,10,10,90,top\nC3,x,CHIPX,3,3,0,top\nTP1,x,TP_1mm,1,1,0,top\n")
    r = import_board(pos, packages=table)
    assert r.board.component("U7").package == "SOIC-8"
    assert r.board.component("U7").rotation_deg == pytest.approx(0.0)
    c3 = r.board.component("C3")
    assert c3.body_height_mm == 1.0 and r.board.joint("C3.2").center_mm[0] - c3.x_mm == 1.0
    assert [s.reason for s in r.skipped] == ["skipped by the package table: test point"]
    bad = tmp_path / "bad.toml"
    bad.write_text('[package."X"]\nkind = "chip"\nbodyy = 1\n')
    with pytest.raises(InputError, match=r"bad\.toml: \[package\.'X'\]: unknown key\(s\) bodyy"):
        load_package_table(bad)


def test_centroid_errors_name_file_and_line(tmp_path):
    p = tmp_path / "e.csv"
    p.write_text("Ref,Val,Package,PosX,PosY,Rot,Side\nR1,x,R0603,1,1,0,top\nR2,x,R0603,abc,1,0,top\n")
    with pytest.raises(InputError, match=r"e\.csv:3: column PosX: 'abc' is not a number"):
        import_board(p)
    p.write_text("foo,bar\n1,2\n")
    with pytest.raises(InputError, match=r"e\.csv:1: not a centroid file"):
        import_board(p)
    p.write_text("Ref,Val,Package,PosX,PosY,Rot,Side\nR1,x,R0603,1,1,0,top\nR1,x,R0603,5,1,0,top\n")
    with pytest.raises(InputError, match=r"e\.csv:3: duplicate reference 'R1'"):
        import_board(p)


@pytest.mark.parametrize("name, package, kind, height", [
    ("Resistor_SMD:R_0402_1005Metric", "0402", "chip", 0.35),
    ("Capacitor_SMD:C_1206_3216Metric_Pad1.33x1.80mm_HandSolder", "1206", "chip", 1.15),
    ("R_1210_3225Metric", "1210", "chip", 0.55),
    ("Package_SO:SOIC-16_3.9x9.9mm_P1.27mm", "SOIC-16", "gullwing", 1.5),
    ("Package_SO:TSSOP-20_4.4x6.5mm_P0.65mm", "TSSOP-20", "gullwing", 1.05),
    ("Package_QFP:LQFP-48_7x7mm_P0.5mm", "LQFP-48", "gullwing", 1.5),
    ("Package_TO_SOT_SMD:SOT-23", "SOT-23", "gullwing", 1.0),
    ("SOT-23-5", "SOT-23-5", "gullwing", 1.1),
])
def test_ipc_names(name, package, kind, height):
    m = match_package(name)
    assert (m.package, m.kind) == (package, kind)
    assert m.body["height_mm"] == pytest.approx(height)


@pytest.mark.parametrize("name, reason", [
    ("Package_DFN_QFN:QFN-32-1EP_5x5mm_P0.5mm", "bottom-terminated"),
    ("Package_BGA:BGA-64_9x9mm", "bottom-terminated"),
    ("Package_SO:HTSSOP-16-1EP_4.4x5mm_P0.65mm", "exposed"),
    ("Package_TO_SOT_SMD:SOT-223-3_TabPin2", "tab"),
    ("Connector_USB:USB_C_Receptacle", "no joint model"),
    ("Unknown_Thing", "matches no known package"),
])
def test_unmodelled_names_give_reasons(name, reason):
    assert reason in match_package(name)


def test_land_patterns_are_valid_boards(tmp_path):
    # Every built-in gull-wing family makes a board the loader accepts, pins counted CCW.
    from smdinspect.inspect._board import board_from_dict

    comps = []
    for k, name in enumerate(["SOIC-14_3.9x8.7mm_P1.27mm", "TSSOP-16_4.4x5mm_P0.65mm",
                              "LQFP-64_10x10mm_P0.5mm", "SOT-23", "SOT-23-5", "SOT-23-6",
                              "R_2512_6332Metric"]):
        m = match_package(name)
        c = {"ref": f"U{k}", "package": m.package, "kind": m.kind, "style": m.style,
             "x_mm": 8.0 + 16.0 * k, "y_mm": 8.0, "rotation_deg": 0.0, "body": m.body,
             "pads": land_pattern(m)}
        if m.lead:
            c["lead"] = m.lead
        comps.append(c)
    board = board_from_dict({"schema": "smdinspect-board", "version": 1, "name": "t",
                             "units": "mm", "size_mm": [120.0, 16.0], "thickness_mm": 1.6,
                             "components": comps})
    q = board.component("U2")
    assert len(q.joints) == 64
    assert q.to_local([q.joints[0].center_mm])[0][1] < 0          # pin 1 at the bottom
    assert q.to_local([q.joints[16].center_mm])[0][0] > 0          # pin 17: right side
    soic = match_package("SOIC-8_3.9x4.9mm_P1.27mm")
    assert land_pattern(soic) == package_defaults("SOIC-8")["pads"]


def test_cli_centroid_import(tmp_path, capsys):
    p = tmp_path / "c.csv"
    p.write_text("Ref,Val,Package,PosX,PosY,Rot,Side\nR1,x,R0603,3,3,0,top\n")
    out = tmp_path / "b.json"
    assert main(["board", "import", str(p), "--out", str(out), "--size-mm", "6,6",
                 "--origin-mm", "0,0"]) == 0
    assert "imported 1 components (2 joints)" in capsys.readouterr().out
    assert load_board(out).size_mm == (6.0, 6.0)
