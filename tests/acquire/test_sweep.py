"""The sweep against the fake GRBL on a pty with a folder camera: order, z, faults, resume."""

from __future__ import annotations

import errno
import json
import os
import signal
import time

import numpy as np
import pytest

import smdinspect._atomic
from smdinspect.acquire import FakeGrbl, FolderCamera, GrblStage, SweepConfig, ZMapping, run_sweep
from smdinspect.errors import CameraError, InputError, StageError
from smdinspect.stack import FocalStack, read_image

from .conftest import FAST, make_frames, stage_config

SWEEP = SweepConfig(z_start_mm=0.0, z_stop_mm=0.2, step_mm=0.02, backlash_mm=0.1)
MAPPING = ZMapping(focus_offset_mm=5.0, direction=1)  # machine z = z_mm - 5


def sweep_with(fake, out, folder, *, sweep=SWEEP, resume=False, camera=None, sha="rig-a",
               **stage_kw):
    """Open a GRBL stage on ``fake`` and a folder camera, run the sweep, close both."""
    camera = camera or FolderCamera(folder)
    with GrblStage(stage_config(**stage_kw), port=fake.port) as stage, camera:
        return run_sweep(stage, camera, out, sweep=sweep, mapping=MAPPING, resume=resume,
                         pixel_size_mm=0.01, rig_sha256=sha)


