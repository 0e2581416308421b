"""GRBL 1.1 protocol over pyserial: the first :class:`~smdinspect.acquire.Stage`.

What is used of GRBL (see the GRBL 1.1 interface documentation):

* the greeting ``Grbl 1.1h ['$' for help]`` after a reset (Ctrl-X, byte 0x18);
* ``$H`` homing, ``$X`` unlock, ``G21`` mm, ``G90`` absolute, ``G1 Z.. F..`` moves;
* the real-time status query ``?`` answered with ``<Idle|MPos:x,y,z|...>`` (or
  ``WPos`` plus a ``WCO`` offset);
* replies ``ok``, ``error:N`` and asynchronous ``ALARM:N``;
* the real-time feed hold ``!``.

Each command waits for its ``ok``; each move is followed by status queries until the
controller is ``Idle`` at the target. Every read has a deadline: a silent controller
gives a :class:`~smdinspect.errors.StageError` naming what it was waiting for.
"""

from __future__ import annotations

import logging
import re
import time

from ..errors import StageError
from ._stage import Stage, StageConfig, StageStatus

__all__ = ["ALARM_MEANINGS", "ERROR_MEANINGS", "GrblStage", "parse_status"]

log = logging.getLogger(__name__)

#: Meanings of GRBL 1.1 ``error:N`` codes (the ones a z stage can meet).
ERROR_MEANINGS = {
    1: "G-code words need a letter and a value; the letter was not found",
    2: "bad or missing numeric value",
    3: "'$' system command not recognised or not supported",
    4: "negative value where a positive one was expected",
    5: "homing is not enabled in the controller settings ($22)",
    8: "'$' command only allowed when the controller is Idle",
    9: "G-code locked out during ALARM or jog state (home with $H or unlock with $X)",
    11: "line too long",
    15: "jog target exceeds machine travel",
    20: "unsupported or invalid G-code command",
    21: "two G-code commands of the same modal group in one block",
    22: "feed rate not set",
    24: "two G-code commands both need the axis words",
    25: "a G-code word was repeated in the block",
    26: "the command needs axis words and none were given",
    33: "invalid motion target",
}

#: Meanings of GRBL 1.1 ``ALARM:N`` codes.
ALARM_MEANINGS = {
    1: "hard limit switch triggered; position lost, re-home",
    2: "soft limit: target exceeds machine travel",
    3: "reset while in motion; position lost, re-home",
    4: "probe fail: probe not in the expected initial state",
    5: "probe fail: probe did not contact",
    6: "homing fail: reset during homing",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: could not clear the limit switch on pull-off",
    9: "homing fail: limit switch not found within the search distance",
}

try:  # a POSIX port whose device vanished fails in tcdrain() with termios.error
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - Windows
    class _TermiosError(Exception):  # type: ignore[no-redef]
        pass

_GREETING = re.compile(r"^Grbl(?:HAL)?\s+(\S+)", re.IGNORECASE)
_CODE = re.compile(r"^(error|ALARM):\s*(\d+)", re.IGNORECASE)


def parse_status(report: str, *, wco: tuple[float, ...] | None = None) -> tuple[StageStatus, tuple[float, ...] | None]:
    """Parse a GRBL 1.1 status report ``<State|MPos:x,y,z|...>``.

    Parameters
    ----------
    report : str
        One report line, with its angle brackets.
    wco : tuple of float or None
        The last work-coordinate offset seen; needed when the report carries ``WPos``.

    Returns
    -------
    status : StageStatus
    wco : tuple of float or None
        The offset to remember (updated when the report carries ``WCO``).

    Raises
    ------
    StageError
        Malformed report, or ``WPos`` without any known ``WCO``.
    """
    text = report.strip()
    if not (text.startswith("<") and text.endswith(">")):
        raise StageError(f"malformed GRBL status report {report!r}")
    fields = text[1:-1].split("|")
    state = fields[0].split(":")[0]
    mpos = wpos = None
    for field in fields[1:]:
        key, _, value = field.partition(":")
        try:
            numbers = tuple(float(v) for v in value.split(","))
        except ValueError:
            if key in ("MPos", "WPos", "WCO"):
                raise StageError(f"malformed {key} in GRBL status report {report!r}") from None
            continue
        if key == "MPos":
            mpos = numbers
        elif key == "WPos":
            wpos = numbers
        elif key == "WCO":
            wco = numbers
    if mpos is None and wpos is not None:
        if wco is None:
            raise StageError(
                "GRBL reports WPos without a WCO offset; set $10=1 on the controller so it "
                "reports machine positions (MPos)"
            )
        mpos = tuple(w + o for w, o in zip(wpos, wco))
    if mpos is None or len(mpos) < 3:
        raise StageError(f"GRBL status report {report!r} has no Z position")
    return StageStatus(state=state, machine_z_mm=float(mpos[2]), raw=text), wco


