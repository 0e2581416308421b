"""The hardening corpus (issue 16): bad stacks, boards, rigs, configs, a full disk, kills.

Every case ends with one line on stderr, the documented exit code, and the output folder
either untouched (it holds exactly what it held before) or complete (this run's outputs,
none of an earlier run's). The README's "Reliability" section lists these cases.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from smdinspect import _atomic
from smdinspect.cli import EXIT_INTERNAL, main
from smdinspect.optics import Optics
from smdinspect.stack import FocalStack, StackWriter, read_image
from smdinspect.synth import cone_scene, render_stack

from ..acquire.rigs import sim_rig

REPO = Path(__file__).parents[2]
DEMO = str(REPO / "references" / "demo_board.json")
RECONSTRUCTION = {"height_mm.tiff", "confidence.tiff", "sigma_mm.tiff", "precision_mm.tiff",
                  "aif.png", "height.png", "reason.png",
                  "view3d.png", "cloud.ply", "mesh.ply", "mesh.stl", "summary.json",
                  "height_filled_mm.tiff", "sigma_filled_mm.tiff", "filled.png", "field.png"}


# -- fixtures and helpers ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def cone(tmp_path_factory):
    """A good 8-bit stack: 96 px at 40 µm/px (3.8 mm field), 13 frames."""
    scene = cone_scene(size_px=96, pixel_size_mm=0.04, height_mm=0.5, seed=3)
    root = tmp_path_factory.mktemp("corpus") / "cone"
    render_stack(scene, np.round(np.arange(-0.1, 0.55, 0.05), 6),
                 optics=Optics.for_pixel_size(0.04), seed=1, out=root, previews=False)
    shutil.rmtree(root / "truth")
    return root


@pytest.fixture(scope="module")
def earlier(cone, tmp_path_factory):
    """The outputs of an earlier successful reconstruct (copied into each test)."""
    out = tmp_path_factory.mktemp("earlier") / "out"
    assert main(["-q", "reconstruct", str(cone), "--out", str(out)]) == 0
    return out


@pytest.fixture
def stack(cone, tmp_path):
    """A private copy of the good stack, to damage."""
    return Path(shutil.copytree(cone, tmp_path / "stack"))


@pytest.fixture
def out(earlier, tmp_path):
    """An output folder holding an earlier run's outputs (and an old-style leftover)."""
    dst = Path(shutil.copytree(earlier, tmp_path / "out"))
    (dst / ".partial-abc123").mkdir()  # left by a SIGKILLed run of an older version
    return dst


def snapshot(folder: Path) -> dict[str, str] | None:
    """Relative path -> SHA-256 of every file under ``folder`` (None when absent)."""
    if not folder.exists():
        return None
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def leftovers(folder: Path) -> list[str]:
    """Temporary siblings of ``folder`` (staging or set-aside folders)."""
    return sorted(p.name for p in folder.parent.iterdir() if p.name.startswith(f".{folder.name}."))


def run(capsys, command: str, *argv, code: int, message: str) -> str:
    """Run ``smdinspect -q COMMAND ARGV``; check the exit code and the one-line message."""
    got = main(["-q", command, *map(str, argv)])
    err = capsys.readouterr().err.strip().splitlines()
    assert got == code, err
    assert len(err) == 1, err
    kind = "internal error" if code == EXIT_INTERNAL else "error"
    assert err[0].startswith(f"smdinspect {command}: {kind}: "), err
    assert message in err[0], err
    return err[0]


def edit_json(path: Path, **changes) -> None:
    doc = json.loads(path.read_text())
    doc.update(changes)
    path.write_text(json.dumps(doc))


def board_file(tmp_path: Path, **changes) -> Path:
    p = tmp_path / "board.json"
    p.write_text(Path(DEMO).read_text())
    edit_json(p, **changes)
    return p


# -- bad stacks: reconstruct leaves OUT untouched ----------------------------------------------
def _mixed_depth(stack: Path) -> None:
    frame = stack / "frame_0005.png"
    cv2.imwrite(str(frame), read_image(frame).astype(np.uint16) * 257)


def _deep(path: Path) -> None:
    path.write_text("[" * 200_000 + "]" * 200_000)


