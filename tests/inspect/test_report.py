"""report.html: its pictures (overview labels, colour bars, crops, profiles) and escaping.

The page is checked as text here; test_report_browser.py renders it in Chromium.
"""

import html
import re
from dataclasses import replace
from html.parser import HTMLParser

import numpy as np
import pytest

from smdinspect.errors import BoardNotLocatedError
from smdinspect.inspect import InspectConfig, Verdict, load_board
from smdinspect.inspect._inspect import inspect_surface
from smdinspect.inspect._report import not_located_html, report_html, write_reports
from smdinspect.inspect._report_figures import (
    PadMark,
    colour_bar_svg,
    joint_profile,
    nice_length,
    nice_ticks,
    place_labels,
)
from smdinspect.pipeline import inspect_stack

from ._synthetic import ALL_DEFECTS, DEMO, DENSE, truth_surface

IDEAL = InspectConfig(side_fillet_ratio=0.8)


@pytest.fixture(scope="module")
def inspected():
    """Demo board, every defect class, and a textureless box that leaves U1.3 unreliable."""
    surface, _, board = truth_surface(DEMO, ALL_DEFECTS, seed=3, offset_mm=(0.8, -0.5),
                                      rotate_deg=2.0, dead_box=("U1.3", 0.5, 1.2))
    result = inspect_surface(surface, board, IDEAL)
    assert result.defects and result.unreliable  # what the tests below look at
    return result


class Page(HTMLParser):
    """Elements of a page: (tag, attrs, text inside), and the overview's joint labels."""

    def __init__(self, text: str):
        super().__init__()
        self.stack, self.elements, self.labels = [], [], []
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        el = [tag, dict(attrs), ""]
        self.elements.append(el)
        if tag not in ("meta", "br", "img"):
            self.stack.append(el)

    def handle_startendtag(self, tag, attrs):  # <rect .../>: no content
        self.elements.append([tag, dict(attrs), ""])

    def handle_endtag(self, tag):
        while self.stack:
            el = self.stack.pop()
            if el[0] == tag:
                break

    def handle_data(self, data):
        for el in self.stack:
            el[2] += data
        if self.stack and self.stack[-1][0] == "text" and any(
                e[0] == "a" and "jl" in e[1].get("class", "") for e in self.stack):
            self.labels.append(data)

    def find(self, tag, **attrs):
        return [e for e in self.elements if e[0] == tag and all(
            v in e[1].get(k.replace("_", "-"), "").split() if k == "class_" or k == "class"
            else e[1].get(k.replace("_", "-")) == v for k, v in attrs.items())]


def test_every_joint_is_labelled_on_the_overview_in_its_verdict_colour(inspected):
    page = Page(report_html(inspected))
    assert sorted(page.labels) == sorted(j.id for j in inspected.joints)
    chips = {e[1]["data-joint"]: e for e in page.elements if e[0] == "a"
             and e[1].get("class") == "jl"}
    rects = [e for e in page.elements if e[0] == "rect" and e[1].get("rx") == "3"]
    assert len(rects) == len(inspected.joints)
    for j, rect in zip(_label_order(inspected), rects):
        assert rect[1]["fill"] == "rgb({},{},{})".format(*_colour(j)), j.id
        assert chips[j.id][1]["href"].startswith("#")


def _label_order(result):
    # Labels are drawn defects first, then unreliable joints, then the rest.
    return sorted(result.joints, key=lambda j: (0 if j.is_defect else
                                               1 if j.verdict is Verdict.UNRELIABLE else 2,
                                               result.joints.index(j)))


def _colour(j):
    from smdinspect.inspect._report import COLOURS

    return COLOURS[j.verdict.value]


def test_labels_link_to_existing_anchors(inspected):
    text = report_html(inspected)
    page = Page(text)
    ids = {e[1]["id"] for e in page.elements if "id" in e[1]}
    for a in page.find("a", **{"class": "jl"}):
        assert a[1]["href"][1:] in ids


