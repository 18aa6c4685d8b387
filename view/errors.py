"""The view's one error class: a user's mistake the command line reports in one line."""

from __future__ import annotations

from calibration.errors import CalibrationError
from edges.errors import ConfigurationError


class ViewError(CalibrationError, ConfigurationError, ValueError):
    """Bad input to ``twin view`` (a file, an option, an endpoint): the message names it."""
