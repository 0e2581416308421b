"""GRBL protocol over pyserial against the fake controller on a real pty."""

from __future__ import annotations

import time

import pytest
import serial

from smdinspect.acquire import FakeGrbl, GrblStage, parse_status
from smdinspect.errors import InputError, StageError

from .conftest import FAST, stage_config


# -- status reports -------------------------------------------------------------------
def test_parse_status_mpos():
    st, wco = parse_status("<Run|MPos:1.000,-2.500,-3.125|FS:500,0>")
    assert (st.state, st.machine_z_mm, wco) == ("Run", -3.125, None)
    st, _ = parse_status("<Hold:0|MPos:0.000,0.000,4.000|FS:0,0>")
    assert st.state == "Hold"


def test_parse_status_wpos_needs_wco():
    with pytest.raises(StageError, match=r"\$10=1"):
        parse_status("<Idle|WPos:0.000,0.000,1.000|FS:0,0>")
    st, wco = parse_status("<Idle|WPos:0.000,0.000,1.000|FS:0,0|WCO:0.000,0.000,-5.000>")
    assert st.machine_z_mm == -4.0 and wco == (0.0, 0.0, -5.0)
    # later reports carry WPos only; the remembered WCO converts them
    st, _ = parse_status("<Idle|WPos:0.000,0.000,2.000|FS:0,0>", wco=wco)
    assert st.machine_z_mm == -3.0


@pytest.mark.parametrize("bad", ["Idle|MPos:0,0,0", "<Idle|MPos:a,b,c>", "<Idle|FS:0,0>",
                                 "<Idle|MPos:1.0,2.0>"])
def test_parse_status_malformed(bad):
    with pytest.raises(StageError):
        parse_status(bad)


# -- round trips ------------------------------------------------------------------------
def test_connect_greeting_and_modes(fake, stage):
    assert stage.version == "1.1h"
    assert fake.realtime[0] == "\x18"  # no greeting seen: soft reset sent
    assert fake.lines[:2] == ["G21", "G90"]
    assert stage.position() == -1.0


def test_move_waits_for_idle_and_reads_back(fake, stage):
    t0 = time.monotonic()
    z = stage.move_to(-11.0, feed_mm_min=6000.0)  # 10 mm at 100 mm/s: ~0.1 s
    elapsed = time.monotonic() - t0
    assert z == -11.0 and fake.machine_z_mm == -11.0
    assert 0.09 <= elapsed < 1.0
    assert fake.lines[-1] == "G1 Z-11.0000 F6000.0"
    assert stage.status().state == "Idle"


def test_position_is_quantised_to_motor_steps(fake, stage):
    # 400 steps/mm: -2.0013 is not a whole step; the controller stops at the nearest
    # step, -2.0025, and reports it with three decimals, as GRBL does
    z = stage.move_to(-2.0013)
    assert fake.machine_z_mm == -2.0025
    assert z in (-2.002, -2.003)


def test_commands_and_error_meaning(fake, stage):
    stage.command("G91")
    stage.command("G1 Z-0.5 F600")
    assert stage.wait_idle() == -1.5
    stage.command("G90")
    with pytest.raises(StageError, match=r"error:20 \(unsupported"):
        stage.command("G38.2 Z-5")
    with pytest.raises(StageError, match="error:3"):
        stage.command("$NOPE")


def test_feed_hold_stops_motion(fake, stage):
    stage._send_move(-15.0, feed_mm_min=600.0)  # 10 mm/s: takes 1.4 s
    time.sleep(0.1)
    stage.stop()
    time.sleep(0.05)
    st = stage.status()
    assert st.state == "Hold"
    z = st.machine_z_mm
    time.sleep(0.1)
    assert stage.position() == z  # really stopped
    assert -3.0 < z < -1.5
    assert fake.feed_holds == 1


def test_homing_from_alarm():
    with FakeGrbl(homing=True, start_z_mm=-7.0, home_z_mm=-0.5, **FAST) as fake:
        with GrblStage(stage_config(home=True), port=fake.port) as st:
            assert st.position() == -0.5
        assert "$H" in fake.lines


def test_alarm_at_start_needs_home_or_unlock():
    with FakeGrbl(homing=True, **FAST) as fake:
        with pytest.raises(StageError, match="ALARM after reset.*home = true"):
            GrblStage(stage_config(), port=fake.port).open()
        with GrblStage(stage_config(unlock=True), port=fake.port) as st:
            assert st.status().state == "Idle"
        assert "$X" in fake.lines


