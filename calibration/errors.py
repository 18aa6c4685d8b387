"""The calibration package's one root exception and its children."""

from __future__ import annotations


class CalibrationError(Exception):
    """Root of every error raised by the ``calibration`` package."""


class DescriptionError(CalibrationError, ValueError):
    """A robot description file is malformed: the message names file, table and key."""


class DataFileError(CalibrationError, ValueError):
    """A measurement file (CSV) is malformed: the message names file, row and column."""


class KinematicsError(CalibrationError, ValueError):
    """Bad arguments to a kinematics function (shapes, joint count)."""


class OutputFileError(CalibrationError, ValueError):
    """An output path is refused: it is an input, a directory, or cannot be written."""


class OptionError(CalibrationError, ValueError):
    """A command-line option has a malformed value (the message names the option)."""