STACK_CASES = {
    "mixed bit depth": (_mixed_depth, "all frames of a stack must have one bit depth"),
    "optics not an object": (lambda s: edit_json(s / "stack.json", optics=[1, 2, 3]),
                             "'optics' must be an object"),
    "meta not an object": (lambda s: edit_json(s / "stack.json", meta="x"),
                           "'meta' must be an object"),
    "absurd pixel size": (lambda s: edit_json(s / "stack.json", pixel_size_mm=1e300),
                          "pixel_size_mm must be between 1e-06 and 10 mm; got 1e+300"),
    "absurd z": (lambda s: edit_json(s / "stack.json", frames=[
        {"file": f"frame_{i:04d}.png", "z_mm": 1e290 * i} for i in range(13)]),
        "heights must lie within"),
    "stack.json nested 200 000 deep": (lambda s: _deep(s / "stack.json"), "nested too deeply"),
    "stack.json not UTF-8": (lambda s: (s / "stack.json").write_bytes(b'{"frames": "\xff"}'),
                             "not UTF-8"),
    "truncated frame": (lambda s: (s / "frame_0004.png").write_bytes(
        (s / "frame_0004.png").read_bytes()[:500]), "frame_0004.png is truncated"),
}


@pytest.mark.parametrize("case", STACK_CASES)
def test_bad_stack_one_line_exit_2_out_untouched(case, stack, out, capsys):
    damage, message = STACK_CASES[case]
    damage(stack)
    before = snapshot(out)
    run(capsys, "reconstruct", stack, "--out", out, code=2, message=message)
    assert snapshot(out) == before and not leftovers(out)


def test_no_such_folder(tmp_path, capsys):
    for command in ("reconstruct", "inspect"):
        board = ["--board", DEMO] if command == "inspect" else []
        run(capsys, command, tmp_path / "nope", *board, "--out", tmp_path / "o", code=2,
            message=f"no such folder: {tmp_path / 'nope'}")
    assert not (tmp_path / "o").exists()


def test_folder_of_images_says_what_was_understood(cone, tmp_path, capsys):
    images = tmp_path / "images"
    images.mkdir()
    for p in sorted(cone.glob("frame_*.png")):
        shutil.copy(p, images / p.name)
    run(capsys, "reconstruct", images, "--out", tmp_path / "o", code=2,
        message=f"{images} has no stack.json; its 13 images need --step-mm")
    stack = FocalStack.open(cone)
    assert main(["reconstruct", str(images), "--step-mm", "0.05", "--pixel-size-mm", "0.04",
                 "--out", str(tmp_path / "o")]) == 0
    said = capsys.readouterr().err
    assert "taking its 13 images frame_0000.png .. frame_0012.png in name order" in said
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["step_mm"] == 0.05 == stack.step_mm  # not 0.05000000000000001
    assert summary["z_range_mm"] == [0.0, 0.6]


