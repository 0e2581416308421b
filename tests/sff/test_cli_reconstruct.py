"""`smdinspect reconstruct` end to end: outputs, formats and one-line errors."""

import json

import cv2
import numpy as np
import pytest
import tifffile

from smdinspect import _atomic
from smdinspect.cli import main
from smdinspect.optics import Optics
from smdinspect.stack import StackWriter
from smdinspect.synth import cone_scene, render_stack


@pytest.fixture(scope="module")
def cone_stack(tmp_path_factory):
    scene = cone_scene(size_px=128, pixel_size_mm=0.015, height_mm=0.6, seed=2, color=True)
    root = tmp_path_factory.mktemp("stack") / "cone"
    z = np.round(np.arange(-0.1, 0.75, 0.05) + 0.013, 6)
    render_stack(scene, z, optics=Optics.for_pixel_size(0.015), seed=1, out=root, previews=False)
    return root, scene


def test_outputs(cone_stack, tmp_path, capsys):
    import open3d as o3d
    import trimesh

    root, scene = cone_stack
    out = tmp_path / "out"
    assert main(["-q", "reconstruct", str(root), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "coverage" in printed and "(where: reason.png)" in printed
    names = {p.name for p in out.iterdir()}
    assert names == {"height_mm.tiff", "confidence.tiff", "sigma_mm.tiff", "precision_mm.tiff",
                     "aif.png", "height.png", "reason.png", "view3d.png",
                     "cloud.ply", "mesh.ply", "mesh.stl", "summary.json", "height_filled_mm.tiff",
                     "sigma_filled_mm.tiff", "filled.png", "field.png"}
    dense = tifffile.imread(out / "height_filled_mm.tiff")
    filled = cv2.imread(str(out / "filled.png"), cv2.IMREAD_GRAYSCALE) > 0
    measured = tifffile.imread(out / "height_mm.tiff")
    conf = tifffile.imread(out / "confidence.tiff")
    assert np.array_equal(dense[~filled], measured[~filled])  # measured never replaced
    assert np.array_equal(~filled, conf >= 0.5) and np.isfinite(dense).all()
    height = tifffile.imread(out / "height_mm.tiff")
    conf = tifffile.imread(out / "confidence.tiff")
    assert height.dtype == np.float32 and height.shape == (128, 128)
    assert conf.dtype == np.float32 and 0 <= conf.min() and conf.max() <= 1
    good = conf >= 0.5
    assert np.median(np.abs(height - scene.height_mm)[good]) < 0.01
    cloud = o3d.t.io.read_point_cloud(str(out / "cloud.ply"))
    assert cloud.point.positions.shape[0] == int(good.sum())
    assert "confidence" in cloud.point
    assert cloud.point.confidence.numpy().min() >= 0.5
    xyz = cloud.point.positions.numpy()
    assert xyz[:, 0].max() <= 127 * 0.015 + 1e-5 and xyz[:, 2].max() < 0.7
    mesh = trimesh.load(out / "mesh.stl")
    assert len(mesh.faces) > 1000
    summary = json.loads((out / "summary.json").read_text())
    assert summary["coverage"] == pytest.approx(good.mean(), abs=1e-3)
    # the random error of each height: NaN where unknown, else a fraction of a step
    precision = tifffile.imread(out / "precision_mm.tiff")
    assert precision.dtype == np.float32 and precision.shape == (128, 128)
    known = precision[good & np.isfinite(precision)]
    assert summary["precision_mm"]["known_fraction"] == pytest.approx(known.size / good.sum(), abs=1e-3)
    if known.size:
        assert 0 <= known.min() and np.median(known) < 0.5 * 0.05
    assert summary["frames"] == 17 and summary["config"]["operator"] == "sml"
    assert not [p for p in out.iterdir() if p.name.startswith(".")]


def test_keep_unreliable_keeps_every_point(cone_stack, tmp_path):
    import open3d as o3d

    root, _ = cone_stack
    out = tmp_path / "out"
    assert main(["-q", "reconstruct", str(root), "--out", str(out), "--keep-unreliable"]) == 0
    assert o3d.t.io.read_point_cloud(str(out / "cloud.ply")).point.positions.shape[0] == 128 * 128


def test_image_list_with_step(cone_stack, tmp_path):
    root, _ = cone_stack
    frames = sorted(root.glob("frame_*.png"))
    out = tmp_path / "out"
    assert main(["-q", "reconstruct", *map(str, frames), "--step-mm", "0.05",
                 "--pixel-size-mm", "0.015", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["z_range_mm"] == [0.0, pytest.approx(0.8)]


def _small_stack(root, n=4, shape=(24, 24)):
    w = StackWriter(root, pixel_size_mm=0.01)
    rng = np.random.default_rng(0)
    for i in range(n):
        w.add_frame(rng.integers(0, 255, shape, dtype=np.uint8), 0.05 * i)
    return root


@pytest.mark.parametrize(
    "make, extra, message",
    [
        (lambda r: _small_stack(r, n=2), [], "at least 3 frames"),
        (lambda r: _small_stack(r), ["--window-px", "4"], "window_px must be an odd integer"),
        (lambda r: _small_stack(r), ["--window-px", "31"], "window_px must be <="),
        (lambda r: _small_stack(r), ["--band-mpixels", "0.1"], "band_mpixels must be 0"),
        (lambda r: _small_stack(r), ["--operator", "nope"], None),  # argparse: exit 2
        (lambda r: (_small_stack(r), (r / "frame_0002.png").write_bytes(b"\x89PNG\r\n\x1a\nxx")),
         [], "truncated"),
        (lambda r: (_small_stack(r), (r / "frame_0001.png").unlink()), [], "cannot read frame"),
        (lambda r: (_small_stack(r), _atomic.write_image(r / "frame_0003.png",
                                                         np.zeros((24, 24, 3), np.uint8))),
         [], "all frames must match"),
    ],
)
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys, make, extra, message):
    root = tmp_path / "stack"
    make(root)
    out = tmp_path / "out"
    if message is None:
        with pytest.raises(SystemExit) as exc:
            main(["reconstruct", str(root), "--out", str(out), *extra])
        assert exc.value.code == 2
        return
    assert main(["-q", "reconstruct", str(root), "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("smdinspect reconstruct: error:")
    assert message in err[0]
    assert not out.exists() or not any(out.iterdir())


def test_list_without_step_is_an_error(cone_stack, tmp_path, capsys):
    root, _ = cone_stack
    frames = sorted(root.glob("frame_*.png"))
    assert main(["reconstruct", *map(str, frames), "--out", str(tmp_path / "o")]) == 2
    assert "--step-mm" in capsys.readouterr().err


def test_outputs_chooses_the_files_written(tmp_path, capsys):
    from smdinspect.cli import main
    from smdinspect.synth import GatherNoise, render_gather, slanted_plane, texture

    tex = texture("band", 64, seed=10_020, freq_cyc_px=0.2, contrast=0.25)
    radiance, height = slanted_plane(size_px=64, low_mm=0.0, high_mm=0.5, texture=tex,
                                     seed=10_020)
    z = np.arange(-0.1, 0.6 + 1e-9, 0.05)
    paths = []
    for i, f in enumerate(render_gather(radiance, height, z, blur_px_per_mm=4.0,
                                        noise=GatherNoise(), seed=10_020)):
        paths.append(tmp_path / f"f{i:02d}.png")
        cv2.imwrite(str(paths[-1]), f)
    out = tmp_path / "out"
    args = ["reconstruct", *map(str, paths), "--step-mm", "0.05", "--out", str(out)]
    assert main(args + ["--outputs", "height_mm.tiff, cloud.ply"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["cloud.ply", "height_mm.tiff", "summary.json"]
    assert main(args + ["--outputs", "height_mm.tiff,nope.png"]) == 2
    assert "unknown nope.png" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["cloud.ply", "height_mm.tiff", "summary.json"]


def test_cloud_filled_adds_the_filled_points_flagged(cone_stack, tmp_path, capsys):
    """``--cloud-filled``: cloud.ply holds every field pixel, the filled ones flagged and at
    the dense surface's height (height_filled_mm.tiff); with --keep-unreliable it is a
    one-line error (exit 2) and the previous outputs stay."""
    import plyfile

    root, _ = cone_stack
    out = tmp_path / "out"
    assert main(["-q", "reconstruct", str(root), "--out", str(out), "--cloud-filled",
                 "--outputs", "cloud.ply,height_filled_mm.tiff,filled.png,field.png"]) == 0
    v = plyfile.PlyData.read(str(out / "cloud.ply"))["vertex"]
    dense = tifffile.imread(out / "height_filled_mm.tiff")
    filled = cv2.imread(str(out / "filled.png"), cv2.IMREAD_GRAYSCALE) > 0
    field = cv2.imread(str(out / "field.png"), cv2.IMREAD_GRAYSCALE) > 0
    assert len(v) == int(((~filled) | field).sum())
    rows = np.round(127 - v["y"] / 0.015).astype(int)
    cols = np.round(v["x"] / 0.015).astype(int)
    assert np.array_equal(v["filled"].astype(bool), filled[rows, cols])
    assert np.array_equal(v["z"], dense[rows, cols])
    assert 0 < v["filled"].sum() < len(v)
    before = sorted(p.name for p in out.iterdir())
    assert main(["-q", "reconstruct", str(root), "--out", str(out), "--cloud-filled",
                 "--keep-unreliable"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not both" in err
    assert sorted(p.name for p in out.iterdir()) == before


def test_coarse_levels_option_reaches_the_reconstruction(cone_stack, tmp_path):
    root, _ = cone_stack
    out = tmp_path / "o"
    # the 128-px cone just holds a 16x level (8 blocks on its shorter side)
    assert main(["-q", "reconstruct", str(root), "--out", str(out), "--coarse-levels", "2",
                 "--outputs", "summary.json"]) == 0
    doc = json.loads((out / "summary.json").read_text())
    assert doc["config"]["coarse_levels"] == 2
    assert list(doc["coarse_fractions"]) == ["4", "16"]
