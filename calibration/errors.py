"""The calibration package's one root exception and its children.

Every public exception of the package is defined here. The module that raises one
imports it from here, so its older path (``from calibration.circle_fit import
CircleFitError``) still works.
"""

from __future__ import annotations


class CalibrationError(Exception):
    """Root of every error raised by the ``calibration`` package."""


# --- input files and options


class DescriptionError(CalibrationError, ValueError):
    """A robot description file is malformed: the message names file, table and key."""


class DataFileError(CalibrationError, ValueError):
    """A measurement file (CSV) is malformed: the message names file, row and column."""


class UnitsError(DataFileError):
    """The numbers of a file are implausible in its columns' units (a hint says which)."""


class StreamError(CalibrationError, ValueError):
    """A recording or live source lacks a stream the twin needs, or cannot be decoded."""


class OutputFileError(CalibrationError, ValueError):
    """An output path is refused: it is an input, a directory, or cannot be written."""


class OptionError(CalibrationError, ValueError):
    """A command-line option has a malformed value (the message names the option)."""


# --- kinematics and the model


class KinematicsError(CalibrationError, ValueError):
    """Bad arguments to a kinematics function (shapes, joint count)."""


class ModelEffectError(CalibrationError, ValueError):
    """A description names an effect kind the twin cannot apply, or its parameters are bad."""


class EffectLibraryError(CalibrationError, ValueError):
    """An effect has bad parameters, or needs data (times) the poses do not have."""


class GravityRegressorError(CalibrationError, ValueError):
    """A moment name is unknown, or the gravity direction is not a direction."""


class StiffnessError(CalibrationError, ValueError):
    """Stiffnesses missing for a force, or a load test that cannot give them."""


# --- grating-scale calibration


class CircleFitError(CalibrationError, ValueError):
    """The points do not determine a circle (too few, non-finite, or collinear)."""


class TargetSetFitError(CircleFitError):
    """The points of a target set do not determine its rotation (shape, count, geometry).

    A :class:`CircleFitError` (so a :class:`CalibrationError`): callers of either fit
    catch both.
    """


class ScaleError(CalibrationError, ValueError):
    """The data of a joint cannot give a scale calibration (too few stops, no zero, ...)."""


# --- identification and compensation


class RegistrationError(CalibrationError, ValueError):
    """The point sets cannot be registered (too few points, collinear, NaN)."""


class IdentifiabilityError(CalibrationError, ValueError):
    """The data identifies nothing, or the arguments have the wrong shape."""


class IdentificationError(CalibrationError, ValueError):
    """The identification cannot run (too few poses, bad shapes, unknown option) or its fit
    ran away beyond repair."""


class RecursiveIdentificationError(CalibrationError, ValueError):
    """Bad settings or data for the recursive identification."""


class PoseSelectionError(CalibrationError, ValueError):
    """Bad arguments to the pose selection (unknown index, too few candidates)."""


class CompensationError(CalibrationError, ValueError):
    """The targets or their joints are malformed (shapes, non-finite values)."""


class ScaleFileError(CalibrationError, ValueError):
    """``scale.toml`` is malformed: the message names the file, table and key."""


class TwinRunError(CalibrationError, ValueError):
    """The data do not hold what a calibration needs (named in the message)."""


class LiveTwinError(CalibrationError):
    """The live twin cannot start (no grating stream where it was told to look)."""


class TrackingError(CalibrationError, ValueError):
    """``twin track``: a model or check that cannot be tracked."""