def test_out_holding_other_files_is_refused(stack, tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("my notes")
    run(capsys, "reconstruct", stack, "--out", mine, code=2,
        message="holds files smdinspect did not write there (notes.txt)")
    assert snapshot(mine) == {"notes.txt": hashlib.sha256(b"my notes").hexdigest()}
    # nor is a stack folder taken as an output folder
    before = snapshot(stack)
    run(capsys, "reconstruct", stack, "--out", stack, code=2, message="did not write there")
    assert snapshot(stack) == before


def test_nothing_measured_says_so_and_writes_what_it_can(tmp_path, out, capsys):
    flat = tmp_path / "flat"
    w = StackWriter(flat, pixel_size_mm=0.04)
    for i in range(5):
        w.add_frame(np.full((48, 48), 100, np.uint8), 0.05 * i)
    run(capsys, "reconstruct", flat, "--out", out, code=2,
        message="nothing could be measured: no pixel of the 5 frames has a reliable focus peak")
    names = {p.name for p in out.iterdir()}
    assert names == RECONSTRUCTION - {"cloud.ply", "mesh.ply", "mesh.stl"}  # earlier ones gone
    summary = json.loads((out / "summary.json").read_text())
    assert summary["measured"] is False and summary["coverage"] == 0
    assert sorted(summary["files"]) == sorted(names) and not leftovers(out)


def test_failed_run_leaves_no_empty_folder(stack, tmp_path, capsys):
    _mixed_depth(stack)
    target = tmp_path / "new" / "deeper" / "out"
    run(capsys, "reconstruct", stack, "--out", target, code=2, message="one bit depth")
    assert not (tmp_path / "new").exists()


def test_success_replaces_every_earlier_output_and_stale_folders(cone, out, capsys):
    stale = out.parent / f".{out.name}.partial-999999999-x1"  # from a killed run: no such pid
    stale.mkdir()
    (stale / "height_mm.tiff").write_bytes(b"half")
    (out / "junk.stl").write_bytes(b"")  # not an output name: refused, untouched
    run(capsys, "reconstruct", cone, "--out", out, code=2, message="(junk.stl)")
    (out / "junk.stl").unlink()
    assert main(["-q", "reconstruct", str(cone), "--out", str(out)]) == 0
    assert {p.name for p in out.iterdir()} == RECONSTRUCTION  # old-style .partial-* gone too
    assert not leftovers(out)


# -- bad boards and settings: inspect stops before reconstructing --------------------------------
@pytest.mark.parametrize("case", ["huge board", "board nested 200 000 deep", "board not UTF-8",
                                  "board larger than the field", "config not UTF-8",
                                  "config nested 200 000 deep", "config not an object",
                                  "image list without pixel size"])
def test_bad_board_or_settings_exit_2_out_untouched(case, cone, out, tmp_path, capsys):
    args = [cone, "--board", DEMO]
    bad = tmp_path / "bad.json"
    if case == "huge board":
        args[2], message = board_file(tmp_path, size_mm=[1e4, 1e4]), "must be <= 1000 mm; got 10000"
    elif case == "board nested 200 000 deep":
        _deep(bad)
        args[2], message = bad, "nested too deeply"
    elif case == "board not UTF-8":
        bad.write_bytes(b'{"name": "\xe9"}')
        args[2], message = bad, "not UTF-8 text"
    elif case == "board larger than the field":
        args[2] = board_file(tmp_path, size_mm=[400.0, 400.0])
        message = "more than 4 times the measured field (3.84 x 3.84 mm: 96 x 96 px at 0.04 mm)"
    elif case.startswith("config"):
        if case == "config not UTF-8":
            bad.write_bytes(b'{"min_fitness": 0.5, "x": "\xff"}')
        elif case == "config nested 200 000 deep":
            _deep(bad)
        else:
            bad.write_text("[1]")
        args += ["--inspect-config", bad]
        message = {"config not UTF-8": "not UTF-8 text", "config not an object":
                   "must hold a JSON object"}.get(case, "nested too deeply")
    else:
        args[:1] = sorted(cone.glob("frame_*.png"))
        args += ["--step-mm", "0.05"]
        message = "inspection needs the pixel size in mm: give --pixel-size-mm"
    before = snapshot(out)
    run(capsys, "inspect", *args, "--out", out, code=2, message=message)
    assert snapshot(out) == before and not leftovers(out)


def test_board_by_name(cone, tmp_path, capsys):
    """--board demo_board names the packaged board; the cone is no board: exit 3."""
    run(capsys, "inspect", cone, "--board", "demo_board", "--out", tmp_path / "o", code=3,
        message="not located")
    doc = json.loads((tmp_path / "o" / "report.json").read_text())
    assert doc["status"] == "not_located" and doc["board"]["name"] == "demo_board"
    run(capsys, "inspect", cone, "--board", "no_such_board", "--out", tmp_path / "o2", code=2,
        message="boards shipped by name: ")


def test_not_located_replaces_the_earlier_report_whole(cone, out, capsys):
    for name in ("report.json", "junit.xml", "report.html", "joints.csv"):
        (out / name).write_text("from an earlier inspection")
    run(capsys, "inspect", cone, "--board", DEMO, "--out", out, code=3, message="not located")
    names = {p.name for p in out.iterdir()}
    # no old junit.xml beside; the IPC-CFX message says "Error" (not located)
    assert names == RECONSTRUCTION | {"report.json", "report.html", "cfx_units_inspected.json"}
    assert json.loads((out / "report.json").read_text())["status"] == "not_located"
    assert "NOT LOCATED" in (out / "report.html").read_text()  # the new report, saying why
    assert not leftovers(out)


def test_bad_reconstruction_summary(earlier, tmp_path, capsys):
    recon = Path(shutil.copytree(earlier, tmp_path / "recon"))
    for bad, message in (("[1]", "summary.json must hold the object"),
                         ('{"step_mm": "x"}', "summary.json step_mm must be a number")):
        (recon / "summary.json").write_text(bad)
        run(capsys, "inspect", recon, "--board", DEMO, "--out", tmp_path / "o", code=2,
            message=message)
    assert not (tmp_path / "o").exists()


# -- rigs and acquire --resume -----------------------------------------------------------------
def test_unbounded_sweep_is_refused(tmp_path, capsys):
    rig = sim_rig(tmp_path / "rig.toml")
    rig.write_text(rig.read_text().replace("step_mm = 0.05", "step_mm = 1e-9"))
    run(capsys, "acquire", "--rig", rig, "--out", tmp_path / "s", code=2,
        message="plans 9e+08 frames, more than max_frames = 2000")
    assert not (tmp_path / "s").exists()
    run(capsys, "simulate", "cone", "--step-mm", "1e-9", "--out", tmp_path / "c", code=2,
        message="more than 2000")


@pytest.mark.parametrize("manifest, message", [
    ("[]", "stack.json must hold an object with a 'frames' list"),
    ('{"frames": [{"file": "frame_0000.png"}]}', "frames[0].z_mm must be a number"),
    ('{"frames": [], "meta": "x"}', "'meta' must be an object"),
    ("[" * 100_000, "nested too deeply"),
])
def test_resume_of_a_bad_manifest(manifest, message, tmp_path, capsys):
    out = tmp_path / "s"
    out.mkdir()
    (out / "stack.json").write_text(manifest)
    run(capsys, "acquire", "--rig", sim_rig(tmp_path / "rig.toml"), "--out", out, "--resume",
        code=2, message=message)
    assert (out / "stack.json").read_text() == manifest


def test_resume_takes_a_damaged_listed_frame_again(tmp_path, capsys):
    rig = sim_rig(tmp_path / "rig.toml")
    ref, out = tmp_path / "ref", tmp_path / "s"
    assert main(["-q", "acquire", "--rig", str(rig), "--out", str(ref)]) == 0
    shutil.copytree(ref, out)
    frame = out / "frame_0010.png"
    frame.write_bytes(frame.read_bytes()[:300])  # damaged after it was written
    assert main(["-q", "acquire", "--rig", str(rig), "--out", str(out), "--resume"]) == 0
    assert "frame_0010.png is truncated; taking frames 10..18 again" in capsys.readouterr().err
    stack = FocalStack.open(out)
    assert len(stack) == 19
    for i in range(19):
        assert np.array_equal(stack.read_frame(i), FocalStack.open(ref).read_frame(i))


def test_failed_acquire_leaves_no_empty_folder(tmp_path, capsys):
    rig = sim_rig(tmp_path / "rig.toml")  # a real stage on a port that does not exist
    rig.write_text(rig.read_text().replace(
        "[stage.fake]\nsteps_per_mm = 400.0\nmax_rate_mm_s = 200.0\nstart_z_mm = 0.0\n",
        'port = "/dev/ttyNOPE9"\n'))
    run(capsys, "acquire", "--rig", rig, "--out", tmp_path / "new" / "s", code=4,
        message="stage port /dev/ttyNOPE9 not found")
    assert not (tmp_path / "new").exists()


# -- full disk ---------------------------------------------------------------------------------
def test_disk_full_errno(cone, out, monkeypatch, capsys):
    calls = []
    real = os.fsync

    def fsync(fd):
        calls.append(fd)
        if len(calls) > 4:  # a few files in
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd)

    before = snapshot(out)
    monkeypatch.setattr(_atomic.os, "fsync", fsync)
    line = run(capsys, "reconstruct", cone, "--out", out, code=2,
               message=f"no space left on device: {out}/")
    assert ".partial" not in line  # the final path, not the staging folder
    assert snapshot(out) == before and not leftovers(out)


