"""The edges: where users, files and the packages meet.

Every command line of the project (``daq``, ``twin``, ``sim-cell`` and the ``python -m``
generators) goes through these three pieces, so bad input costs the same everywhere:

* :mod:`edges.command`: the error boundary. A user's mistake is one line on stderr and
  exit 2; a bug is one line, exit 70 and a pointer to ``--debug``; never a traceback
  unless asked.
* :mod:`edges.outputs`: :class:`OutputSet`, every output of a run staged beside its target
  and moved into place together only after the run succeeded; an output that is an input
  is refused before anything runs.
* :mod:`edges.inputs`: bounded reading. A file larger than a stated limit, or one that
  never ends, is refused cleanly.

This package imports nothing from the project: every other package may import it.
"""

from edges.command import EXIT_BUG, EXIT_USER, run_command
from edges.inputs import MAX_TEXT_BYTES, read_input_bytes
from edges.outputs import OutputSet

__all__ = [
    "EXIT_BUG",
    "EXIT_USER",
    "MAX_TEXT_BYTES",
    "OutputSet",
    "read_input_bytes",
    "run_command",
]