class GrblStage(Stage):
    """A z stage behind a GRBL 1.1 compatible controller.

    Parameters
    ----------
    config : StageConfig
    port : str, optional
        Overrides ``config.port`` (the simulated rig passes its fake's pty here).
    """

    def __init__(self, config: StageConfig, *, port: str | None = None) -> None:
        super().__init__(config)
        self._port = port if port is not None else config.port
        self._ser = None
        self._buf = b""
        self._wco: tuple[float, ...] | None = None
        self._target: float | None = None
        self.version: str | None = None

    @property
    def port(self) -> str:
        return self._port

    # -- connection -----------------------------------------------------------------
    def open(self) -> None:
        """Open the port, wait for the greeting, home or unlock, select mm + absolute."""
        import serial

        c = self.config
        try:
            self._ser = serial.serial_for_url(
                self._port, baudrate=c.baud, timeout=0.05, write_timeout=c.timeout_s,
                exclusive=True,
            )
        except (serial.SerialException, OSError, ValueError, _TermiosError) as exc:
            raise StageError(_open_error(self._port, exc)) from None
        try:
            self._connect()
        except BaseException:
            self.stop()
            self.close()
            raise

    def _connect(self) -> None:
        c = self.config
        self.version = self._wait_greeting(c.boot_wait_s) if c.boot_wait_s > 0 else None
        if self.version is None:
            log.debug("no greeting yet; sending soft reset (Ctrl-X)")
            self._write(b"\x18")
            self.version = self._wait_greeting(c.timeout_s)
        if self.version is None:
            raise StageError(
                f"no GRBL greeting from {self._port} within {c.timeout_s:g} s after a soft "
                f"reset: is a GRBL controller connected there, at {c.baud} baud?"
            )
        log.info("connected to Grbl %s on %s", self.version, self._port)
        status = self.status()
        if c.home:
            self.home()
        elif status.state == "Alarm":
            if not c.unlock:
                raise StageError(
                    f"controller on {self._port} is in ALARM after reset (homing required): "
                    "set home = true (runs $H) or unlock = true (sends $X) in [stage]"
                )
            self.command("$X")
        self.command("G21")
        self.command("G90")

    def _wait_greeting(self, wait_s: float) -> str | None:
        deadline = time.monotonic() + wait_s
        while True:
            try:
                line = self._readline(deadline, "the GRBL greeting", wait_s)
            except StageError as exc:
                if "timed out" in str(exc):
                    return None
                raise
            m = _GREETING.match(line)
            if m:
                return m.group(1)
            log.debug("before greeting: %r", line)

    def close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - closing must not raise
                pass

    # -- low level ------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        import serial

        if self._ser is None:
            raise StageError("the stage port is not open")
        try:
            self._ser.write(data)
            self._ser.flush()
        except (serial.SerialException, OSError, _TermiosError) as exc:
            raise StageError(f"lost the connection to the stage on {self._port} "
                             f"while writing: {exc}") from None

    def _readline(self, deadline: float, what: str, timeout_s: float) -> str:
        """Next non-empty line, or StageError at ``deadline`` naming ``what``."""
        import serial

        if self._ser is None:
            raise StageError("the stage port is not open")
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                raw, self._buf = self._buf[:nl], self._buf[nl + 1:]
                line = raw.strip(b"\r \t\x00").decode("ascii", "replace")
                if line:
                    return line
                continue
            now = time.monotonic()
            if now >= deadline:
                raise StageError(f"timed out after {timeout_s:g} s waiting for {what} "
                                 f"from the stage on {self._port}")
            try:
                chunk = self._ser.read(max(1, self._ser.in_waiting))
            except (serial.SerialException, OSError, _TermiosError) as exc:
                raise StageError(f"lost the connection to the stage on {self._port} while "
                                 f"waiting for {what}: {exc}") from None
            self._buf += chunk

    def _check_async(self, line: str, doing: str) -> bool:
        """Handle lines that may arrive at any time; True when ``line`` was consumed."""
        m = _CODE.match(line)
        if m and m.group(1).upper() == "ALARM":
            code = int(m.group(2))
            raise StageError(f"controller ALARM:{code} ({ALARM_MEANINGS.get(code, 'unknown alarm')}) "
                             f"while {doing}")
        if line.startswith("["):
            log.info("controller: %s", line)
            return True
        if _GREETING.match(line):
            raise StageError(f"the controller on {self._port} reset itself while {doing} "
                             "(power or USB glitch?); position is lost")
        return False

    def command(self, line: str, *, timeout_s: float | None = None) -> None:
        """Send one line and wait for ``ok``.

        Raises
        ------
        StageError
            ``error:N`` (with its meaning), ``ALARM:N``, or no reply in time.
        """
        timeout = self.config.timeout_s if timeout_s is None else timeout_s
        log.debug("> %s", line)
        self._write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + timeout
        doing = f"running {line!r}"
        while True:
            reply = self._readline(deadline, f"the reply to {line!r}", timeout)
            log.debug("< %s", reply)
            if reply == "ok":
                return
            m = _CODE.match(reply)
            if m and m.group(1).lower() == "error":
                code = int(m.group(2))
                raise StageError(f"controller rejected {line!r}: error:{code} "
                                 f"({ERROR_MEANINGS.get(code, 'unknown error')})")
            if self._check_async(reply, doing) or reply.startswith("<"):
                continue
            log.debug("ignored line %r", reply)

    # -- Stage ----------------------------------------------------------------------
    def status(self) -> StageStatus:
        self._write(b"?")
        deadline = time.monotonic() + self.config.timeout_s
        while True:
            line = self._readline(deadline, "a status report (reply to '?')",
                                 self.config.timeout_s)
            if line.startswith("<"):
                status, self._wco = parse_status(line, wco=self._wco)
                return status
            if not self._check_async(line, "waiting for a status report"):
                log.debug("ignored line %r", line)

    def home(self) -> None:
        log.info("homing ($H)")
        self.command("$H", timeout_s=self.config.homing_timeout_s)
        self._target = None
        self._last_direction = 0
        self.wait_idle()

    def _send_move(self, machine_z_mm: float, *, feed_mm_min: float) -> None:
        self._target = machine_z_mm
        self.command(f"G1 Z{machine_z_mm:.4f} F{feed_mm_min:.1f}")

    def wait_idle(self) -> float:
        """Poll ``?`` until Idle (at the last target); return the reported machine z."""
        c = self.config
        deadline = time.monotonic() + c.move_timeout_s
        seen_motion = False
        last = None
        while True:
            status = self.status()
            last = status
            if status.state == "Alarm":
                raise StageError(f"controller in ALARM while moving (last report {status.raw})")
            if status.state == "Idle":
                at_target = (self._target is None
                             or abs(status.machine_z_mm - self._target) <= c.position_tolerance_mm)
                if at_target or seen_motion:
                    return status.machine_z_mm
            else:
                seen_motion = True
            if time.monotonic() >= deadline:
                raise StageError(f"stage did not reach Idle within {c.move_timeout_s:g} s "
                                 f"(last report {last.raw})")
            time.sleep(c.poll_interval_s)

    def stop(self) -> None:
        """Send a feed hold ``!`` (never raises; a dead port is only logged)."""
        if self._ser is None:
            return
        try:
            self._ser.write(b"!")
            self._ser.flush()
            log.info("feed hold sent to the stage on %s", self._port)
        except Exception as exc:  # noqa: BLE001 - stopping must not raise
            log.warning("could not send feed hold to %s: %s", self._port, exc)


def _open_error(port: str, exc: BaseException) -> str:
    text = str(exc)
    low = text.lower()
    if "no such file" in low or "could not find" in low or "filenotfound" in low or "errno 2]" in low:
        return f"stage port {port} not found (is the controller plugged in? check the port name)"
    if "lock" in low or "busy" in low or "errno 16]" in low or "access is denied" in low:
        return f"stage port {port} is busy: another program has it open ({text})"
    if "permission" in low or "errno 13]" in low:
        return f"no permission to open stage port {port} (add yourself to the dialout group)"
    return f"cannot open stage port {port}: {text}"
