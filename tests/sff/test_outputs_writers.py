"""The reconstruction writers: mesh.ply read back by trimesh/Open3D/plyfile, height.png
(legend, monotonic colours, unreliable marking, scale bar), concurrent writing, and
that ``reconstruct`` loads neither matplotlib, trimesh nor Open3D."""

import subprocess
import sys
import threading
import time

import cv2
import numpy as np
import pytest

from smdinspect.sff import Surface
from smdinspect.sff import _export
from smdinspect.sff._heightpng import _lut_bgr, _nice_length, display_range, render_height_map


def _surface(height, reliable=None, *, pixel_size_mm=0.02, aif=None):
    h, w = height.shape
    reliable = np.ones((h, w), bool) if reliable is None else reliable
    if aif is None:
        aif = (np.random.default_rng(3).random((h, w, 3)) * 255).astype(np.uint8)
    f = np.ones((h, w), np.float32)
    conf = np.where(reliable, 0.9, 0.1).astype(np.float32)
    return Surface(height_mm=height.astype(np.float32), confidence=conf, reliable=reliable,
                   f_peak=f, sigma_mm=f * 0.05, reliability_db=f * 30, aif=aif,
                   pixel_size_mm=pixel_size_mm, z_mm=np.linspace(0.0, 1.0, 11))


def _ramp(h=90, w=160):
    return np.tile(np.linspace(0.0, 1.0, w, dtype=np.float32), (h, 1))


# ----------------------------------------------------------------------------- mesh.ply


def test_mesh_ply_reads_back_in_trimesh_open3d_and_plyfile(tmp_path):
    import open3d as o3d
    import plyfile
    import trimesh

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(50, 3)) * 3
    faces = rng.integers(0, 50, size=(70, 3))
    rgb = rng.integers(0, 256, size=(50, 3), dtype=np.uint8)
    path = _export.write_mesh_ply(tmp_path / "m.ply", verts, faces, rgb)

    ply = plyfile.PlyData.read(str(path))
    assert ply.header.splitlines()[1] == "format binary_little_endian 1.0"
    assert np.array_equal(np.vstack(ply["face"]["vertex_indices"]), faces)
    assert np.allclose(np.column_stack([ply["vertex"][a] for a in "xyz"]), verts, atol=1e-5)

    tm = trimesh.load(path, process=False)
    assert np.array_equal(tm.faces, faces)
    assert np.allclose(tm.vertices, verts.astype(np.float32))
    assert np.array_equal(tm.visual.vertex_colors[:, :3], rgb)

    om = o3d.io.read_triangle_mesh(str(path))
    assert np.array_equal(np.asarray(om.triangles), faces)
    assert np.allclose(np.asarray(om.vertices), verts, atol=1e-5)
    assert np.allclose(np.asarray(om.vertex_colors), rgb / 255.0, atol=1e-6)


def test_mesh_ply_and_stl_of_a_reconstruction_agree(tmp_path):
    import trimesh

    yy, xx = np.mgrid[0:120, 0:150]
    height = 0.5 * np.exp(-((xx - 75) ** 2 + (yy - 60) ** 2) / 800.0)
    surface = _surface(height)
    paths = _export.write_reconstruction(surface, tmp_path / "out",
                                         outputs=["mesh.ply", "mesh.stl"])
    assert sorted(paths) == ["mesh.ply", "mesh.stl", "summary.json"]
    ply = trimesh.load(paths["mesh.ply"], process=False)
    stl = trimesh.load(paths["mesh.stl"])
    assert len(ply.faces) == len(stl.faces) == 2 * 119 * 149
    assert np.allclose(np.sort(ply.triangles.reshape(-1, 9), axis=0),
                       np.sort(stl.triangles.reshape(-1, 9), axis=0), atol=1e-5)
    assert ply.vertices[:, 2].max() == pytest.approx(0.5, abs=1e-3)
    assert np.all(ply.face_normals[:, 2] > 0)  # faces point up, towards the camera
    assert ply.vertices[:, 0].max() == pytest.approx(149 * 0.02)


