"""The fake GRBL at the byte level, through a plain pyserial port on its pty."""

from __future__ import annotations

import time

import pytest
import serial

from smdinspect.acquire import FakeGrbl
from smdinspect.errors import InputError

from .conftest import FAST


class Term:
    """A minimal terminal: send a line or a real-time byte, read reply lines."""

    def __init__(self, port):
        self.ser = serial.serial_for_url(port, baudrate=115200, timeout=0.5)

    def send(self, text: str | bytes) -> None:
        self.ser.write(text if isinstance(text, bytes) else text.encode() + b"\n")

    def line(self) -> str:
        raw = self.ser.readline()
        assert raw.endswith(b"\r\n"), f"no complete line: {raw!r}"
        return raw.decode().strip()

    def ask(self, text) -> list[str]:
        """Send, then read lines up to and including ok / error:N."""
        self.send(text)
        out = []
        while True:
            out.append(self.line())
            if out[-1] == "ok" or out[-1].startswith(("error:", "ALARM:")):
                return out

    def status(self) -> str:
        self.send(b"?")
        return self.line()


@pytest.fixture
def term():
    with FakeGrbl(start_z_mm=-1.0, **FAST) as fake:
        t = Term(fake.port)
        yield fake, t
        t.ser.close()


def test_reset_greeting_and_status(term):
    fake, t = term
    t.send(b"\x18")
    assert [t.line(), t.line()] == ["", "Grbl 1.1h ['$' for help]"]
    assert t.status() == "<Idle|MPos:0.000,0.000,-1.000|FS:0,0>"
    assert t.ask("$I") == ["[VER:1.1h.20190825:smdinspect-fake]", "[OPT:V,15,128]", "ok"]
    assert "$102=400.000" in t.ask("$$")


def test_motion_takes_time_and_reports_run(term):
    fake, t = term
    t0 = time.monotonic()
    assert t.ask("G1 Z-3 F1200") == ["ok"]  # 20 mm/s over 2 mm: 0.1 s
    assert t.status().startswith("<Run|MPos:0.000,0.000,-")
    while not t.status().startswith("<Idle"):
        time.sleep(0.005)
    assert 0.09 < time.monotonic() - t0 < 0.5
    assert t.status() == "<Idle|MPos:0.000,0.000,-3.000|FS:0,0>"
    assert t.ask("G91 G0 Z0.5") == ["ok"]  # relative, rapid
    time.sleep(0.05)
    assert fake.machine_z_mm == -2.5


def test_dwell_and_homing_reply_only_when_done(term):
    fake, t = term
    t.ask("G1 Z-2 F600")  # 10 mm/s: 0.1 s
    t0 = time.monotonic()
    assert t.ask("G4 P0.05") == ["ok"]  # ok after the move AND the dwell
    assert time.monotonic() - t0 > 0.14
    assert t.ask("$H") == ["error:5"]  # homing not enabled on this controller


def test_errors_alarms_and_lockout(term):
    fake, t = term
    assert t.ask("G1 Z-2") == ["error:22"]  # no feed rate yet
    assert t.ask("G38.2 Z-2") == ["error:20"]
    assert t.ask("G1 Z-2 Z-3 F100") == ["error:25"]
    assert t.ask("G1 Z-") == ["error:2"]  # ("?" would be the real-time status query)
    assert t.ask("$Q") == ["error:3"]
    # a soft reset while moving loses position: ALARM:3, then G-code is locked out
    t.ask("G1 Z-10 F600")
    time.sleep(0.05)
    t.send(b"\x18")
    assert [t.line() for _ in range(4)] == ["ALARM:3", "", "Grbl 1.1h ['$' for help]",
                                            "[MSG:'$H'|'$X' to unlock]"]
    assert t.ask("G1 Z-1 F600") == ["error:9"]
    assert t.ask("$X") == ["[MSG:Caution: Unlocked]", "ok"]
    assert t.status().startswith("<Idle")


def test_feed_hold_and_resume(term):
    fake, t = term
    t.ask("G1 Z-5 F600")
    time.sleep(0.05)
    t.send(b"!")
    time.sleep(0.02)
    held = t.status()
    assert held.startswith("<Hold:0|")
    z = fake.machine_z_mm
    time.sleep(0.05)
    assert fake.machine_z_mm == z
    t.send(b"~")
    time.sleep(0.02)
    assert t.status().startswith("<Run|")
    assert fake.realtime == ["!", "~"]


def test_fake_soft_limits_alarm():
    with FakeGrbl(soft_limits_mm=(-5.0, 0.0), **FAST) as fake:
        t = Term(fake.port)
        assert t.ask("G0 Z-6") == ["ALARM:2"]
        assert fake.state == "Alarm" and fake.moves == []
        t.ser.close()


def test_fake_validation():
    with pytest.raises(InputError, match="fault kind must be one of alarm, disconnect, error, "
                                         "timeout; got 'fire'"):
        FakeGrbl().inject("fire")
    with pytest.raises(InputError, match="steps_per_mm must be > 0"):
        FakeGrbl(steps_per_mm=0)
