"""The offscreen 3D view (VTK through EGL/OSMesa): known scenes land where expected."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from smdinspect.errors import InputError
from smdinspect.sff import Surface, render_view3d_png
from smdinspect.sff._view3d import _build_scene, render_height_field

SIZE = (400, 300)  # small renders keep the tests fast
RED = (220, 30, 30)
GREEN = (60, 140, 80)


def _box_scene(row: int, col: int, *, n: int = 200, side: int = 30):
    """A flat green plane (10 x 10 mm) with one red 2 mm box centred at (row, col)."""
    height = np.zeros((n, n), np.float32)
    rgb = np.empty((n, n, 3), np.uint8)
    rgb[:] = GREEN
    r0, c0 = row - side // 2, col - side // 2
    height[r0:r0 + side, c0:c0 + side] = 2.0
    rgb[r0:r0 + side, c0:c0 + side] = RED
    return height, rgb


def _red_centroid(image: np.ndarray) -> tuple[float, float]:
    r, g, b = (image[..., i].astype(int) for i in range(3))
    mask = (r > 120) & (r > 2 * g) & (r > 2 * b)
    assert mask.sum() > 200, "the red box is not in the picture"
    rows, cols = np.nonzero(mask)
    return rows.mean(), cols.mean()


def _render(height, rgb, valid=None, **kw):
    kw.setdefault("pixel_size_mm", 0.05)
    kw.setdefault("size_px", SIZE)
    return render_height_field(height, rgb, valid, **kw)


@pytest.fixture(scope="module")
def cone():
    n = 120
    yy, xx = np.mgrid[0:n, 0:n]
    height = (1.5 * np.clip(1 - np.hypot(xx - n / 2, yy - n / 2) / (n / 3), 0, 1)).astype(np.float32)
    rgb = (np.random.default_rng(0).random((n, n, 3)) * 255).astype(np.uint8)
    return height, rgb


def test_render_is_not_blank(cone):
    image = _render(*cone)
    assert image.shape == (SIZE[1], SIZE[0], 3) and image.dtype == np.uint8
    colours = np.unique(image.reshape(-1, 3), axis=0)
    assert len(colours) > 2000
    saturated = (image.max(axis=2).astype(int) - image.min(axis=2)) > 40  # the texture
    assert saturated.mean() > 0.2


def test_box_moves_the_expected_way():
    left = _red_centroid(_render(*_box_scene(100, 50), z_exaggeration=1))
    right = _red_centroid(_render(*_box_scene(100, 150), z_exaggeration=1))
    back = _red_centroid(_render(*_box_scene(40, 100), z_exaggeration=1))
    front = _red_centroid(_render(*_box_scene(160, 100), z_exaggeration=1))
    assert right[1] - left[1] > 0.25 * SIZE[0]  # +x (columns) goes right in the picture
    assert front[0] - back[0] > 0.1 * SIZE[1]  # the image's bottom edge is nearest
    # moving along x keeps the depth, but for the 20° azimuth (its rows move by
    # ~sin 20°·sin 55° of the shift: 31 px here)
    assert abs(left[0] - right[0]) < 0.15 * SIZE[1]


def test_taller_box_reaches_higher_in_the_picture():
    low_h, rgb = _box_scene(100, 100)
    tall_h = low_h * 2

    def top_row(image):
        r, g, b = (image[..., i].astype(int) for i in range(3))
        rows = np.nonzero(((r > 120) & (r > 2 * g) & (r > 2 * b)).any(axis=1))[0]
        return rows.min()
    assert top_row(_render(tall_h, rgb, z_exaggeration=1)) < top_row(_render(low_h, rgb, z_exaggeration=1))


def test_render_is_deterministic(cone):
    assert np.array_equal(_render(*cone), _render(*cone))


def test_pixel_size_none_works(cone):
    image = _render(*cone, pixel_size_mm=None)
    assert image.shape == (SIZE[1], SIZE[0], 3)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 2000


def test_invalid_pixels_are_grey():
    height = np.zeros((100, 100), np.float32)
    rgb = np.empty((100, 100, 3), np.uint8)
    rgb[:] = RED
    valid = np.ones((100, 100), bool)
    valid[:, :50] = False
    height[:, :50] = np.nan  # not finite: no valid height either

    def neutral_share(image):
        i = image.astype(int)
        neutral = (np.ptp(i, axis=2) < 12) & (i.mean(axis=2) > 60) & (i.mean(axis=2) < 200)
        return neutral.mean()

    all_red = _render(np.zeros_like(height), rgb)
    half_grey = _render(height, rgb, valid)
    assert neutral_share(half_grey) > neutral_share(all_red) + 0.1


def test_out_path_writes_the_png_atomically(tmp_path, cone):
    out = tmp_path / "view3d.png"
    image = _render(*cone, out_path=out)
    back = cv2.cvtColor(cv2.imread(str(out), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(back, image)
    assert [p.name for p in tmp_path.iterdir()] == ["view3d.png"]


def test_large_input_is_decimated():
    height, rgb = _box_scene(500, 500, n=1000, side=150)
    scene = _build_scene(height, rgb, np.ones(height.shape, bool), None, pixel_size_mm=0.01,
                         z_exaggeration=None, max_side=384)
    assert max(scene.z_mm.shape) <= 385
    image = _render(height, rgb, pixel_size_mm=0.01)
    _red_centroid(image)


def test_auto_exaggeration_shows_small_relief():
    height, rgb = _box_scene(100, 100)
    height *= 0.05  # 0.1 mm on a 10 mm field
    scene = _build_scene(height, rgb, np.ones(height.shape, bool), None, pixel_size_mm=0.05,
                         z_exaggeration=None, max_side=384)
    assert 10 <= scene.ex <= 30
    tall = _build_scene(height * 100, rgb, np.ones(height.shape, bool), None, pixel_size_mm=0.05,
                        z_exaggeration=None, max_side=384)
    assert tall.ex == 1  # never squashed


def test_render_view3d_png_from_a_surface(tmp_path, cone):
    height, rgb = cone
    shape = height.shape
    reliable = np.ones(shape, bool)
    reliable[:10] = False
    surface = Surface(height_mm=height, confidence=reliable.astype(np.float32), reliable=reliable,
                      f_peak=np.ones(shape, np.float32), sigma_mm=np.ones(shape, np.float32),
                      reliability_db=np.full(shape, 30, np.float32), aif=rgb, pixel_size_mm=0.03,
                      z_mm=np.linspace(0, 2, 5))
    path = render_view3d_png(surface, tmp_path / "view3d.png", size_px=SIZE)
    image = cv2.imread(str(path))
    assert image.shape == (SIZE[1], SIZE[0], 3)


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (dict(height_mm=np.zeros(10, np.float32)), "height_mm"),
        (dict(height_mm=np.zeros((20, 20), bool)), "height_mm"),
        (dict(rgb=np.zeros((20, 21, 3), np.uint8)), "rgb"),
        (dict(rgb=np.zeros((20, 20, 3), np.int8)), "rgb"),
        (dict(valid=np.ones((21, 20), bool)), "valid"),
        (dict(valid=np.ones((20, 20), np.float32)), "valid"),
        (dict(filled=np.ones((2, 2), bool)), "filled"),
        (dict(pixel_size_mm=-0.1), "pixel_size_mm"),
        (dict(pixel_size_mm="a"), "pixel_size_mm"),
        (dict(size_px=(10, 10)), "size_px"),
        (dict(size_px=(640.5, 480)), "size_px"),
        (dict(z_exaggeration=0), "z_exaggeration"),
        (dict(z_exaggeration=float("nan")), "z_exaggeration"),
        (dict(max_side=1), "max_side"),
        (dict(elevation_deg=100), "elevation_deg"),
    ],
)
def test_bad_input_names_the_argument(change, match):
    args = dict(height_mm=np.zeros((20, 20), np.float32), rgb=np.zeros((20, 20, 3), np.uint8),
                valid=None, pixel_size_mm=0.05)
    args.update(change)
    with pytest.raises(InputError, match=match):
        render_height_field(args.pop("height_mm"), args.pop("rgb"), args.pop("valid"), **args)


def test_importing_sff_does_not_load_vtk():
    code = "import sys, smdinspect.sff; print(any(m.startswith('vtkmodules') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_filled_guesses_do_not_set_the_height_range():
    # a flat target measured along its lines at -22..-20 mm; a few filled pixels took the
    # sweep's far end (-80 mm): the picture's range is the measured one
    height, rgb = _box_scene(100, 100)
    height = -20.0 - 2.0 * height / max(float(height.max()), 1e-9)
    filled = np.zeros(height.shape, bool)
    filled[:, :70] = True
    height[0:5, 0:10] = -80.0   # 0.5 % of the field
    scene = _build_scene(height, rgb, np.ones(height.shape, bool), filled, pixel_size_mm=None,
                         z_exaggeration=None, max_side=384)
    assert scene.zlo > -23.0 and scene.zhi <= -19.8