def test_disk_full_short_write_without_errno(cone, out, monkeypatch, capsys):
    """numpy's tofile (tifffile) says "16384 requested and 16316 written", no errno."""
    import tifffile

    class Full:
        f_bavail, f_frsize = 0, 4096

    def imwrite(*args, **kwargs):
        raise OSError("16384 requested and 16316 written")

    before = snapshot(out)
    monkeypatch.setattr(tifffile, "imwrite", imwrite)
    monkeypatch.setattr(_atomic.os, "statvfs", lambda folder: Full)
    run(capsys, "reconstruct", cone, "--out", out, code=2,
        message=f"no space left on device: {out}/height_mm.tiff")
    assert snapshot(out) == before and not leftovers(out)


def test_disk_full_during_the_reports_keeps_the_earlier_report(cone, out, monkeypatch, capsys):
    """The issue's case: junit.xml replaced but the old report.json kept. Not any more."""
    for name in ("report.json", "junit.xml"):
        (out / name).write_text("earlier")
    before = snapshot(out)
    real = _atomic.write_bytes

    def write_bytes(path, data):
        if Path(path).name == "report.json":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, data)

    monkeypatch.setattr(_atomic, "write_bytes", write_bytes)
    run(capsys, "inspect", cone, "--board", DEMO, "--out", out, code=2,
        message="no space left on device")
    assert snapshot(out) == before and not leftovers(out)


