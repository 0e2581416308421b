"""The focal-stack format: manifest parsing, validation, streaming reads, writer."""

import json

import cv2
import numpy as np
import pytest

from smdinspect import _atomic
from smdinspect.errors import InputError
from smdinspect.stack import FocalStack, StackWriter, open_stack, read_image


def _write_frames(root, n=4, shape=(16, 20), colour=False, dtype=np.uint8):
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    names = []
    for i in range(n):
        hi = 255 if dtype == np.uint8 else 65535
        img = rng.integers(0, hi, size=shape + ((3,) if colour else ()), dtype=dtype)
        name = f"f{i}.png"
        _atomic.write_image(root / name, img)
        names.append(name)
    return names


def _manifest(root, frames, **extra):
    (root / "stack.json").write_text(json.dumps({"frames": frames, **extra}))


def test_open_sorts_descending_frames_and_ignores_unknown_keys(tmp_path):
    names = _write_frames(tmp_path)
    frames = [{"file": n, "z_mm": 0.3 - 0.1 * i, "exposure": 3} for i, n in enumerate(names)]
    _manifest(tmp_path, frames, pixel_size_mm=0.02, whatever={"a": 1})
    stack = FocalStack.open(tmp_path)
    np.testing.assert_allclose(stack.z_mm, [0.0, 0.1, 0.2, 0.3], atol=1e-12)
    assert [f.path.name for f in stack.frames] == names[::-1]
    assert stack.pixel_size_mm == 0.02
    assert stack.step_mm == pytest.approx(0.1)


def test_z_from_rig_block(tmp_path):
    names = _write_frames(tmp_path)
    _manifest(tmp_path, [{"file": n} for n in names],
              rig={"d_mm": 100.0, "d_f_mm": 99.0, "step_mm": 0.25})
    stack = FocalStack.open(tmp_path)
    # h_n = d - (d_f + n*step): 1.0, 0.75, 0.5, 0.25 -> ascending
    np.testing.assert_allclose(stack.z_mm, [0.25, 0.5, 0.75, 1.0])


@pytest.mark.parametrize(
    "frames, match",
    [
        ([{"file": "f0.png", "z_mm": 0}, {"file": "f1.png", "z_mm": 0.1}], "at least 3 frames"),
        ([{"file": "f0.png", "z_mm": 0}, {"file": "f1.png", "z_mm": 0},
          {"file": "f2.png", "z_mm": 0.1}], "duplicate z_mm"),
        ([{"file": "f0.png", "z_mm": 0}, {"file": "f1.png", "z_mm": 0.2},
          {"file": "f2.png", "z_mm": 0.1}], "not monotonic"),
        ([{"file": "../f0.png", "z_mm": 0}, {"file": "f1.png", "z_mm": 0.1},
          {"file": "f2.png", "z_mm": 0.2}], "leaves the stack folder"),
        ([{"file": "/etc/passwd", "z_mm": 0}, {"file": "f1.png", "z_mm": 0.1},
          {"file": "f2.png", "z_mm": 0.2}], "absolute"),
        ([{"file": "f0.png", "z_mm": "x"}, {"file": "f1.png", "z_mm": 0.1},
          {"file": "f2.png", "z_mm": 0.2}], "must be a number"),
        ([{"file": "f0.png"}, {"file": "f1.png", "z_mm": 0.1},
          {"file": "f2.png", "z_mm": 0.2}], "no z_mm"),
    ],
)
def test_bad_manifests(tmp_path, frames, match):
    _write_frames(tmp_path, n=3)
    _manifest(tmp_path, frames)
    with pytest.raises(InputError, match=match):
        FocalStack.open(tmp_path)


def test_nan_in_manifest_rejected(tmp_path):
    _write_frames(tmp_path, n=3)
    (tmp_path / "stack.json").write_text(
        '{"frames": [{"file": "f0.png", "z_mm": NaN}, {"file": "f1.png", "z_mm": 0.1},'
        ' {"file": "f2.png", "z_mm": 0.2}]}')
    with pytest.raises(InputError, match="NaN"):
        FocalStack.open(tmp_path)


def test_bad_json_and_missing_manifest(tmp_path):
    with pytest.raises(InputError, match="no stack.json"):
        FocalStack.open(tmp_path)
    (tmp_path / "stack.json").write_text("{nope")
    with pytest.raises(InputError, match="not valid JSON"):
        FocalStack.open(tmp_path)
    (tmp_path / "stack.json").write_text('{"version": 9, "frames": []}')
    with pytest.raises(InputError, match="unsupported format version 9"):
        FocalStack.open(tmp_path)


def test_image_list_needs_step_and_accepts_negative(tmp_path):
    names = _write_frames(tmp_path)
    paths = [tmp_path / n for n in names]
    with pytest.raises(InputError, match="--step-mm"):
        open_stack(paths)
    stack = open_stack(paths, step_mm=-0.05)
    assert [f.path.name for f in stack.frames] == names[::-1]
    np.testing.assert_allclose(stack.z_mm, [0.0, 0.05, 0.10, 0.15], atol=1e-12)
    stack = open_stack([tmp_path], step_mm=0.05, pixel_size_mm=0.01)
    assert len(stack) == 4 and stack.pixel_size_mm == 0.01
    with pytest.raises(InputError, match="not found"):
        open_stack([tmp_path / "missing.png", *paths], step_mm=0.1)


