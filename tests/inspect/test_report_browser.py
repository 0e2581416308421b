"""report.html rendered in a real headless browser (Chromium, installed by scripts/setup.sh).

Chromium draws the page (the screenshot is not blank and shows the verdict colours of the
overview's labels) and its DOM holds every joint id; a board that could not be located
still gets a report.html, written inside the CLI's atomic output-folder swap.
"""

import shutil
import subprocess
from html.parser import HTMLParser

import numpy as np
import pytest

from smdinspect.cli import main
from smdinspect.inspect import Verdict
from smdinspect.inspect._inspect import inspect_surface
from smdinspect.inspect._report import COLOURS, write_reports
from smdinspect.sff import write_reconstruction

from ._synthetic import ALL_DEFECTS, DEMO, DENSE, truth_surface
from .test_report import IDEAL

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome"))
                 if p), None)
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium: run scripts/setup.sh")


def chromium(tmp_path, *args: str) -> str:
    """Run headless Chromium with ``args``; returns its standard output."""
    profile = tmp_path / "chromium-profile"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           "--no-first-run", f"--user-data-dir={profile}", *args]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def screenshot(tmp_path, page, *, size=(1400, 2600)) -> np.ndarray:
    import cv2

    png = tmp_path / "shot.png"
    chromium(tmp_path, f"--window-size={size[0]},{size[1]}", f"--screenshot={png}", page.as_uri())
    img = cv2.imread(str(png), cv2.IMREAD_COLOR)
    assert img is not None, "Chromium wrote no screenshot"
    return img[:, :, ::-1]


def assert_not_blank(rgb: np.ndarray) -> None:
    grey = rgb.mean(axis=2)
    assert grey.std() > 20, "the screenshot is (nearly) one colour"
    assert (grey < 235).mean() > 0.15, "the screenshot is mostly empty"
    assert len(np.unique(rgb.reshape(-1, 3)[::7], axis=0)) > 500, "no pictures were drawn"


def has_colour(rgb: np.ndarray, colour, tol: int = 3) -> bool:
    return bool((np.abs(rgb.astype(int) - np.array(colour)).max(axis=2) <= tol).sum() >= 20)


class Dom(HTMLParser):
    """Collects the overview labels' texts, the joint ids of the cards, and element ids."""

    def __init__(self, text: str):
        super().__init__()
        self.in_label, self.in_text = 0, False
        self.labels, self.cards, self.ids = [], [], set()
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            self.ids.add(a["id"])
        self.in_text = tag == "text"
        if tag == "a" and "jl" in (a.get("class") or "").split():
            self.in_label += 1
        if tag == "div" and a.get("class") == "card":
            self.cards.append(a.get("data-joint"))

    def handle_endtag(self, tag):
        self.in_text = False
        if tag == "a" and self.in_label:
            self.in_label -= 1

    def handle_data(self, data):
        if self.in_label and self.in_text:  # the label's <text>, not its <title>
            self.labels.append(data)


@pytest.fixture(scope="module")
def board_report(tmp_path_factory):
    surface, _, board = truth_surface(DEMO, ALL_DEFECTS, seed=3, offset_mm=(0.8, -0.5),
                                      rotate_deg=2.0, dead_box=("U1.3", 0.5, 1.2))
    result = inspect_surface(surface, board, IDEAL)
    out = tmp_path_factory.mktemp("report")
    write_reports(result, out)
    return result, out / "report.html"


def test_the_report_renders_and_is_not_blank(board_report, tmp_path):
    result, page = board_report
    rgb = screenshot(tmp_path, page)
    assert_not_blank(rgb)
    # The overview's labels are drawn: every verdict present shows its colour.
    for v in {j.verdict.value for j in result.joints}:
        assert has_colour(rgb, COLOURS[v]), v


def test_every_joint_id_is_in_the_dom(board_report, tmp_path):
    result, page = board_report
    dom = Dom(chromium(tmp_path, "--virtual-time-budget=2000", "--dump-dom", page.as_uri()))
    assert sorted(dom.labels) == sorted(j.id for j in result.joints)
    looked_at = [j.id for j in result.joints if j.is_defect] + \
        [j.id for j in result.joints if j.verdict is Verdict.UNRELIABLE]
    assert dom.cards == looked_at
    assert {f"row-{k}" for k in range(len(result.joints))} <= dom.ids


MEASURE_LABELS = """<script>
var out = [];
document.querySelectorAll('svg.overview a.jl').forEach(function(a){
  var t = a.querySelector('text').getBoundingClientRect();
  var r = a.querySelector('rect').getBoundingClientRect();
  out.push([a.dataset.joint, t.height, r.left, r.top, r.right, r.bottom].join(' '));
});
var pre = document.createElement('pre'); pre.id = 'measured';
pre.textContent = out.join('\\n'); document.body.appendChild(pre);
</script>"""


def test_labels_are_readable_at_the_default_zoom(board_report, tmp_path):
    """Chromium lays the labels out at >= 10 CSS px text, without covering each other."""
    result, page = board_report
    probe = tmp_path / "probe.html"
    probe.write_text(page.read_text().replace("</body>", MEASURE_LABELS + "</body>"))
    dom = chromium(tmp_path, "--window-size=1366,900", "--virtual-time-budget=3000",
                   "--dump-dom", probe.as_uri())
    text = dom.split('id="measured">', 1)[1].split("</pre>", 1)[0]
    rows = [line.split(" ") for line in text.strip().splitlines()]
    assert sorted(r[0] for r in rows) == sorted(j.id for j in result.joints)
    boxes = []
    for _, text_h, *box in rows:
        assert float(text_h) >= 10, rows
        boxes.append([float(v) for v in box])
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            overlap_w = min(a[2], b[2]) - max(a[0], b[0])
            overlap_h = min(a[3], b[3]) - max(a[1], b[1])
            assert overlap_w <= 0.5 or overlap_h <= 0.5, (a, b)


def test_a_board_not_located_gets_a_report_html_through_the_cli(tmp_path, capsys):
    surface, _, _ = truth_surface(DEMO, "", seed=6)
    recon = tmp_path / "recon"
    write_reconstruction(surface, recon)
    out = tmp_path / "out"
    # A first, located run fills --out; the failed one replaces all of it.
    assert main(["-q", "inspect", str(recon), "--board", DEMO, "--out", str(out)]) in (0, 1)
    assert "NOT LOCATED" not in (out / "report.html").read_text()
    assert main(["-q", "inspect", str(recon), "--board", DENSE, "--out", str(out)]) == 3
    assert "not located" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "recon"]  # no partial folder
    assert (out / "report.json").is_file() and not (out / "joints.csv").exists()
    page = out / "report.html"
    assert_not_blank(screenshot(tmp_path, page, size=(1400, 1300)))
    dom = chromium(tmp_path, "--dump-dom", page.as_uri())
    assert "NOT LOCATED" in dom and "dense_board" in dom and "id=\"reason\"" in dom
    assert "fitness" in dom.split("id=\"reason\"", 1)[1].split("</p>", 1)[0]