# -- internal errors ---------------------------------------------------------------------------
def test_internal_error_exits_70_in_one_line(cone, out, monkeypatch, capsys):
    from smdinspect import sff

    def broken(*args, **kwargs):
        raise TypeError("unsupported operand\ntype(s)")

    before = snapshot(out)
    monkeypatch.setattr(sff, "reconstruct", broken)
    run(capsys, "reconstruct", cone, "--out", out, code=EXIT_INTERNAL,
        message="TypeError: unsupported operand type(s); this is a bug in smdinspect")
    assert snapshot(out) == before and not leftovers(out)
    assert main(["reconstruct", "-v", str(cone), "--out", str(out)]) == EXIT_INTERNAL
    assert "Traceback" in capsys.readouterr().err  # -v after the subcommand works too


def test_verbosity_after_the_subcommand(cone, tmp_path, capsys):
    assert main(["reconstruct", str(cone), "--out", str(tmp_path / "o"), "-q"]) == 0
    assert capsys.readouterr().err == ""


# -- kills -------------------------------------------------------------------------------------
def test_sigkill_mid_reconstruct_then_rerun(cone, out, tmp_path):
    """SIGKILL a real `smdinspect reconstruct` while it writes: OUT keeps the earlier
    outputs; the next run removes the killed run's staging folder and completes."""
    big = tmp_path / "big"
    scene = cone_scene(size_px=512, pixel_size_mm=0.01, height_mm=0.5, seed=3)
    render_stack(scene, np.round(np.arange(-0.1, 0.55, 0.05), 6),
                 optics=Optics.for_pixel_size(0.01), seed=1, out=big, previews=False)
    before = snapshot(out)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    argv = [sys.executable, "-m", "smdinspect", "-q", "reconstruct", str(big), "--out", str(out)]
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        staged = [p for p in out.parent.glob(f".{out.name}.partial-*")]
        if staged and any(p.name == "height_mm.tiff" for p in staged[0].iterdir()):
            break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()
    proc.stderr.close()
    assert snapshot(out) == before
    assert leftovers(out)  # the killed run's staging folder
    assert main(["-q", "reconstruct", str(big), "--out", str(out)]) == 0
    assert {p.name for p in out.iterdir()} == RECONSTRUCTION and not leftovers(out)
    assert json.loads((out / "summary.json").read_text())["image_size_px"] == [512, 512]


def test_pipeline_refuses_a_board_far_larger_than_the_field(earlier, tmp_path):
    """Batch and Python callers go through inspect_stack, not the CLI's early check."""
    from smdinspect.errors import InputError
    from smdinspect.pipeline import inspect_stack

    with pytest.raises(InputError, match="more than 4 times the measured field"):
        inspect_stack(earlier, board_file(tmp_path, size_mm=[400.0, 400.0]), tmp_path / "rep")
    assert not (tmp_path / "rep" / "report.json").exists()


def test_every_help_page_prints(capsys):
    """`smdinspect --help` once crashed on a bare '%' in a subcommand's help string."""
    from smdinspect.cli import build_parser

    parser = build_parser()
    commands = [[]]
    for action in parser._subparsers._group_actions:
        for name, sub in action.choices.items():
            commands.append([name])
            for inner in sub._actions:
                if isinstance(inner, type(action)):
                    commands.extend([name, n] for n in inner.choices)
    for argv in commands:
        with pytest.raises(SystemExit) as stop:
            main([*argv, "--help"])
        assert stop.value.code == 0, argv
        assert "usage: smdinspect" in capsys.readouterr().out, argv
    assert len(commands) > 10
