"""What every bad-input test asserts about a refusal, in one place (the ``daq``, ``sim-cell``
and ``twin`` bad-input modules used to write it three times).

A refused input: exit status 2, exactly one line on stderr naming the file and
row/column/key/option (the key words given), no traceback, and every file under the
working directory byte for byte as before (no output created, no staging left).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
from collections import Counter
from pathlib import Path

import pytest

#: Set to print every refusal's message (``SHOW_MESSAGES=1 pytest -s ...``).
SHOW_MESSAGES = "SHOW_MESSAGES"
#: Variables a test's environment must not inherit (they change limits and endpoints).
CLEARED_PREFIXES = ("DAQ_",)
CLEARED = ("GRATING_TWIN_MAX_INPUT_MB",)


def refuse_moves_into(monkeypatch: pytest.MonkeyPatch, directory: Path) -> None:
    """The system refusing every file moved into ``directory`` (what a read-only report
    directory does to a user who is not root, and tests run as root), every other move
    done as usual."""
    real = os.replace

    def replace(src: str | Path, dst: str | Path) -> None:
        if os.path.abspath(dst).startswith(os.path.abspath(directory) + os.sep):
            raise PermissionError(13, "Permission denied", str(dst))
        real(src, dst)

    monkeypatch.setattr(os, "replace", replace)


def snapshot(root: Path) -> dict[str, str]:
    """Every entry under ``root`` (hidden ones too): files by content hash, directories,
    symlinks by target, other special files (named pipes: never read) by kind."""
    out: dict[str, str] = {}
    for dirpath, dirs, files in os.walk(root):
        for d in dirs:
            p = Path(dirpath) / d
            out[str(p.relative_to(root))] = "link:" + os.readlink(p) if p.is_symlink() else "dir"
        for f in files:
            p = Path(dirpath) / f
            rel = str(p.relative_to(root))
            if p.is_symlink():
                out[rel] = "link:" + os.readlink(p)
            elif not p.is_file():
                out[rel] = "special"
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def changed(before: dict[str, str], after: dict[str, str]) -> set[str]:
    """The entries that differ between two snapshots."""
    return {k for k in set(before) | set(after) if before.get(k) != after.get(k)}


def run(
    argv: list[str], cwd: Path, env: dict[str, str] | None = None, *, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    """``argv`` as a process in ``cwd``, the test's own environment cleared, plus ``env``."""
    environ = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(CLEARED_PREFIXES) and k not in CLEARED
    }
    environ.update(env or {})
    return subprocess.run(
        argv, cwd=cwd, env=environ, capture_output=True, text=True, timeout=timeout
    )


def assert_refusal(
    status: int,
    stderr: str,
    words: list[str] | tuple[str, ...],
    before: dict[str, str],
    after: dict[str, str],
    *,
    ignore_case: bool = False,
) -> str:
    """The refusal's assertions on an outcome (from a process or an in-process ``main``);
    the stderr line."""
    err = stderr.strip()
    assert status == 2, (status, err)
    assert "Traceback" not in err, err
    assert len(err.splitlines()) == 1, err
    seen = err.lower() if ignore_case else err
    missing = [w for w in words if (w.lower() if ignore_case else w) not in seen]
    assert not missing, (missing, err)
    assert after == before, (changed(before, after), err)
    return err


def refused(
    work: Path,
    argv: list[str],
    words: list[str] | tuple[str, ...],
    *,
    env: dict[str, str] | None = None,
    timeout: float = 60,
    tally: Counter[str] | None = None,
    ignore_case: bool = False,
    quiet_stdout: bool = False,
) -> subprocess.CompletedProcess[str]:
    """Run ``argv`` in ``work`` and assert the clean refusal (module docstring);
    ``quiet_stdout``: nothing on stdout either. Counts the outcome in ``tally``."""
    tally = Counter() if tally is None else tally
    before = snapshot(work)
    tally["tried"] += 1
    try:
        proc = run(argv, work, env, timeout=timeout)
    except subprocess.TimeoutExpired:
        tally["hang"] += 1
        raise
    after = snapshot(work)
    err = proc.stderr
    if os.environ.get(SHOW_MESSAGES):
        print(f"\n{' '.join(argv[1:])}\n    -> {proc.returncode} {err.strip()}")
    seen = err.lower() if ignore_case else err
    clear = (
        proc.returncode == 2
        and len(err.strip().splitlines()) == 1
        and "Traceback" not in err
        and all((w.lower() if ignore_case else w) in seen for w in words)
        and before == after
        and (proc.stdout == "" or not quiet_stdout)
    )
    tally["traceback"] += "Traceback" in err
    tally["silent"] += proc.returncode == 0
    tally["changed"] += before != after
    tally["clear"] += clear
    assert_refusal(proc.returncode, err, words, before, after, ignore_case=ignore_case)
    if quiet_stdout:
        assert proc.stdout == "", proc.stdout
    return proc