def test_defective_and_unreliable_joints_get_a_card_with_crops_bar_and_profile(inspected):
    page = Page(report_html(inspected))
    cards = {e[1]["data-joint"]: e for e in page.elements if e[0] == "div"
             and e[1].get("class") == "card"}
    want = {j.id for j in inspected.joints if j.verdict is not Verdict.OK}
    assert set(cards) == want
    for j in inspected.joints:
        if j.id not in want:
            continue
        card = cards[j.id]
        assert j.reason in card[2] and j.verdict.value in card[2]
        assert "image" in card[2] and "height" in card[2]          # labelled panels
        assert re.search(r"\d+ µm|\d+(\.\d+)? mm", card[2])       # a scale bar's label
    n_cards = len(want)
    assert len(page.find("svg", **{"class": "crop"})) == 2 * n_cards
    assert len(page.find("svg", **{"class": "profile"})) == n_cards
    # One colour bar per crop pair and one on the board's height map.
    assert len(page.find("svg", **{"class": "colourbar"})) == n_cards + 1


def test_crop_colour_bars_use_each_joints_own_height_range(inspected):
    text = report_html(inspected)
    ranges = re.findall(r"this joint's own range, (-?[\d.]+) … (-?[\d.]+) mm", text)
    assert len(ranges) == len(inspected.defects) + len(inspected.unreliable)
    board = re.search(r"Colour scale (-?[\d.]+) … (-?[\d.]+) mm", text)
    board_hi = float(board.group(2))
    his = [float(hi) for _, hi in ranges]
    assert len(set(his)) > 1              # not one range for all
    assert min(his) < 0.8 * board_hi      # a fillet is not scaled to the IC body's top


def test_profile_draws_the_acceptance_band(inspected):
    page = Page(report_html(inspected))
    for svg in page.find("svg", **{"class": "profile"}):
        assert "band" in svg[2] and "height mm" in svg[2]
    titles = [e[2] for e in page.elements if e[0] == "title" and e[2].startswith("acceptance band")]
    bands = {f"{j.expected_min_mm:.3f}–{j.expected_max_mm:.3f}" for j in inspected.joints
             if j.verdict is not Verdict.OK}
    assert bands <= {t.split("band ")[1].split(" mm")[0] for t in titles}


def test_3d_view_is_embedded(inspected):
    rgb = np.zeros((30, 40, 3), np.uint8)
    rgb[:, :20] = (200, 10, 10)
    text = report_html(inspected, view3d=rgb)
    assert "class='view3d'" in text and "data:image/jpeg;base64," in text
    text = report_html(inspected, view3d=None, view3d_note="VTK is missing <here>")
    assert "3D view not available: VTK is missing &lt;here&gt;" in text


def test_write_reports_renders_the_3d_view_with_the_sff_renderer(inspected, tmp_path):
    paths = write_reports(inspected, tmp_path)
    text = paths["report.html"].read_text()
    assert "class='view3d'" in text, re.findall(r"3D view not available[^<]*", text)


def test_all_text_is_escaped(inspected):
    evil = "<script>alert('x')</script>&\"'"
    joints = list(inspected.joints)
    k = next(i for i, j in enumerate(joints) if j.is_defect)
    joints[k] = replace(joints[k], id=evil, reason=evil, component=evil)
    result = replace(inspected, board=evil, board_source=evil, joints=joints)
    text = report_html(result, source=evil, view3d_note=evil)
    assert "<script>alert" not in text
    assert text.count("<script>") == 1  # the page's own sorting script
    assert "&lt;script&gt;alert(&#x27;x&#x27;)&lt;/script&gt;&amp;&quot;&#x27;" in text
    page = Page(text)
    assert evil in page.labels and evil in [e[1].get("data-joint") for e in page.elements]


def test_not_located_page_says_why_and_shows_the_measurement(tmp_path):
    surface, _, _ = truth_surface(DEMO, "", seed=6)
    with pytest.raises(BoardNotLocatedError) as info:
        inspect_stack(surface, DENSE, tmp_path / "out", source="<b>stack</b>")
    out = tmp_path / "out"
    assert (out / "report.json").is_file()
    text = (out / "report.html").read_text()
    assert "NOT LOCATED" in text
    assert html.escape(str(info.value)) in text
    assert "&lt;b&gt;stack&lt;/b&gt;" in text
    page = Page(text)
    assert page.find("svg", **{"class": "overview"}) and page.find("svg", **{"class": "colourbar"})
    # The rejected placement is drawn: every pad of the wrong board.
    dense = load_board(DENSE)
    assert "best placement found (rejected)" in text
    assert len(page.find("polygon")) == len(dense.joints()) + 1


def test_not_located_page_without_a_registration():
    board = load_board(DEMO)
    text = not_located_html(board, None, reason="only 1.0% of the surface is reliable")
    assert "only 1.0% of the surface is reliable" in text and "not attempted" in text


# ----------------------------------------------------------------------------- figures


