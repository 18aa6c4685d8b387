"""The calibration package's one root exception and its children.

Every public exception of the package is defined here. The module that raises one
imports it from here, so its older path (``from calibration.scales.circle_fit import
CircleFitError``) still works. Besides the root, each inherits one kind of failure from
:mod:`edges.errors` (configuration, input data, device, numerical).
"""

from __future__ import annotations

from edges.errors import ConfigurationError, DeviceError, InputDataError, NumericalError


class CalibrationError(Exception):
    """Root of every error raised by the ``calibration`` package."""


# --- input files and options


class DescriptionError(CalibrationError, ConfigurationError, ValueError):
    """A robot description file is malformed: the message names file, table and key."""


class DataFileError(CalibrationError, InputDataError, ValueError):
    """A measurement file (CSV) is malformed: the message names file, row and column."""


class UnitsError(DataFileError):
    """The numbers of a file are implausible in its columns' units (a hint says which)."""


class StreamError(CalibrationError, InputDataError, ValueError):
    """A recording or live source lacks a stream the twin needs, or cannot be decoded."""


class OutputFileError(CalibrationError, ConfigurationError, ValueError):
    """An output path is refused: it is an input, a directory, or cannot be written."""


class OptionError(CalibrationError, ConfigurationError, ValueError):
    """A command-line option has a malformed value (the message names the option)."""


# --- kinematics and the model


class KinematicsError(CalibrationError, InputDataError, ValueError):
    """Bad arguments to a kinematics function (shapes, joint count)."""


class ModelEffectError(CalibrationError, ConfigurationError, ValueError):
    """A description names an effect kind the twin cannot apply, or its parameters are bad."""


class EffectLibraryError(CalibrationError, InputDataError, ValueError):
    """An effect has bad parameters, or needs data (times) the poses do not have."""


class GravityRegressorError(CalibrationError, ConfigurationError, ValueError):
    """A moment name is unknown, or the gravity direction is not a direction."""


class StiffnessError(CalibrationError, InputDataError, ValueError):
    """Stiffnesses missing for a force, or a load test that cannot give them."""


# --- grating-scale calibration


class CircleFitError(CalibrationError, NumericalError, ValueError):
    """The points do not determine a circle (too few, non-finite, or collinear)."""


class TargetSetFitError(CircleFitError):
    """The points of a target set do not determine its rotation (shape, count, geometry).

    A :class:`CircleFitError` (so a :class:`CalibrationError`): callers of either fit
    catch both.
    """


class ScaleError(CalibrationError, InputDataError, ValueError):
    """The data of a joint cannot give a scale calibration (too few stops, no zero, ...)."""


# --- identification and compensation


class RegistrationError(CalibrationError, NumericalError, ValueError):
    """The point sets cannot be registered (too few points, collinear, NaN)."""


class IdentifiabilityError(CalibrationError, NumericalError, ValueError):
    """The data identifies nothing, or the arguments have the wrong shape."""


class IdentificationError(CalibrationError, NumericalError, ValueError):
    """The identification cannot run (too few poses, bad shapes, unknown option) or its fit
    ran away beyond repair."""


class RecursiveIdentificationError(CalibrationError, InputDataError, ValueError):
    """Bad settings or data for the recursive identification."""


class PoseSelectionError(CalibrationError, InputDataError, ValueError):
    """Bad arguments to the pose selection (unknown index, too few candidates)."""


class CompensationError(CalibrationError, InputDataError, ValueError):
    """The targets or their joints are malformed (shapes, non-finite values)."""


class ScaleFileError(CalibrationError, InputDataError, ValueError):
    """``scale.toml`` is malformed: the message names the file, table and key."""


class TwinRunError(CalibrationError, InputDataError, ValueError):
    """The data do not hold what a calibration needs (named in the message)."""


class LiveTwinError(CalibrationError, DeviceError):
    """The live twin cannot start (no grating stream where it was told to look)."""


class TrackingError(CalibrationError, InputDataError, ValueError):
    """``twin track``: a model or check that cannot be tracked."""


class PlanError(CalibrationError, ConfigurationError, ValueError):
    """``twin plan``: a campaign that cannot be planned in this cell (region, view, counts)."""


class ProgramError(CalibrationError, ConfigurationError, ValueError):
    """A robot program that cannot be written or read back (controller conventions)."""
