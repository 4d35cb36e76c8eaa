"""Errors raised by radar_calib_ros.

The CLI and the node catch :class:`CalibrationError` only: a bug keeps its traceback.
CLI exit codes: :class:`InsufficientDataError` and :class:`NotConvergedError` are "the data
cannot be calibrated" (exit 1); every other :class:`CalibrationError` is bad usage or
unreadable input (exit 2).
"""
from __future__ import annotations


class CalibrationError(Exception):
    """Base of every error this package raises on purpose."""


class ConfigError(CalibrationError, ValueError):
    """A parameter is unknown, ill-typed or out of range."""


class BagReadError(CalibrationError):
    """A recording cannot be opened or read (missing path, not a bag, corrupt, no topic)."""


class DecodeError(CalibrationError):
    """A message does not have the layout we can decode (fields, sizes)."""


class ResultFileError(CalibrationError):
    """A result file cannot be read or written, or is not a valid calibration."""


class InsufficientDataError(CalibrationError):
    """The data cannot be calibrated: too few passes, vehicle never seen, ...

    Parameters
    ----------
    stage : str
        Pipeline stage that found the problem.
    message : str
        One plain sentence with the numbers, e.g.
        ``"calibration vehicle seen in 1 pass, need at least 3"``.
    """

    def __init__(self, stage: str, message: str) -> None:
        super().__init__(f'{stage}: {message}')
        self.stage = stage
        self.reason = message


class NotConvergedError(InsufficientDataError):
    """An optimisation did not converge (carries scipy's status and message)."""

    def __init__(self, stage: str, message: str, status: int | None = None) -> None:
        super().__init__(stage, message)
        self.status = status


def exit_code(error: CalibrationError) -> int:
    """CLI exit code for an error (CONTRACT.md: 1 cannot calibrate, 2 bad input)."""
    return 1 if isinstance(error, InsufficientDataError) else 2
