"""The one error family of smdinspect.

Library code raises these; only :mod:`smdinspect.cli` turns them into exit codes and
one-line messages.
"""

__all__ = [
    "BoardNotLocatedError",
    "CameraError",
    "InputError",
    "OutputError",
    "RegistrationError",
    "SmdInspectError",
    "StageError",
]


class SmdInspectError(Exception):
    """Root of every error smdinspect raises on purpose."""

    exit_code = 2


class InputError(SmdInspectError, ValueError):
    """Bad input from the user: a file, an argument, a manifest, a board file."""

    exit_code = 2


class OutputError(SmdInspectError, OSError):
    """An output could not be written: no space left on the device, no permission.

    Built as ``OutputError(errno.ENOSPC, "no space left on device: PATH")``: ``errno``
    is kept for callers, the message is the whole text.
    """

    exit_code = 2

    def __str__(self) -> str:
        return self.strerror or super().__str__()


class StageError(SmdInspectError):
    """The motion stage failed: port, protocol, timeout, alarm, soft limit."""

    exit_code = 4


class CameraError(SmdInspectError):
    """The camera failed: not found, no frame, a frame of the wrong size."""

    exit_code = 4


class RegistrationError(SmdInspectError):
    """Registration could not run at all (as opposed to running and not converging)."""

    exit_code = 3


class BoardNotLocatedError(RegistrationError):
    """The board could not be found in the measurement with enough confidence."""

    exit_code = 3