def test_mesh_ply_bad_arrays_name_the_argument(tmp_path):
    with pytest.raises(ValueError, match=r"faces must be \(F, 3\)"):
        _export.write_mesh_ply(tmp_path / "m.ply", np.zeros((4, 3)), np.zeros((2, 4), int))
    assert not list(tmp_path.iterdir())


def test_cloud_ply_points_and_colours(tmp_path):
    import plyfile

    height = _ramp(40, 50)
    reliable = np.zeros(height.shape, bool)
    reliable[5:30, 10:40] = True
    aif = (np.arange(40 * 50 * 3) % 251).reshape(40, 50, 3).astype(np.uint8)
    surface = _surface(height, reliable, aif=aif, pixel_size_mm=0.01)
    _export.write_point_cloud(surface, tmp_path / "c.ply")
    v = plyfile.PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    rows, cols = np.nonzero(reliable)
    assert len(v) == reliable.sum()
    assert np.allclose(v["x"], cols * 0.01) and np.allclose(v["y"], (39 - rows) * 0.01)
    assert np.array_equal(v["z"], height[rows, cols])
    assert np.array_equal(np.column_stack([v["red"], v["green"], v["blue"]]), aif[rows, cols])
    assert np.allclose(v["confidence"], 0.9)
    assert np.isnan(v["precision"]).all()  # a surface without a precision: unknown


def test_cloud_ply_with_the_filled_surface_flags_every_filled_point(tmp_path):
    """``filled``: the field's unmeasured pixels join the cloud at the dense surface's
    height, each flagged filled = 1 with its fill uncertainty, confidence 0 and precision
    NaN; measured points keep their reading (filled = 0, sigma_filled 0). Outside the
    field nothing is added. Open3D reads the file (its x, y, z); by default the cloud is
    the measured points alone, and with the unreliable readings as well it is refused."""
    import dataclasses
    import json

    import open3d as o3d
    import plyfile

    from smdinspect.errors import InputError

    height = 0.3 + 0.2 * _ramp(40, 50)
    reliable = np.zeros(height.shape, bool)
    reliable[::3] = True
    field = np.ones(height.shape, bool)
    field[:, :4] = False
    surface = dataclasses.replace(_surface(height, reliable), field=field,
                                  precision_mm=np.full(height.shape, 0.004, np.float32))
    _export.write_point_cloud(surface, tmp_path / "c.ply", filled=True)
    v = plyfile.PlyData.read(str(tmp_path / "c.ply"))["vertex"]
    keep = reliable | field
    rows, cols = np.nonzero(keep)
    assert len(v) == keep.sum()
    assert np.allclose(v["x"], cols * 0.02) and np.allclose(v["y"], (39 - rows) * 0.02)
    flag = v["filled"].astype(bool)
    assert np.array_equal(flag, ~reliable[rows, cols])
    assert np.array_equal(v["z"][~flag], height[rows, cols][~flag])
    dense_z, _, dense_sigma = surface.dense
    assert np.array_equal(v["z"][flag], dense_z[rows, cols][flag])  # the dense surface's
    assert np.array_equal(v["sigma_filled"][flag], dense_sigma[rows, cols][flag])
    assert (v["sigma_filled"][~flag] == 0).all() and (v["sigma_filled"][flag] > 0).all()
    assert (v["confidence"][flag] == 0).all() and np.isnan(v["precision"][flag]).all()
    assert np.allclose(v["precision"][~flag], 0.004)
    pc = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    assert len(pc.points) == keep.sum()

    _export.write_point_cloud(surface, tmp_path / "m.ply")
    plain = plyfile.PlyData.read(str(tmp_path / "m.ply"))["vertex"]
    assert len(plain) == reliable.sum() and "filled" not in plain.data.dtype.names
    with pytest.raises(InputError, match="not both"):
        _export.write_point_cloud(surface, tmp_path / "x.ply", filled=True, keep_unreliable=True)
    assert not (tmp_path / "x.ply").exists()
    paths = _export.write_reconstruction(surface, tmp_path / "out", cloud_filled=True,
                                         outputs=["cloud.ply"])
    summary = json.loads(paths["summary.json"].read_text())
    assert summary["cloud_points"] == keep.sum() and summary["cloud_filled"] is True


