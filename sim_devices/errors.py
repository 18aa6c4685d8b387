"""The sim_devices package's one root exception and its children."""

from __future__ import annotations

from edges.errors import ConfigurationError


class SimError(Exception):
    """Root of every error raised by the ``sim_devices`` package."""


class SimConfigError(SimError, ConfigurationError, ValueError):
    """A cell configuration is malformed: the message names file, table and key."""