# -- soft limits --------------------------------------------------------------------------
def test_soft_limit_refused_before_sending(fake, stage):
    n = len(fake.lines)
    with pytest.raises(StageError, match=r"outside the soft limits -20.0 .. 0.0"):
        stage.move_to(0.5)
    with pytest.raises(StageError, match="soft limits"):
        stage.approach(-19.95, direction=1, backlash_mm=0.1)  # comes up from -20.05
    assert len(fake.lines) == n  # nothing was sent


def test_stage_config_validation():
    with pytest.raises(InputError, match="z_min_mm < z_max_mm"):
        stage_config(z_min_mm=1.0, z_max_mm=0.0)
    with pytest.raises(InputError, match="protocol must be one of grbl"):
        stage_config(protocol="marlin")
    with pytest.raises(InputError, match="port is empty"):
        stage_config(fake=False, port="")
    with pytest.raises(InputError, match="timeout_s must be > 0; got 0"):
        stage_config(timeout_s=0)


# -- backlash ------------------------------------------------------------------------------
def test_backlash_approach_always_from_same_side(fake, stage):
    # fake starts at -1.0; approach from above (direction -1 = moving down)
    for target in (-3.0, -3.2, -3.4, -2.0, -2.2):
        assert stage.approach(target, direction=-1, backlash_mm=0.25) == target
    # -3.0 is below: down directly is wrong only if the last motion was unknown -> overshoot
    assert fake.moves == [-2.75, -3.0, -3.2, -3.4, -1.75, -2.0, -2.2]
    # every frame position is reached by a downward move
    prev = -1.0
    for z in fake.moves:
        if z in (-3.0, -3.2, -3.4, -2.0, -2.2):
            assert z < prev
        prev = z


# -- faults -----------------------------------------------------------------------------
def test_timeout_names_what_it_waited_for(fake, stage):
    fake.inject("timeout", at_move=1)
    t0 = time.monotonic()
    with pytest.raises(StageError, match=r"timed out after 0.5 s waiting for the reply to "
                                         r"'G1 Z-2.0000"):
        stage.move_to(-2.0)
    assert 0.45 < time.monotonic() - t0 < 1.5


def test_error_reply(fake, stage):
    fake.inject("error", at_move=2, code=33)
    stage.move_to(-2.0)
    with pytest.raises(StageError, match=r"rejected 'G1 Z-3.0000 F12000.0': error:33 "
                                         r"\(invalid motion target\)"):
        stage.move_to(-3.0)
    assert fake.machine_z_mm == -2.0


def test_alarm_mid_move(fake, stage):
    fake.inject("alarm", at_move=1, code=1, fraction=0.5)
    with pytest.raises(StageError, match=r"ALARM:1 \(hard limit"):
        stage.move_to(-11.0)  # 10 mm at 200 mm/s, alarm after ~25 ms
    assert fake.state == "Alarm"
    assert -9.0 < fake.machine_z_mm < -3.0  # stopped half-way


def test_disconnect_mid_move(fake, stage):
    fake.inject("disconnect", at_move=1, fraction=0.3)
    with pytest.raises(StageError, match="lost the connection"):
        stage.move_to(-11.0)
    stage.stop()  # must not raise on a dead port
    stage.close()


def test_no_greeting():
    with FakeGrbl(greeting=False, **FAST) as fake:
        t0 = time.monotonic()
        with pytest.raises(StageError, match=r"no GRBL greeting from /dev/pts/\d+ within 0.5 s"):
            GrblStage(stage_config(), port=fake.port).open()
        assert time.monotonic() - t0 < 1.5


def test_port_missing():
    with pytest.raises(StageError, match="stage port /dev/ttyNOPE0 not found"):
        GrblStage(stage_config(port="/dev/ttyNOPE0", fake=False)).open()


def test_port_busy(fake):
    holder = serial.serial_for_url(fake.port, baudrate=115200, exclusive=True)
    try:
        with pytest.raises(StageError, match=r"stage port /dev/pts/\d+ is busy"):
            GrblStage(stage_config(), port=fake.port).open()
    finally:
        holder.close()


def test_socket_url_is_accepted_and_refused_cleanly():
    # any pyserial URL: nothing listens on this port -> one clear StageError
    with pytest.raises(StageError, match="cannot open stage port socket://127.0.0.1:9"):
        GrblStage(stage_config(port="socket://127.0.0.1:9", fake=False)).open()
