"""A fake GRBL 1.1 controller on a real pseudo-terminal, with fault injection.

:class:`FakeGrbl` opens a pty pair with :func:`os.openpty`, serves the master side in a
thread and gives clients the slave's name (``/dev/pts/N``) to open with pyserial like
any USB serial port. It speaks the part of GRBL 1.1 that :class:`GrblStage` uses:
greeting on soft reset (Ctrl-X), ``$H``, ``$X``, ``$$``, ``$I``, ``$G``, ``G0``/``G1``
moves in ``G90``/``G91``, ``G20``/``G21``, ``G4`` dwell, ``F``, the real-time ``?``,
``!`` (feed hold) and ``~`` (resume), ``ok`` / ``error:N`` / ``ALARM:N``.

Motion takes time (``distance / rate``; ``G0`` at ``max_rate_mm_s``), positions are
quantised to whole motor steps (``steps_per_mm``) and reported with three decimals, as
GRBL does. Faults (:meth:`FakeGrbl.inject`): the controller goes silent, answers
``error:N``, raises ``ALARM:N`` half-way through a move, or disconnects mid-move.

Every received line, every real-time byte and every planned move target is recorded
(:attr:`FakeGrbl.lines`, :attr:`FakeGrbl.realtime`, :attr:`FakeGrbl.moves`) so tests can
check the commanded sequence.

POSIX only (pseudo-terminals).
"""

from __future__ import annotations

import errno
import logging
import math
import os
import re
import select
import threading
import time
from dataclasses import dataclass

from ..errors import InputError

__all__ = ["FAULT_KINDS", "FakeGrbl"]

log = logging.getLogger(__name__)

GREETING = "Grbl 1.1h ['$' for help]"
FAULT_KINDS = ("alarm", "disconnect", "error", "timeout")
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")


@dataclass
class _Fault:
    kind: str
    at_move: int
    code: int
    fraction: float


@dataclass
class _Segment:
    target: list[float]
    rate_mm_s: float
    dwell_s: float = 0.0
    homing: bool = False


