"""The error boundary every command line runs its body in.

A user's mistake (the package's own error class, or the system refusing a file: missing,
unreadable, unwritable, disk full) is one line on stderr naming what was wrong, exit 2.
Anything else is a bug: one line with the exception, a pointer to ``--debug``, exit 70
(``EX_SOFTWARE``); ``--debug`` prints the traceback as well. A reader that closes the
pipe (``daq info F | head``) ends the command quietly; Ctrl-C exits 130. A traceback never
reaches a user who did not ask for it.
"""

from __future__ import annotations

import os
import sys
import traceback
from collections.abc import Callable, Sequence

EXIT_USER = 2
EXIT_BUG = 70  # sysexits.h EX_SOFTWARE
EXIT_INTERRUPTED = 130
EXIT_PIPE = 141  # 128 + SIGPIPE, what a C tool killed by the closed pipe reports

DEBUG_FLAG = "--debug"


def take_debug_flag(argv: Sequence[str]) -> tuple[list[str], bool]:
    """``argv`` without ``--debug`` (anywhere on the line), and whether it was there."""
    rest = [a for a in argv if a != DEBUG_FLAG]
    return rest, len(rest) != len(argv)


def progress(prog: str, quiet: bool = False) -> Callable[[str], None]:
    """A ``say(text)`` that prints ``PROG: text`` on stderr (nothing when ``quiet``)."""

    def say(text: str) -> None:
        if not quiet:
            print(f"{prog}: {text}", file=sys.stderr, flush=True)

    return say


def one_line(text: str) -> str:
    """A message on one line (a multi-line exception text joined with ' | ')."""
    parts = [p.strip() for p in str(text).splitlines() if p.strip()]
    return " | ".join(parts) if parts else ""


def os_error_text(exc: OSError) -> str:
    """``path: reason`` for an OSError raised on a file (``reason`` alone otherwise)."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    names = [n for n in (exc.filename, exc.filename2) if n is not None]
    if names:
        return f"{' -> '.join(os.fsdecode(n) for n in names)}: {reason}"
    return reason


def _quiet_stdout() -> None:
    # the reader went away: point stdout at /dev/null so the interpreter's final flush
    # does not raise again (Python docs, "Note on SIGPIPE")
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def run_command(
    prog: str,
    body: Callable[[], int],
    *,
    user_errors: tuple[type[BaseException], ...],
    debug: bool = False,
) -> int:
    """Run ``body`` (returns the exit status) behind the boundary; ``prog`` starts every
    message (``"twin predict"``). ``user_errors``: the package's own error classes."""
    try:
        return int(body())
    except BrokenPipeError:
        _quiet_stdout()
        return EXIT_PIPE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except user_errors as exc:
        if debug:
            traceback.print_exc()
        print(f"{prog}: error: {one_line(str(exc))}", file=sys.stderr)
        return EXIT_USER
    except OSError as exc:
        if debug:
            traceback.print_exc()
        print(f"{prog}: error: {one_line(os_error_text(exc))}", file=sys.stderr)
        return EXIT_USER
    except MemoryError:
        print(f"{prog}: error: out of memory (is an input far larger than meant?)", file=sys.stderr)
        return EXIT_USER
    except Exception as exc:
        if debug:
            traceback.print_exc()
        print(
            f"{prog}: internal error: {type(exc).__name__}: {one_line(str(exc))} "
            f"(a bug; run again with {DEBUG_FLAG} for the traceback and report it)",
            file=sys.stderr,
        )
        return EXIT_BUG