def test_z_from_file_names(tmp_path):
    """--z-from-name: each frame's z from its name (the flat-target-zknown convention,
    XP005_Z-020.jpg = -20 mm), in z order whatever the names' order; clear errors."""
    img = np.full((12, 12), 128, np.uint8)
    for z in (20, 21, 23, 22):
        cv2.imwrite(str(tmp_path / f"XP005_Z-{z:03d}.png"), img)
    stack = open_stack([tmp_path], z_from_name=r"Z(-?[0-9.]+)")
    np.testing.assert_allclose(stack.z_mm, [-23, -22, -21, -20])
    assert [f.path.name for f in stack.frames][0] == "XP005_Z-023.png"
    no_group = open_stack(sorted(tmp_path.glob("*.png")), z_from_name=r"-?[0-9]+(?=\.png)")
    np.testing.assert_allclose(no_group.z_mm, stack.z_mm)
    with pytest.raises(InputError, match="does not match"):
        open_stack([tmp_path], z_from_name=r"Q([0-9]+)")
    with pytest.raises(InputError, match="not a number"):
        open_stack([tmp_path], z_from_name=r"(XP)")
    with pytest.raises(InputError, match="not a regular expression"):
        open_stack([tmp_path], z_from_name=r"Z(")
    with pytest.raises(InputError, match="not both"):
        open_stack([tmp_path], z_from_name=r"Z(-?[0-9.]+)", step_mm=1.0)
    cv2.imwrite(str(tmp_path / "XP005_Z-022b.png"), img)  # z -22 twice
    with pytest.raises(InputError, match="duplicate z_mm"):
        open_stack([tmp_path], z_from_name=r"Z(-?[0-9]+)")


def test_z_from_name_on_the_command_line(tmp_path):
    from smdinspect import cli

    src = tmp_path / "frames"
    src.mkdir()
    from smdinspect.synth import cone, render_gather, texture

    tex = texture("grain", 96, seed=10_500, freq_cyc_px=0.2, contrast=0.25)
    radiance, height = cone(size_px=96, low_mm=0.05, high_mm=0.25, texture=tex, seed=10_500)
    z = np.arange(7) * 0.05
    for zk, frame in zip(z, render_gather(radiance, height, z, blur_px_per_mm=7.0)):
        cv2.imwrite(str(src / f"shot_z{zk:.2f}mm.png"), frame)
    out = tmp_path / "out"
    assert cli.main(["-q", "reconstruct", str(src), "--z-from-name", r"z([0-9.]+)mm",
                     "--outputs", "height_mm.tiff", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    np.testing.assert_allclose(summary["z_range_mm"], [0.0, 0.30])
    assert cli.main(["-q", "reconstruct", str(src), "--z-from-name", "nope([0-9])",
                     "--out", str(tmp_path / "o2")]) == 2
    assert not (tmp_path / "o2").exists()


def test_read_image_kinds_and_errors(tmp_path):
    _write_frames(tmp_path / "c", n=1, colour=True)
    _write_frames(tmp_path / "g16", n=1, dtype=np.uint16)
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 200  # red
    _atomic.write_image(tmp_path / "red.png", rgb)
    img = read_image(tmp_path / "red.png")
    assert img.shape == (4, 5, 3) and img[0, 0, 0] == 200 and img[0, 0, 2] == 0
    assert read_image(tmp_path / "g16" / "f0.png").dtype == np.uint16
    data = (tmp_path / "c" / "f0.png").read_bytes()
    (tmp_path / "trunc.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated"):
        read_image(tmp_path / "trunc.png")
    ok, jpg = cv2.imencode(".jpg", np.full((32, 32), 128, np.uint8))
    (tmp_path / "trunc.jpg").write_bytes(jpg.tobytes()[:-40])
    with pytest.raises(InputError, match="truncated"):
        read_image(tmp_path / "trunc.jpg")
    (tmp_path / "junk.png").write_bytes(b"not an image at all")
    with pytest.raises(InputError, match="not a readable image"):
        read_image(tmp_path / "junk.png")
    with pytest.raises(InputError, match="cannot read"):
        read_image(tmp_path / "nope.png")


def test_writer_roundtrip_and_resume(tmp_path):
    w = StackWriter(tmp_path / "s", pixel_size_mm=0.015, rig={"step_mm": 0.05})
    frames = [np.full((8, 8), i * 10, np.uint8) for i in range(3)]
    for i, f in enumerate(frames):
        w.add_frame(f, 0.05 * i, stage_mm=1.0 + i)
    r = StackWriter.resume(tmp_path / "s")
    assert len(r.frames) == 3
    r.add_frame(np.full((8, 8), 99, np.uint8), 0.15)
    stack = FocalStack.open(tmp_path / "s")
    assert len(stack) == 4
    assert [int(img[0, 0]) for _, _, img in stack.iter_frames()] == [0, 10, 20, 99]
    assert not [p for p in (tmp_path / "s").iterdir() if p.name.startswith(".")]
