"""smdinspect: shape-from-focus 3D inspection of SMD solder joints.

Subpackages: :mod:`smdinspect.acquire` (stage, cameras, sweeps),
:mod:`smdinspect.sff` (focus measures, depth, confidence, surfaces),
:mod:`smdinspect.inspect` (reference boards, registration, verdicts, reports),
:mod:`smdinspect.synth` (synthetic scenes and boards rendered through the optics).
"""

from .errors import (
    BoardNotLocatedError,
    CameraError,
    InputError,
    RegistrationError,
    SmdInspectError,
    StageError,
)
from .stack import FocalStack, StackWriter, open_stack

__version__ = "0.1.0"

__all__ = [
    "BoardNotLocatedError",
    "CameraError",
    "FocalStack",
    "InputError",
    "RegistrationError",
    "SmdInspectError",
    "StackWriter",
    "StageError",
    "__version__",
    "open_stack",
]
