"""The errors exuflex raises for bad input; the CLI reports these in one line without a traceback."""

from __future__ import annotations

from .erls.kinematics import KinematicsError
from .mechanism import ModelFileError
from .mechanism.loader import UsageError

__all__ = ["LogFormatError", "ModelFileError", "KinematicsError", "SimulationError", "UsageError", "EXPECTED_ERRORS"]


class LogFormatError(ValueError):
    """A sensor log is malformed; the message names the file, the channel or row, and what was expected."""


class SimulationError(ValueError):
    """A truth's solver failed on the input it was given; the message names the input's likely cause (the model
    file's field or the argument) and what was expected."""


EXPECTED_ERRORS = (ModelFileError, KinematicsError, LogFormatError, UsageError, SimulationError, FileNotFoundError)