class FakeGrbl:
    """A GRBL 1.1 controller simulated behind a pseudo-terminal.

    Parameters
    ----------
    steps_per_mm : float
        Motor resolution; positions are whole steps (GRBL ``$102``).
    max_rate_mm_s : float
        Top speed (``$112`` / 60); ``G0`` moves run at it, ``G1`` at ``min(F/60, max)``.
    start_z_mm : float
        Machine z at power-up.
    homing : bool
        Homing enabled (``$22=1``): starts in ALARM until ``$H`` or ``$X``.
    home_z_mm : float
        Machine z after homing.
    soft_limits_mm : (float, float) or None
        Machine travel (``$20=1``); a target outside raises ``ALARM:2``.
    greeting : bool
        ``False`` gives a silent device that never prints the greeting.

    Examples
    --------
    >>> with FakeGrbl() as fake:          # doctest: +SKIP
    ...     stage = GrblStage(StageConfig(fake=True, boot_wait_s=0), port=fake.port)
    """

    def __init__(
        self,
        *,
        steps_per_mm: float = 400.0,
        max_rate_mm_s: float = 200.0,
        start_z_mm: float = 0.0,
        homing: bool = False,
        home_z_mm: float = 0.0,
        soft_limits_mm: tuple[float, float] | None = None,
        greeting: bool = True,
        faults: list[dict] | None = None,
    ) -> None:
        for name, value in (("steps_per_mm", steps_per_mm), ("max_rate_mm_s", max_rate_mm_s)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
                raise InputError(f"fake GRBL {name} must be > 0; got {value!r}")
        for name, value in (("start_z_mm", start_z_mm), ("home_z_mm", home_z_mm)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise InputError(f"fake GRBL {name} must be a finite number; got {value!r}")
        if soft_limits_mm is not None:
            if len(soft_limits_mm) != 2 or not soft_limits_mm[0] < soft_limits_mm[1]:
                raise InputError(f"fake GRBL soft_limits_mm must be (min, max); got {soft_limits_mm!r}")
        self.steps_per_mm = float(steps_per_mm)
        self.max_rate_mm_s = float(max_rate_mm_s)
        self.homing_enabled = bool(homing)
        self.home_z_mm = float(home_z_mm)
        self.soft_limits_mm = tuple(soft_limits_mm) if soft_limits_mm else None
        self.greeting = bool(greeting)

        self.lines: list[str] = []  #: every line received, in order
        self.realtime: list[str] = []  #: real-time bytes received ("?" omitted), in order
        self.moves: list[float] = []  #: machine z target of every accepted move, in order
        self.n_moves = 0

        self._lock = threading.RLock()
        self._pos = [0.0, 0.0, self._quantise(float(start_z_mm))]
        self._queue: list[_Segment] = []
        self._t_last = time.monotonic()
        self._state = "Alarm" if self.homing_enabled else "Idle"
        self._hold = False
        self._absolute = True
        self._inches = False
        self._feed_mm_min: float | None = None
        self._rx = b""
        self._pending: list[str] = []  # lines waiting while a $H / G4 blocks the parser
        self._blocked_ok = False  # an "ok" owed when the queue drains ($H, G4)
        self._silent = False
        self._faults: list[_Fault] = []
        self._scheduled: tuple[str, int, float] | None = None  # (kind, code, at time)
        for f in faults or ():
            self.inject(**f)

        self._master = self._slave = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.port: str = ""

    # -- life cycle -----------------------------------------------------------------
    def start(self) -> "FakeGrbl":
        """Open the pty and start serving; :attr:`port` is then the slave's path."""
        import tty

        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="fake-grbl", daemon=True)
        self._thread.start()
        self._emit("")
        if self.greeting:
            self._emit(GREETING)
        log.debug("fake GRBL serving on %s", self.port)
        return self

    def stop(self) -> None:
        """Stop serving and close both ends of the pty."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._close_fds()

    def _close_fds(self) -> None:
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, -1)

    def __enter__(self) -> "FakeGrbl":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- fault injection ------------------------------------------------------------
    def inject(self, kind: str, *, at_move: int = 1, code: int | None = None,
               fraction: float = 0.5) -> None:
        """Arm a fault that fires at the ``at_move``-th move command (counted from 1).

        Parameters
        ----------
        kind : {"timeout", "error", "alarm", "disconnect"}
            ``timeout``: from that move on the controller answers nothing at all;
            ``error``: the move is answered ``error:code`` (default 33) and not run;
            ``alarm``: the move starts and stops at ``fraction`` of its way with
            ``ALARM:code`` (default 1, hard limit);
            ``disconnect``: the move starts and the pty is closed at ``fraction``.
        at_move : int
            Counts moves accepted since start (including earlier ones); a move number
            already passed fires at the next move.
        """
        if kind not in FAULT_KINDS:
            raise InputError(f"fault kind must be one of {', '.join(FAULT_KINDS)}; got {kind!r}")
        if isinstance(at_move, bool) or not isinstance(at_move, int) or at_move < 1:
            raise InputError(f"fault at_move must be an integer >= 1; got {at_move!r}")
        if not 0.0 <= fraction < 1.0:
            raise InputError(f"fault fraction must be in [0, 1); got {fraction}")
        default = {"error": 33, "alarm": 1}.get(kind, 0)
        with self._lock:
            self._faults.append(_Fault(kind, at_move, default if code is None else int(code),
                                       float(fraction)))

    # -- state ----------------------------------------------------------------------
    @property
    def machine_z_mm(self) -> float:
        """Current machine z (whole steps)."""
        with self._lock:
            self._advance(time.monotonic())
            return self._quantise(self._pos[2])

    @property
    def state(self) -> str:
        with self._lock:
            self._advance(time.monotonic())
            return self._state_name()

    @property
    def feed_holds(self) -> int:
        """Number of feed-hold bytes ``!`` received."""
        return self.realtime.count("!")

    def _quantise(self, z: float) -> float:
        return round(z * self.steps_per_mm) / self.steps_per_mm

    def _state_name(self) -> str:
        if self._state == "Alarm":
            return "Alarm"
        if self._hold:
            return "Hold:0"
        if self._queue:
            return "Home" if self._queue[0].homing else "Run"
        return "Idle"

    # -- serving --------------------------------------------------------------------
    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._master], [], [], 0.002)
            except (OSError, ValueError):
                return
            with self._lock:
                self._advance(time.monotonic())
                if self._master < 0:
                    return
                if ready:
                    try:
                        data = os.read(self._master, 4096)
                    except BlockingIOError:
                        data = b""
                    except OSError:
                        return
                    self._receive(data)

    def _emit(self, line: str) -> None:
        if self._silent or self._master < 0:
            return
        try:
            os.write(self._master, line.encode("ascii") + b"\r\n")
        except BlockingIOError:
            pass  # nobody reads: drop, like a UART
        except OSError as exc:
            if exc.errno not in (errno.EIO, errno.EBADF):
                raise

    def _receive(self, data: bytes) -> None:
        for byte in data:
            ch = chr(byte)
            if self._silent:  # hung: bytes arrive (and are recorded) but nothing happens
                if ch in "!~\x18":
                    self.realtime.append(ch)
                continue
            if ch == "?":
                self._report()
            elif ch in "!~\x18":
                self.realtime.append(ch)
                if ch == "!":
                    if self._queue and self._state != "Alarm":
                        self._hold = True
                elif ch == "~":
                    self._hold = False
                else:
                    self._soft_reset()
            elif ch in "\r\n":
                line, self._rx = self._rx.decode("ascii", "replace"), b""
                if line.strip():
                    if self._blocked_ok:
                        self._pending.append(line)
                    else:
                        self._line(line)
            elif byte >= 0x80:
                continue  # extended real-time commands: ignored
            else:
                self._rx += bytes([byte])

    def _report(self) -> None:
        x, y, z = (self._quantise(v) for v in self._pos)
        rate = 0.0
        if self._queue and not self._hold and self._state != "Alarm":
            rate = self._queue[0].rate_mm_s * 60.0
        self._emit(f"<{self._state_name()}|MPos:{x:.3f},{y:.3f},{z:.3f}|FS:{rate:.0f},0>")

    def _soft_reset(self) -> None:
        moving = bool(self._queue) and not self._hold
        self._queue.clear()
        self._pending.clear()
        self._blocked_ok = False
        self._scheduled = None
        self._hold = False
        self._rx = b""
        self._absolute, self._inches = True, False
        for i in range(3):
            self._pos[i] = self._quantise(self._pos[i])
        if moving:
            self._state = "Alarm"
            self._emit("ALARM:3")
        elif self.homing_enabled and self._state != "Idle":
            self._state = "Alarm"
        self._emit("")
        if self.greeting:
            self._emit(GREETING)
        if self._state == "Alarm":
            self._emit("[MSG:'$H'|'$X' to unlock]")

    # -- motion ---------------------------------------------------------------------
    def _advance(self, now: float) -> None:
        dt = now - self._t_last
        self._t_last = now
        if self._scheduled is not None and now >= self._scheduled[2]:
            kind, code, _ = self._scheduled
            self._scheduled = None
            if kind == "alarm":
                self._queue.clear()
                self._state = "Alarm"
                self._emit(f"ALARM:{code}")
                self._emit("[MSG:Reset to continue]")
            else:  # disconnect
                log.debug("fake GRBL: disconnecting")
                self._stop.set()
                self._close_fds()
                return
        if self._hold or self._state == "Alarm":
            return
        while dt > 0 and self._queue:
            seg = self._queue[0]
            if seg.dwell_s > 0:
                used = min(dt, seg.dwell_s)
                seg.dwell_s -= used
                dt -= used
                if seg.dwell_s <= 1e-12:
                    self._queue.pop(0)
                continue
            delta = [t - p for t, p in zip(seg.target, self._pos)]
            dist = math.sqrt(sum(d * d for d in delta))
            step = seg.rate_mm_s * dt
            if step >= dist:
                self._pos = list(seg.target)
                dt -= dist / seg.rate_mm_s if seg.rate_mm_s > 0 else dt
                self._queue.pop(0)
            else:
                self._pos = [p + d * step / dist for p, d in zip(self._pos, delta)]
                dt = 0.0
        if not self._queue and self._blocked_ok:
            self._blocked_ok = False
            if self._state == "Home":
                self._state = "Idle"
            self._emit("ok")
            pending, self._pending = self._pending, []
            for line in pending:
                if self._blocked_ok:
                    self._pending.append(line)
                else:
                    self._line(line)

    def _planned_end(self) -> list[float]:
        return list(self._queue[-1].target) if self._queue else list(self._pos)

    # -- commands -------------------------------------------------------------------
    def _line(self, raw: str) -> None:
        self.lines.append(raw)
        line = re.sub(r"\([^)]*\)", "", raw).split(";")[0].strip().upper()
        if not line:
            self._emit("ok")
            return
        if line.startswith("$"):
            self._system(line)
            return
        if self._state == "Alarm":
            self._emit("error:9")
            return
        compact = line.replace(" ", "")
        words = _WORD.findall(compact)
        if "".join(a + b for a, b in words) != compact:
            self._emit("error:1" if re.search(r"[A-Z]", compact) is None else "error:2")
            return
        motion = None
        axes: dict[str, float] = {}
        dwell = None
        seen: set[str] = set()
        for letter, value in words:
            v = float(value)
            if letter == "G":
                g = int(v) if v == int(v) else v
                if g in (0, 1):
                    motion = g
                elif g == 4:
                    motion = 4
                elif g == 20:
                    self._inches = True
                elif g == 21:
                    self._inches = False
                elif g == 90:
                    self._absolute = True
                elif g == 91:
                    self._absolute = False
                elif g in (17, 54, 94):
                    pass
                else:
                    self._emit("error:20")
                    return
            elif letter in "XYZ":
                if letter in seen:
                    self._emit("error:25")
                    return
                seen.add(letter)
                axes[letter] = v * (25.4 if self._inches else 1.0)
            elif letter == "F":
                if v <= 0:
                    self._emit("error:4")
                    return
                self._feed_mm_min = v * (25.4 if self._inches else 1.0)
            elif letter == "P":
                dwell = v
            elif letter in "MNST":
                pass
            else:
                self._emit("error:20")
                return
        if motion == 4:
            if dwell is None or dwell < 0:
                self._emit("error:28")
                return
            self._queue.append(_Segment(self._planned_end(), 0.0, dwell_s=max(dwell, 1e-6)))
            self._blocked_ok = True  # G4 synchronises: ok once everything has run
            return
        if not axes:
            self._emit("ok")
            return
        if motion is None:
            motion = 1 if self._feed_mm_min is not None else 0
        if motion == 1 and self._feed_mm_min is None:
            self._emit("error:22")
            return
        end = self._planned_end()
        for i, letter in enumerate("XYZ"):
            if letter in axes:
                end[i] = axes[letter] if self._absolute else end[i] + axes[letter]
        end = [self._quantise(v) for v in end]
        self.n_moves += 1
        fault = self._fault_for(self.n_moves)
        if fault is not None and fault.kind == "timeout":
            log.debug("fake GRBL: going silent at move %d", self.n_moves)
            self._silent = True
            return
        if fault is not None and fault.kind == "error":
            self._emit(f"error:{fault.code}")
            return
        if self.soft_limits_mm is not None and not (
            self.soft_limits_mm[0] <= end[2] <= self.soft_limits_mm[1]
        ):
            self._queue.clear()
            self._state = "Alarm"
            self._emit("ALARM:2")
            self._emit("[MSG:Reset to continue]")
            return
        rate = self.max_rate_mm_s if motion == 0 else min(self._feed_mm_min / 60.0, self.max_rate_mm_s)
        start = self._planned_end()
        self._queue.append(_Segment(end, rate))
        self.moves.append(end[2])
        if fault is not None:
            dist = math.sqrt(sum((e - s) ** 2 for e, s in zip(end, start)))
            queued = sum(self._remaining_time(s) for s in self._queue[:-1])
            at = time.monotonic() + queued + fault.fraction * dist / rate
            self._scheduled = (fault.kind, fault.code, at)
        self._emit("ok")

    def _remaining_time(self, seg: _Segment) -> float:
        if seg.dwell_s > 0:
            return seg.dwell_s
        dist = math.sqrt(sum((t - p) ** 2 for t, p in zip(seg.target, self._pos)))
        return dist / seg.rate_mm_s

    def _fault_for(self, n: int) -> _Fault | None:
        for f in self._faults:
            if f.at_move <= n:
                self._faults.remove(f)
                return f
        return None

    def _system(self, line: str) -> None:
        cmd = line.replace(" ", "")
        if cmd == "$H":
            if not self.homing_enabled:
                self._emit("error:5")
                return
            self._state = "Home"
            self._queue.append(_Segment([self._pos[0], self._pos[1], self.home_z_mm],
                                        self.max_rate_mm_s, homing=True))
            self._blocked_ok = True  # ok once homing is done
            return
        if cmd == "$X":
            if self._state == "Alarm":
                self._state = "Idle"
                self._emit("[MSG:Caution: Unlocked]")
            self._emit("ok")
            return
        if self._state not in ("Idle", "Alarm") or self._queue:
            self._emit("error:8")
            return
        if cmd == "$$":
            travel = (self.soft_limits_mm[1] - self.soft_limits_mm[0]) if self.soft_limits_mm else 200.0
            for key, value in (("$10", "1"), ("$20", "1" if self.soft_limits_mm else "0"),
                               ("$22", "1" if self.homing_enabled else "0"),
                               ("$102", f"{self.steps_per_mm:.3f}"),
                               ("$112", f"{self.max_rate_mm_s * 60:.3f}"),
                               ("$132", f"{travel:.3f}")):
                self._emit(f"{key}={value}")
            self._emit("ok")
        elif cmd == "$I":
            self._emit("[VER:1.1h.20190825:smdinspect-fake]")
            self._emit("[OPT:V,15,128]")
            self._emit("ok")
        elif cmd == "$G":
            mode = "G90" if self._absolute else "G91"
            units = "G20" if self._inches else "G21"
            self._emit(f"[GC:G0 G54 G17 {units} {mode} G94 M5 M9 T0 F{self._feed_mm_min or 0:g} S0]")
            self._emit("ok")
        else:
            self._emit("error:3")