def wait_for(cond, timeout_s=1.0):
    """Poll ``cond`` (the fake serves its pty in a thread) until true or timed out."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def manifest(out):
    return json.loads((out / "stack.json").read_text())


def assert_intact(out):
    """Every frame stack.json lists decodes; no temp file or unlisted frame is left."""
    doc = manifest(out)
    listed = {f["file"] for f in doc["frames"]}
    for name in listed:
        assert read_image(out / name).shape == (48, 64)
    return doc


def assert_same_stack(a, b):
    da, db = manifest(a), manifest(b)
    assert [(f["file"], f["z_mm"]) for f in da["frames"]] == \
           [(f["file"], f["z_mm"]) for f in db["frames"]]
    for f in da["frames"]:
        assert (a / f["file"]).read_bytes() == (b / f["file"]).read_bytes()


# -- the uninterrupted sweep ----------------------------------------------------------------
def test_full_sweep_writes_measured_z_and_frames(fake, frames_dir, tmp_path):
    progress = []
    with GrblStage(stage_config(), port=fake.port) as stage, FolderCamera(frames_dir) as cam:
        res = run_sweep(stage, cam, tmp_path / "s", sweep=SWEEP, mapping=MAPPING,
                        pixel_size_mm=0.01, rig_sha256="abc",
                        progress=lambda d, t: progress.append((d, t)))
    assert res.complete and res.n_frames == 11 and res.n_new == 11
    assert progress[0] == (0, 11) and progress[-1] == (11, 11)
    stack = FocalStack.open(tmp_path / "s")
    np.testing.assert_allclose(stack.z_mm, np.arange(11) * 0.02, atol=1e-9)
    doc = manifest(tmp_path / "s")
    assert doc["meta"]["complete"] is True and doc["meta"]["rig_sha256"] == "abc"
    assert doc["rig"]["step_mm"] == 0.02 and doc["pixel_size_mm"] == 0.01
    for f in doc["frames"]:
        assert f["z_mm"] == pytest.approx(5.0 + f["machine_z_mm"], abs=1e-12)
    imgs = sorted(frames_dir.iterdir())
    for n, (_, z, img) in enumerate(stack.iter_frames()):
        np.testing.assert_array_equal(img, read_image(imgs[n]))


def test_recorded_z_is_measured_not_commanded(fake, frames_dir, tmp_path):
    # 0.0213 mm is not a whole number of 2.5 µm motor steps: the stack must carry the
    # positions the controller reports, not the planned ones
    sweep = SweepConfig(z_start_mm=0.0, z_stop_mm=0.2, step_mm=0.0213)
    sweep_with(fake, tmp_path / "s", frames_dir, sweep=sweep)
    doc = manifest(tmp_path / "s")
    targets = np.array([f["target_z_mm"] for f in doc["frames"]])
    z = np.array([f["z_mm"] for f in doc["frames"]])
    machine = np.array([f["machine_z_mm"] for f in doc["frames"]])
    quantised = np.round((targets - 5.0) * 400) / 400
    np.testing.assert_allclose(machine, quantised, atol=6e-4)  # reported to 3 decimals
    np.testing.assert_allclose(z, machine + 5.0, atol=1e-12)
    assert np.max(np.abs(z - targets)) > 5e-4  # measured really differs from planned


def test_backlash_order_from_below(fake, frames_dir, tmp_path):
    sweep_with(fake, tmp_path / "s", frames_dir)
    planned = [round(-5.0 + 0.02 * i, 4) for i in range(11)]
    # fake started at -1.0 (above): overshoot below the first frame, then only upward moves
    assert fake.moves == [-5.1] + planned


def test_backlash_order_downward_sweep(frames_dir, tmp_path):
    sweep = SweepConfig(z_start_mm=0.2, z_stop_mm=0.0, step_mm=0.02, backlash_mm=0.1)
    with FakeGrbl(start_z_mm=-6.0, **FAST) as fake:
        sweep_with(fake, tmp_path / "s", frames_dir, sweep=sweep)
        planned = [round(-4.8 - 0.02 * i, 4) for i in range(11)]
        assert fake.moves == [-4.7] + planned
    stack = FocalStack.open(tmp_path / "s")  # stored descending, served ascending
    np.testing.assert_allclose(stack.z_mm, np.arange(11) * 0.02, atol=1e-9)


def test_stage_that_does_not_advance_is_an_error(fake, frames_dir, tmp_path):
    sweep = SweepConfig(z_start_mm=0.0, z_stop_mm=0.004, step_mm=0.001)  # < 1 motor step
    with pytest.raises(StageError, match="stage did not advance: frame 1"):
        sweep_with(fake, tmp_path / "s", frames_dir, sweep=sweep)


# -- faults mid-sweep, then resume -----------------------------------------------------------
@pytest.fixture
def reference(frames_dir, tmp_path):
    """An uninterrupted sweep to compare resumed ones with."""
    with FakeGrbl(start_z_mm=-1.0, **FAST) as fake:
        sweep_with(fake, tmp_path / "ref", frames_dir)
    return tmp_path / "ref"


@pytest.mark.parametrize("kind, match, kept", [
    ("alarm", r"ALARM:1 \(hard limit", 4),
    ("timeout", "timed out after 0.5 s waiting for the reply to 'G1 Z-4.9200", 4),
    ("error", r"error:33", 4),
    ("disconnect", "lost the connection", 4),
])
def test_fault_mid_sweep_keeps_frames_and_resume_completes(kind, match, kept, frames_dir,
                                                           tmp_path, reference):
    out = tmp_path / "s"
    with FakeGrbl(start_z_mm=-1.0, **FAST) as fake:
        fake.inject(kind, at_move=6)  # move 1 = overshoot, move k+2 = frame k -> frame 4
        with pytest.raises(StageError, match=match):
            sweep_with(fake, out, frames_dir)
        if kind != "disconnect":
            assert wait_for(lambda: fake.feed_holds >= 1)  # the stage was told to stop
    doc = assert_intact(out)
    assert len(doc["frames"]) == kept and doc["meta"]["complete"] is False
    # a fresh controller (after a reset/power cycle) finishes the stack
    with FakeGrbl(start_z_mm=-3.0, **FAST) as fake2:
        res = sweep_with(fake2, out, frames_dir, resume=True)
        assert fake2.moves[0] == round(-4.92 - 0.1, 4)  # overshoot again before frame 4
    assert res.complete and res.n_new == 11 - kept
    assert_same_stack(out, reference)


def test_resume_on_same_controller_after_alarm_needs_unlock(frames_dir, tmp_path, reference):
    out = tmp_path / "s"
    with FakeGrbl(start_z_mm=-1.0, **FAST) as fake:
        fake.inject("alarm", at_move=9)
        with pytest.raises(StageError, match="ALARM:1"):
            sweep_with(fake, out, frames_dir)
        with pytest.raises(StageError, match="in ALARM after reset"):
            sweep_with(fake, out, frames_dir, resume=True)
        sweep_with(fake, out, frames_dir, resume=True, unlock=True)
    assert_same_stack(out, reference)


def test_ctrl_c_sends_feed_hold_keeps_frames_and_resumes(fake, frames_dir, tmp_path, reference):
    # a test run started in the background by a shell has SIGINT ignored: restore what an
    # interactive terminal gives (Ctrl-C raises KeyboardInterrupt)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _ctrl_c_at_fifth(fake, frames_dir, tmp_path, reference)
    finally:
        signal.signal(signal.SIGINT, previous)


def _ctrl_c_at_fifth(fake, frames_dir, tmp_path, reference):
    class CtrlCAtFifth(FolderCamera):
        def capture(self):
            if self._next == 5:
                os.kill(os.getpid(), signal.SIGINT)  # what a Ctrl-C in the terminal does
            return super().capture()

    out = tmp_path / "s"
    with pytest.raises(KeyboardInterrupt):
        sweep_with(fake, out, frames_dir, camera=CtrlCAtFifth(frames_dir))
    assert wait_for(lambda: fake.feed_holds >= 1)
    doc = assert_intact(out)
    assert len(doc["frames"]) == 5
    sweep_with(fake, out, frames_dir, resume=True)
    assert_same_stack(out, reference)


def test_wrong_frame_size_mid_sweep(fake, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    make_frames(folder, 12)
    smdinspect._atomic.write_image(folder / "img_006.png", np.zeros((40, 64), np.uint8))
    with pytest.raises(CameraError, match="64x40 grey uint8 frame at frame 6; earlier frames "
                                          "are 64x48 grey uint8"):
        sweep_with(fake, tmp_path / "s", folder)
    assert len(assert_intact(tmp_path / "s")["frames"]) == 6
    assert wait_for(lambda: fake.feed_holds >= 1)


def test_disk_full_is_one_clear_error_and_resumable(fake, frames_dir, tmp_path, monkeypatch,
                                                    reference):
    real = smdinspect._atomic.write_image
    calls = []

    def full_after_three(path, image):
        calls.append(path)
        if len(calls) > 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, image)

    out = tmp_path / "s"
    monkeypatch.setattr(smdinspect._atomic, "write_image", full_after_three)
    with pytest.raises(OSError, match=r"no space left on device: .*s \(frame 3\); the 3 frames "
                                      r"before it are kept: free space and run again with --resume"
                       ) as ei:
        sweep_with(fake, out, frames_dir)
    assert ei.value.errno == errno.ENOSPC
    assert len(assert_intact(out)["frames"]) == 3
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temp file left
    monkeypatch.setattr(smdinspect._atomic, "write_image", real)
    sweep_with(fake, out, frames_dir, resume=True)
    assert_same_stack(out, reference)


# -- resume rules ------------------------------------------------------------------------------
def test_resume_rules(fake, frames_dir, tmp_path):
    out = tmp_path / "s"
    with pytest.raises(InputError, match="nothing to resume"):
        sweep_with(fake, out, frames_dir, resume=True)
    fake.inject("error", at_move=4)
    with pytest.raises(StageError):
        sweep_with(fake, out, frames_dir)
    with pytest.raises(InputError, match="already holds a stack.*--resume"):
        sweep_with(fake, out, frames_dir)
    n_moves = len(fake.moves)
    with pytest.raises(InputError, match=r"rig file \(stage, camera, optics or sweep\) changed"):
        sweep_with(fake, out, frames_dir, resume=True, sha="rig-b")
    assert len(fake.moves) == n_moves  # refused before moving
    # a leftover temp file and an unlisted frame from a killed run are cleaned up
    (out / ".frame_0002.abc123.png").write_bytes(b"\x89PNG partial")
    (out / ".stack.k2j4h5.json").write_text('{"frames": [')
    (out / "frame_0002.png").write_bytes((out / "frame_0000.png").read_bytes())
    res = sweep_with(fake, out, frames_dir, resume=True)
    assert res.complete and res.n_new == 9
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]
    # resuming a complete stack does nothing
    res = sweep_with(fake, out, frames_dir, resume=True)
    assert res.n_new == 0 and res.n_frames == 11


def test_frames_per_step_averaging(fake, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    imgs = make_frames(folder, 6, seed=3)
    sweep = SweepConfig(z_start_mm=0.0, z_stop_mm=0.04, step_mm=0.02, frames_per_step=2)
    sweep_with(fake, tmp_path / "s", folder, sweep=sweep)
    stack = FocalStack.open(tmp_path / "s")
    for n, (_, _, img) in enumerate(stack.iter_frames()):
        mean = (imgs[2 * n].astype(np.float64) + imgs[2 * n + 1]) / 2
        np.testing.assert_array_equal(img, np.rint(mean).astype(np.uint8))


def test_sweep_config_validation():
    assert SweepConfig(z_start_mm=1.0, z_stop_mm=0.0, step_mm=0.25).n_frames == 5
    np.testing.assert_allclose(SweepConfig(z_start_mm=0, z_stop_mm=0.1, step_mm=0.05)
                               .z_positions_mm(), [0, 0.05, 0.1])
    with pytest.raises(InputError, match="step_mm must be > 0; got -0.1"):
        SweepConfig(z_start_mm=0, z_stop_mm=1, step_mm=-0.1)
    with pytest.raises(InputError, match="gives 2 frame\\(s\\); a stack needs >= 3"):
        SweepConfig(z_start_mm=0, z_stop_mm=0.1, step_mm=0.1)
    with pytest.raises(InputError, match="frames_per_step must be an integer >= 1; got 0"):
        SweepConfig(z_start_mm=0, z_stop_mm=1, step_mm=0.1, frames_per_step=0)
    with pytest.raises(InputError, match="direction must be 1 or -1; got 2"):
        ZMapping(direction=2)
    m = ZMapping(focus_offset_mm=3.0, direction=-1)
    assert m.z_mm(m.machine_z_mm(0.7)) == pytest.approx(0.7) and m.machine_z_mm(0.0) == 3.0