# ---------------------------------------------------------------------------- height.png


def _lut_index_of(pixels_rgb: np.ndarray) -> np.ndarray:
    """Nearest viridis index of each RGB pixel."""
    lut = _lut_bgr()[:, ::-1].astype(np.int32)
    d = ((pixels_rgb[:, None, :].astype(np.int32) - lut[None]) ** 2).sum(axis=2)
    return d.argmin(axis=1), d.min(axis=1)


def _map_box(image: np.ndarray) -> tuple[int, int, int, int]:
    """(top, bottom, left, right) of the map: the largest non-white block at the left."""
    ink = (image < 250).any(axis=2)
    col = ink[:, : image.shape[1] // 3].sum(axis=1)
    rows = np.nonzero(col > 0.8 * col.max())[0]
    row = ink[(rows[0] + rows[-1]) // 2]
    cols = np.nonzero(row)[0]
    # the map's columns: the first contiguous run of ink in its middle row
    breaks = np.nonzero(np.diff(cols) > 1)[0]
    right = cols[breaks[0]] if len(breaks) else cols[-1]
    return rows[0], rows[-1], cols[0], right


def test_height_png_colours_grow_with_height_and_legend_matches(tmp_path):
    surface = _surface(_ramp())
    path = _export.render_height_png(surface, tmp_path / "height.png")
    image = cv2.imread(str(path))[:, :, ::-1]
    assert image.shape[1] >= 1000  # small maps are enlarged: the labels stay legible
    top, bottom, left, right = _map_box(image)
    middle = image[(top + bottom) // 2, left + 4:right - 4]
    index, dist = _lut_index_of(middle)
    assert dist.max() < 30  # every map pixel is a viridis colour
    assert np.all(np.diff(index) >= 0) and index[0] < 10 and index[-1] > 245

    # the colour bar right of the map runs from the top colour (high) to the bottom (low)
    bar_cols = [c for c in range(right + 5, image.shape[1])
                if _lut_index_of(image[top + 5:bottom - 5:40, c])[1].max() < 30]
    assert len(bar_cols) >= 16
    bar = image[top + 2:bottom - 2, bar_cols[len(bar_cols) // 2]]
    bar_index, _ = _lut_index_of(bar)
    assert np.all(np.diff(bar_index) <= 0) and bar_index[0] > 245 and bar_index[-1] < 10
    # tick labels: dark ink right of the bar, spread over its height
    labels = (image[top:bottom, bar_cols[-1] + 2:].max(axis=2) < 90)
    ink_rows = np.nonzero(labels.any(axis=1))[0]
    assert len(ink_rows) > 40 and ink_rows.max() - ink_rows.min() > 0.6 * (bottom - top)


def test_height_png_range_is_robust_to_outliers():
    height = _ramp()
    height[0, 0] = 50.0  # one wild pixel must not flatten the colours
    lo, hi = display_range(height, np.ones(height.shape, bool))
    assert lo == pytest.approx(0.0, abs=0.01) and hi == pytest.approx(1.0, abs=0.01)
    image = render_height_map(height, np.ones(height.shape, bool), pixel_size_mm=0.02)
    top, bottom, left, right = _map_box(image)
    index, _ = _lut_index_of(image[(top + bottom) // 2, (left + right) // 2][None])
    assert 100 < index[0] < 156


def test_height_png_marks_unreliable_pixels_grey_and_says_how_many(tmp_path):
    height = _ramp()
    reliable = np.ones(height.shape, bool)
    reliable[:, :40] = False  # a quarter
    image = render_height_map(height, reliable, pixel_size_mm=0.02,
                              aif=np.full(height.shape + (3,), 128, np.uint8))
    top, bottom, left, right = _map_box(image)
    mid = image[(top + bottom) // 2]
    split = left + (right - left) // 4
    grey = mid[left + 4:split - 4].astype(int)
    assert (grey.max(axis=1) - grey.min(axis=1)).max() <= 2  # no colour
    assert 150 < grey.mean() < 230  # pale: marked, but not a dark block that takes the eye
    coloured = mid[split + 4:right - 4].astype(int)
    assert (coloured.max(axis=1) - coloured.min(axis=1)).min() > 40
    other = render_height_map(height, np.ones(height.shape, bool), pixel_size_mm=0.02)
    assert not np.array_equal(image[:top], other[:top])  # the title states the share


def test_height_png_scale_bar_has_the_right_length():
    height = _ramp(300, 500)
    image = render_height_map(height, np.ones(height.shape, bool), pixel_size_mm=0.01)
    top, bottom, left, right = _map_box(image)
    scale = (right - left + 1) / 500
    white = (image[top:bottom, left:right] >= 250).all(axis=2)
    runs = [np.diff(np.nonzero(np.diff(np.r_[0, r, 0]))[0])[::2].max(initial=0) for r in white]
    expected = _nice_length(500 * 0.01 / 4) / 0.01 * scale  # 1 mm = 100 px, enlarged
    assert max(runs) == pytest.approx(expected, abs=3)


def test_height_png_large_maps_are_downsized_and_non_blank():
    height = np.random.default_rng(1).random((1800, 2400)).astype(np.float32)
    image = render_height_map(height, np.ones(height.shape, bool), pixel_size_mm=None)
    assert max(image.shape[:2]) < 2000
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 200


# ----------------------------------------------------------------------------- writing


def test_write_lanes_error_stops_and_waits_for_running_writers():
    finished = threading.Event()
    ran_after = []

    def slow():
        time.sleep(0.3)
        finished.set()

    def fail():
        time.sleep(0.05)
        raise OSError("disk on fire")

    with pytest.raises(OSError, match="disk on fire"):
        _export._run_lanes([[fail, lambda: ran_after.append("here")],
                            [slow, lambda: ran_after.append("there")]])
    assert finished.is_set()  # the running writer finished before the error came out
    assert ran_after == []  # nothing started after it


def test_write_lanes_results_by_lane():
    assert _export._run_lanes([[lambda: 1, lambda: 2], [lambda: 3]]) == [[1, 2], [3]]
    assert _export._run_lanes([[], [lambda: 3]]) == [[], [3]]


def test_failing_writer_leaves_the_earlier_outputs(tmp_path, monkeypatch, capsys):
    from smdinspect.cli import main
    from smdinspect.stack import StackWriter

    rng = np.random.default_rng(5)
    tex = cv2.GaussianBlur(rng.random((64, 64)).astype(np.float32), (0, 0), 1.0)
    w = StackWriter(tmp_path / "stack", pixel_size_mm=0.02)
    for i, s in enumerate([3.0, 1.5, 0.0, 1.5, 3.0]):
        img = tex if s == 0 else cv2.GaussianBlur(tex, (0, 0), s)
        w.add_frame((np.clip(img, 0, 1) * 255).astype(np.uint8), 0.05 * i)
    out = tmp_path / "out"
    assert main(["-q", "reconstruct", str(tmp_path / "stack"), "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def broken(surface, path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(_export, "render_height_png", broken)
    assert main(["-q", "reconstruct", str(tmp_path / "stack"), "--out", str(out)]) != 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_reconstruct_imports_neither_matplotlib_trimesh_nor_open3d(tmp_path):
    from smdinspect.stack import StackWriter

    rng = np.random.default_rng(6)
    w = StackWriter(tmp_path / "stack", pixel_size_mm=0.02)
    for i in range(5):
        w.add_frame(rng.integers(0, 255, (48, 48), dtype=np.uint8), 0.05 * i)
    code = ("import sys; from smdinspect.cli import main; "
            f"main(['-q', 'reconstruct', {str(tmp_path / 'stack')!r}, '--out', "
            f"{str(tmp_path / 'out')!r}, '--min-confidence', '0']); "
            "print(sorted(m for m in ('matplotlib', 'trimesh', 'open3d', 'scipy.spatial') "
            "if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip().splitlines()[-1] == "[]"
    written = {p.name for p in (tmp_path / "out").iterdir()}
    assert {"height.png", "mesh.ply", "view3d.png"} <= written