def test_joint_profile_follows_a_known_ramp():
    rows, cols = np.indices((60, 80))
    height = (0.01 * cols + 0.002 * rows).astype(np.float32)  # mm per pixel
    reliable = np.ones(height.shape, bool)
    reliable[:, 40:43] = False  # an unmeasured band across the line
    s, z = joint_profile(height, reliable, (10, 30), (70, 30), pixel_size_mm=0.02)
    assert s[0] == 0 and s[-1] == pytest.approx(60 * 0.02)
    col = 10 + s / 0.02
    ok = np.isfinite(z)
    assert not ok[np.abs(col - 41) <= 0.6].any()
    np.testing.assert_allclose(z[ok], 0.01 * np.round(col[ok]) + 0.002 * 30, atol=1e-6)
    # A diagonal line: heights rise by the gradient along it.
    s, z = joint_profile(height, np.ones_like(reliable), (10, 10), (40, 50), pixel_size_mm=0.02)
    assert len(s) == 51 and np.all(np.diff(z) >= -0.0105)
    assert z[-1] - z[0] == pytest.approx(0.01 * 30 + 0.002 * 40, abs=0.011)


def test_nice_ticks_and_lengths():
    assert nice_ticks(0.0, 1.0, 6) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert nice_ticks(-0.013, 0.572, 5) == [0.0, 0.2, 0.4]
    assert nice_ticks(0.1, 0.1) == [0.1]
    assert nice_length(0.7) == 0.5 and nice_length(0.19) == 0.1 and nice_length(3.0) == 2.0


def test_colour_bar_ticks_and_band():
    svg = colour_bar_svg(0.0, 0.6, height_px=200, band=(0.13, 0.57), uid="x")
    ticks = re.findall(r"class='tick'>([^<]+)<", svg)
    assert ticks[0] == "0.0" and ticks[-1] == "0.6"
    assert "acceptance band 0.130–0.570 mm" in svg and "url(#x)" in svg


def test_labels_do_not_overlap_each_other_and_stay_near_their_pad():
    rng = np.random.default_rng(4)
    marks = []
    for r in range(4):          # a 4 x 6 grid of small pads 40 px apart
        for c in range(6):
            x, y = 60 + 40 * c, 60 + 40 * r
            poly = np.array([[x - 6, y - 9], [x + 6, y - 9], [x + 6, y + 9], [x - 6, y + 9]], float)
            marks.append(PadMark(poly, f"U{r}.{c + 1}", (46, 160, 67), "#", "", (0.0, -1.0)))
    rng.shuffle(marks)
    boxes = place_labels(marks, size=(400, 300))
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            w = min(a[2], b[2]) - max(a[0], b[0])
            h = min(a[3], b[3]) - max(a[1], b[1])
            assert w <= 0 or h <= 0, (a, b)
        assert 0 <= a[0] and a[2] <= 400 and 0 <= a[1] and a[3] <= 300
    for m, (x0, y0, x1, y1) in zip(marks, boxes):
        cx, cy = m.polygon.mean(axis=0)
        assert np.hypot((x0 + x1) / 2 - cx, (y0 + y1) / 2 - cy) < 45


def test_joints_csv_cells_cannot_run_as_spreadsheet_formulas(inspected):
    import csv
    import io

    from smdinspect.inspect._report import joints_csv

    joints = list(inspected.joints)
    joints[0] = replace(joints[0], id="=HYPERLINK(\"x\")", component="+R1", reason="@SUM(A1)")
    rows = list(csv.DictReader(io.StringIO(joints_csv(replace(inspected, joints=joints)))))
    assert rows[0]["id"] == "'=HYPERLINK(\"x\")" and rows[0]["component"] == "'+R1"
    assert rows[0]["reason"] == "'@SUM(A1)"
    # numbers stay numbers, negative ones included
    assert all(not r["measured_max_mm"].startswith("'") for r in rows)


def test_board_height_map_spends_its_colours_on_the_joints(inspected):
    """The demo board's IC body stands 1.5 mm high, its fillets 0.1-0.3 mm: the board map's
    scale stops at the highest nominal joint height (taller parts clipped)."""
    text = report_html(inspected)
    board = re.search(r"Colour scale (-?[\d.]+) … (-?[\d.]+) mm \(([^)]*)\)", text)
    top = max(j.expected_nominal_mm for j in inspected.joints)
    assert float(board.group(2)) == pytest.approx(top, abs=6e-4)
    assert "highest nominal joint height" in board.group(3)
