"""The motion-stage interface: one z axis moved in machine coordinates.

A :class:`Stage` hides the controller's protocol (GRBL today; Marlin or a custom line
protocol can be added by subclassing). The sweep only calls :meth:`Stage.approach`,
:meth:`Stage.position` and :meth:`Stage.stop`.

All positions here are **machine** z in mm, as the controller reports them (GRBL's
``MPos``). The rig file's ``[mapping]`` turns them into focused-plane heights ``z_mm``
(see :class:`smdinspect.acquire.ZMapping`).
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from enum import Enum

from ..errors import InputError, StageError

__all__ = ["Stage", "StageConfig", "StageProtocol", "StageStatus"]

log = logging.getLogger(__name__)


class StageProtocol(str, Enum):
    """Controller protocols a rig file may name in ``[stage] protocol``."""

    GRBL = "grbl"


@dataclass(frozen=True)
class StageStatus:
    """One status report of the controller.

    Attributes
    ----------
    state : str
        The controller state without sub-state: ``"Idle"``, ``"Run"``, ``"Hold"``,
        ``"Jog"``, ``"Alarm"``, ``"Door"``, ``"Check"``, ``"Home"``, ``"Sleep"``.
    machine_z_mm : float
        Machine z position (mm).
    raw : str
        The report as received, for logs and error messages.
    """

    state: str
    machine_z_mm: float
    raw: str = ""


@dataclass(frozen=True)
class StageConfig:
    """How to reach and drive the stage (the rig file's ``[stage]`` table).

    Parameters
    ----------
    port : str
        Any pyserial URL: ``/dev/ttyUSB0``, ``COM3``, ``socket://host:port``,
        ``rfc2217://host:port``. Ignored when ``fake`` is true (the fake's pty is used).
    protocol : StageProtocol or str
        ``"grbl"``.
    baud : int
        Serial speed (GRBL 1.1: 115200).
    timeout_s : float
        Longest wait for any single reply (a line, a status report), in s.
    move_timeout_s : float
        Longest wait for a move to end in ``Idle``, in s.
    homing_timeout_s : float
        Longest wait for ``$H`` to finish, in s.
    boot_wait_s : float
        How long to wait for the greeting a board prints after the port opens (Arduino
        boards reset when the port opens) before sending a soft reset (Ctrl-X).
    home : bool
        Run the homing cycle ``$H`` after connecting.
    unlock : bool
        Send ``$X`` when the controller starts in ALARM and ``home`` is false.
    z_min_mm, z_max_mm : float
        Soft limits in machine coordinates; no move outside is ever sent.
    feed_mm_min : float
        Feed rate of the ``G1`` moves, mm/min.
    poll_interval_s : float
        Time between status queries while waiting for ``Idle``.
    position_tolerance_mm : float
        Largest accepted difference between a commanded and the reported position.
    fake : bool
        Start an in-process fake GRBL controller on a pseudo-terminal instead of opening
        ``port`` (the simulated rig); its settings are ``fake_options``.
    fake_options : dict
        Keyword arguments of :class:`smdinspect.acquire.FakeGrbl` (``[stage.fake]``).
    """

    port: str = ""
    protocol: StageProtocol = StageProtocol.GRBL
    baud: int = 115200
    timeout_s: float = 2.0
    move_timeout_s: float = 60.0
    homing_timeout_s: float = 120.0
    boot_wait_s: float = 2.0
    home: bool = False
    unlock: bool = False
    z_min_mm: float = -100.0
    z_max_mm: float = 100.0
    feed_mm_min: float = 300.0
    poll_interval_s: float = 0.05
    position_tolerance_mm: float = 0.01
    fake: bool = False
    fake_options: dict | None = None

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "protocol", StageProtocol(self.protocol))
        except ValueError:
            choices = ", ".join(p.value for p in StageProtocol)
            raise InputError(
                f"stage protocol must be one of {choices}; got {self.protocol!r}"
            ) from None
        if not isinstance(self.port, str):
            raise InputError(f"stage port must be a string (a pyserial URL); got {self.port!r}")
        if not self.fake and not self.port:
            raise InputError("stage port is empty; give a pyserial URL such as /dev/ttyUSB0 "
                             "(or set fake = true for the simulated rig)")
        if isinstance(self.baud, bool) or not isinstance(self.baud, int) or self.baud <= 0:
            raise InputError(f"stage baud must be a positive integer; got {self.baud!r}")
        for name in ("timeout_s", "move_timeout_s", "homing_timeout_s", "feed_mm_min",
                     "poll_interval_s", "position_tolerance_mm"):
            _positive(getattr(self, name), f"stage {name}")
        _finite(self.boot_wait_s, "stage boot_wait_s")
        if self.boot_wait_s < 0:
            raise InputError(f"stage boot_wait_s must be >= 0; got {self.boot_wait_s}")
        _finite(self.z_min_mm, "stage z_min_mm")
        _finite(self.z_max_mm, "stage z_max_mm")
        if not self.z_min_mm < self.z_max_mm:
            raise InputError(f"stage soft limits need z_min_mm < z_max_mm; got "
                             f"{self.z_min_mm} .. {self.z_max_mm}")
        for name in ("home", "unlock", "fake"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"stage {name} must be true or false; got {getattr(self, name)!r}")
        if self.fake_options is not None and not isinstance(self.fake_options, dict):
            raise InputError("stage fake options ([stage.fake]) must be a table")


class Stage(ABC):
    """A z axis driven by a controller; positions in machine mm.

    Subclasses implement the protocol (:meth:`open`, :meth:`close`, :meth:`home`,
    :meth:`status`, :meth:`_send_move`, :meth:`wait_idle`, :meth:`stop`); this base
    class adds soft limits and the backlash-aware :meth:`approach`.

    Use as a context manager: the port is closed on exit, after a feed hold when the
    block ends with an exception.
    """

    def __init__(self, config: StageConfig) -> None:
        self.config = config
        self._last_direction = 0  # sign of the last commanded motion; 0 = unknown

    # -- protocol -------------------------------------------------------------------
    @property
    @abstractmethod
    def port(self) -> str:
        """The port (pyserial URL) in use."""

    @abstractmethod
    def open(self) -> None:
        """Open the port, check the controller answers, home/unlock as configured."""

    @abstractmethod
    def close(self) -> None:
        """Close the port (never raises)."""

    @abstractmethod
    def home(self) -> None:
        """Run the homing cycle."""

    @abstractmethod
    def status(self) -> StageStatus:
        """Query and return one status report."""

    @abstractmethod
    def _send_move(self, machine_z_mm: float, *, feed_mm_min: float) -> None:
        """Command an absolute move (returns once the controller accepted it)."""

    @abstractmethod
    def wait_idle(self) -> float:
        """Wait until the controller is idle; return the machine z it reports."""

    @abstractmethod
    def stop(self) -> None:
        """Feed hold: stop motion now, keeping position (never raises)."""

    # -- common logic ---------------------------------------------------------------
    def position(self) -> float:
        """Machine z (mm) as reported by the controller now."""
        return self.status().machine_z_mm

    def check_limits(self, machine_z_mm: float) -> None:
        """Raise :class:`StageError` if ``machine_z_mm`` is outside the soft limits."""
        c = self.config
        if not math.isfinite(machine_z_mm) or not c.z_min_mm <= machine_z_mm <= c.z_max_mm:
            raise StageError(
                f"move to machine Z {machine_z_mm:.4f} mm refused: outside the soft limits "
                f"{c.z_min_mm} .. {c.z_max_mm} mm of the rig file"
            )

    def move_to(self, machine_z_mm: float, *, feed_mm_min: float | None = None) -> float:
        """Move to ``machine_z_mm`` (absolute), wait for Idle, return the reported z.

        Raises
        ------
        StageError
            Outside the soft limits (nothing is sent), a controller error or alarm, a
            timeout, or a position that differs from the target by more than
            ``position_tolerance_mm``.
        """
        self.check_limits(machine_z_mm)
        feed = self.config.feed_mm_min if feed_mm_min is None else feed_mm_min
        before = self.position()
        self._send_move(machine_z_mm, feed_mm_min=feed)
        reached = self.wait_idle()
        if abs(reached - machine_z_mm) > self.config.position_tolerance_mm:
            raise StageError(
                f"stage stopped at machine Z {reached:.4f} mm instead of {machine_z_mm:.4f} mm "
                f"(tolerance {self.config.position_tolerance_mm} mm)"
            )
        if reached != before:
            self._last_direction = 1 if reached > before else -1
        return reached

    def approach(
        self,
        machine_z_mm: float,
        *,
        direction: int,
        backlash_mm: float,
        feed_mm_min: float | None = None,
    ) -> float:
        """Move to ``machine_z_mm`` so the last motion runs in ``direction`` (+1 or -1).

        When the stage last moved the other way (or its history is unknown), or the target
        lies behind it, it first goes ``backlash_mm`` past the target on the far side
        (overshoot) and then comes back, so the lead screw's slack is always taken up on
        the same side. Returns the machine z reported after the final move.
        """
        if direction not in (1, -1):
            raise InputError(f"direction must be +1 or -1; got {direction!r}")
        if not (math.isfinite(backlash_mm) and backlash_mm >= 0):
            raise InputError(f"backlash_mm must be >= 0; got {backlash_mm}")
        self.check_limits(machine_z_mm)
        if backlash_mm > 0:
            pre = machine_z_mm - direction * backlash_mm
            self.check_limits(pre)
            here = self.position()
            ahead = (machine_z_mm - here) * direction > 0
            if not (ahead and self._last_direction == direction):
                log.debug("backlash: pre-position at machine Z %.4f", pre)
                self.move_to(pre, feed_mm_min=feed_mm_min)
        return self.move_to(machine_z_mm, feed_mm_min=feed_mm_min)

    def __enter__(self) -> "Stage":
        self.open()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.stop()
        self.close()


def _finite(value: object, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{name} must be a finite number; got {value!r}")


def _positive(value: object, name: str) -> None:
    _finite(value, name)
    if value <= 0:  # type: ignore[operator]
        raise InputError(f"{name} must be > 0; got {value}")
