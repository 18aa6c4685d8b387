"""The old name of :mod:`daq.foxglove_channels` (the Foxglove channels a recording carries
beside its columnar data; ``view/`` is the twin's browser view, something else), kept for
the modules that still import it from here."""

from __future__ import annotations

from daq.foxglove_channels import StreamViewer

__all__ = ["StreamViewer"]
