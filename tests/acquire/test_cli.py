"""``smdinspect acquire``: exit codes, one-line errors, and a SIGKILL mid-sweep."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from smdinspect.cli import main
from smdinspect.stack import FocalStack, read_image

from .rigs import sim_rig

REPO = Path(__file__).parents[2]


def run_cli(capsys, *argv):
    code = main(["-q", "acquire", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err.strip()


def frames_and_z(out):
    doc = json.loads((out / "stack.json").read_text())
    return [(f["file"], f["z_mm"], (out / f["file"]).read_bytes()) for f in doc["frames"]]


def test_acquire_sim_rig_exit_0(tmp_path, capsys):
    code = main(["acquire", "--rig", str(sim_rig(tmp_path / "rig.toml")),
                 "--out", str(tmp_path / "s")])
    out, _ = capsys.readouterr()
    assert code == 0
    assert "19 frames (19 new), z_mm -0.1500 .. 0.7500" in out
    assert len(FocalStack.open(tmp_path / "s")) == 19


def test_shipped_sim_rig_works(tmp_path, capsys):
    rc, out, err = run_cli(capsys, "--rig", REPO / "examples" / "sim_rig.toml", "--out",
                           tmp_path / "s")
    assert rc == 0, err
    stack = FocalStack.open(tmp_path / "s")
    assert len(stack) == 19 and stack.pixel_size_mm == 0.015


@pytest.mark.parametrize("case, code, message", [
    ("missing_rig", 2, "rig file not found"),
    ("bad_rig", 2, r"unknown key(s) stepp_mm in [sweep]"),
    ("port_missing", 4, "stage port /dev/ttyNOPE9 not found"),
    ("camera_missing", 4, "camera '/dev/no-such-video' not found or busy"),
    ("alarm", 4, "controller ALARM:1 (hard limit switch triggered"),
    ("timeout", 4, "timed out after 1 s waiting for the reply to 'G1 Z-5.0500"),
])
def test_errors_exit_code_and_one_line(case, code, message, tmp_path, capsys):
    rig = sim_rig(tmp_path / "rig.toml")
    text = rig.read_text()
    if case == "missing_rig":
        rig = tmp_path / "none.toml"
    elif case == "bad_rig":
        rig.write_text(text.replace("step_mm = 0.05", "step_mm = 0.05\nstepp_mm = 1"))
    elif case == "port_missing":
        text = text.replace("[stage.fake]", "[unused]").replace("[unused]\n", "")
        for key in ("steps_per_mm = 400.0\n", "max_rate_mm_s = 200.0\n", "start_z_mm = 0.0\n"):
            text = text.replace(key, "")
        rig.write_text(text.replace('protocol = "grbl"', 'protocol = "grbl"\n'
                                                        'port = "/dev/ttyNOPE9"'))
    elif case == "camera_missing":
        rig.write_text(text.replace('kind = "simulated"', 'kind = "opencv"\n'
                                                          'device = "/dev/no-such-video"')
                       .replace('scene = "cone"\n', "").replace("seed = 7\n", "")
                       .replace('sensor = "low"\n', "")
                       .replace("[camera.scene_options]\nsize_px = 64\npixel_size_mm = 0.015\n"
                                "height_mm = 0.6\n", ""))
    elif case == "alarm":
        rig = sim_rig(rig, faults='faults = [{kind = "alarm", at_move = 4}]')
    elif case == "timeout":
        rig = sim_rig(rig, faults='faults = [{kind = "timeout", at_move = 4}]')
    rc, out, err = run_cli(capsys, "--rig", rig, "--out", tmp_path / "s")
    assert rc == code, err
    assert err.count("\n") == 0, err  # one line
    assert err.startswith("smdinspect acquire: error: ")
    assert message in err
    if case in ("alarm", "timeout"):
        # frames before the fault are intact and listed
        doc = json.loads((tmp_path / "s" / "stack.json").read_text())
        assert len(doc["frames"]) == 2
        for f in doc["frames"]:
            read_image(tmp_path / "s" / f["file"])


def test_resume_via_cli(tmp_path, capsys):
    ref = tmp_path / "ref"
    assert run_cli(capsys, "--rig", sim_rig(tmp_path / "r0.toml"), "--out", ref)[0] == 0
    rig = sim_rig(tmp_path / "rig.toml", faults='faults = [{kind = "alarm", at_move = 9}]')
    out = tmp_path / "s"
    assert run_cli(capsys, "--rig", rig, "--out", out)[0] == 4
    rc, _, err = run_cli(capsys, "--rig", rig, "--out", out)
    assert rc == 2 and "already holds a stack" in err and "--resume" in err
    changed = sim_rig(tmp_path / "changed.toml", z_stop=0.8)
    rc, _, err = run_cli(capsys, "--rig", changed, "--out", out, "--resume")
    assert rc == 2 and "changed since this stack was started" in err
    sim_rig(rig)  # the same rig, fault removed
    rc, _, err = run_cli(capsys, "--rig", rig, "--out", out, "--resume")
    assert rc == 0, err
    assert frames_and_z(out) == frames_and_z(ref)


def test_sigkill_mid_sweep_leaves_no_corrupt_frame_and_resumes(tmp_path, capsys):
    """Kill a real `smdinspect acquire` process six times, at different moments of a frame
    (moving, settling, rendering, writing); every time the stack on disk is intact, and
    --resume finally completes it exactly like an uninterrupted sweep."""
    ref = tmp_path / "ref"
    assert run_cli(capsys, "--rig", sim_rig(tmp_path / "r0.toml", size=96), "--out", ref)[0] == 0
    rig = sim_rig(tmp_path / "rig.toml", size=96, settle=0.02)
    out = tmp_path / "s"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    killed_at = []
    for attempt, (kill_after, delay_s) in enumerate([(2, 0.0), (4, 0.006), (6, 0.012),
                                                     (8, 0.018), (10, 0.024), (12, 0.03)]):
        argv = [sys.executable, "-m", "smdinspect", "-q", "acquire", "--rig", str(rig),
                "--out", str(out)] + (["--resume"] if attempt else [])
        proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                if len(json.loads((out / "stack.json").read_text())["frames"]) >= kill_after:
                    break
            except (FileNotFoundError, json.JSONDecodeError, KeyError):
                pass
            time.sleep(0.002)
        time.sleep(delay_s)  # land somewhere inside the next frame
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()
        proc.stderr.close()
        doc = json.loads((out / "stack.json").read_text())  # always valid JSON
        killed_at.append(len(doc["frames"]))
        for f in doc["frames"]:  # every listed frame decodes
            assert read_image(out / f["file"]).shape == (96, 96)
        for p in out.glob("frame_*"):  # nothing partial under a final name
            read_image(p)
    assert killed_at == sorted(killed_at) and 12 <= killed_at[-1] < 19, killed_at
    rc, _, err = run_cli(capsys, "--rig", rig, "--out", out, "--resume")
    assert rc == 0, err
    assert frames_and_z(out) == frames_and_z(ref)
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]


def test_ctrl_c_exits_130_and_keeps_frames(tmp_path, capsys):
    rig = sim_rig(tmp_path / "rig.toml", settle=0.03)
    out = tmp_path / "s"
    # SIG_DFL: a test run started in the background by a shell inherits SIGINT ignored,
    # and so would the child (Python installs its handler only when SIGINT is not ignored)
    proc = subprocess.Popen([sys.executable, "-m", "smdinspect", "-q", "acquire", "--rig",
                             str(rig), "--out", str(out)],
                            env={**os.environ, "PYTHONPATH": str(REPO)},
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if len(json.loads((out / "stack.json").read_text())["frames"]) >= 3:
                break
        except (FileNotFoundError, json.JSONDecodeError):
            pass
        time.sleep(0.005)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 130, err.decode()
    assert err.decode().strip() == "smdinspect acquire: interrupted; finished work was kept"
    kept = json.loads((out / "stack.json").read_text())["frames"]
    assert 3 <= len(kept) < 19
    rc, _, err = run_cli(capsys, "--rig", rig, "--out", out, "--resume")
    assert rc == 0, err
    assert len(FocalStack.open(out)) == 19
