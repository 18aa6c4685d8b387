"""Outputs written atomically, together, and only after the run succeeded.

A command declares its outputs up front (``OutputSet.file`` for a file, ``.directory``
for a directory of files) and writes them to the staging paths it gets back. The staging
area is a hidden sibling (``.NAME.partial-XXXX``) in the nearest existing directory above
the target, so the final moves are renames on one file system. When the run ends
without an exception, :meth:`OutputSet.commit` checks every destination (its kind, and
that its directory can be written) and then moves every file into place (``os.replace``,
directories created as needed). When a move still fails (a report directory the system
refuses to write, a full disk), the moves already made are undone: each replaced file is
put back from a hard link taken beside it, each new file and directory removed. When the
run raises, the staging area is removed and the targets are as they were.

Refused before anything runs: an output that is one of the run's inputs (same file, by
device and inode, through any symlink or relative path), a file output whose path is a
directory (or the reverse), a place where no directory can be made or written. A
``kill -9`` mid-run leaves a ``.NAME.partial-XXXX`` directory beside the target (mid-commit,
also ``.NAME.partial-old-XXXX`` links to replaced files), never a half-written target.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

PARTIAL = ".partial-"


@dataclass(frozen=True)
class _Staged:
    target: Path  # where it goes (absolute, lexically normal)
    shown: Path  # as the user gave it (messages, final())
    staged: Path  # where the run writes it
    root: Path  # the staging directory to remove afterwards
    is_dir: bool
    option: str


def _identity(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


@dataclass(frozen=True)
class _Moved:
    """One move of a commit, as much as undoing it needs."""

    target: Path
    backup: Path | None  # a hard link to the file the move replaced
    created: tuple[Path, ...]  # directories the move made, outermost first


def _backup(target: Path) -> Path | None:
    """A hidden link (a copy where links are refused) to the file at ``target``, beside it."""
    if not (target.exists() or target.is_symlink()):
        return None
    backup = target.with_name(f".{target.name}{PARTIAL}old-{os.urandom(4).hex()}")
    try:
        os.link(target, backup, follow_symlinks=False)
    except OSError:
        shutil.copy2(target, backup, follow_symlinks=False)
    return backup


def _move(src: Path, dst: Path) -> _Moved:
    """``os.replace(src, dst)``, making ``dst``'s missing directories and keeping a backup
    of the file it replaces."""
    created = [d for d in [dst.parent, *dst.parent.parents] if not d.exists()][::-1]
    dst.parent.mkdir(parents=True, exist_ok=True)
    done = _Moved(dst, None, tuple(created))
    try:
        done = _Moved(dst, _backup(dst), tuple(created))
        os.replace(src, dst)
    except OSError:
        _undo([done], restore=False)
        raise
    return done


def _undo(moves: list[_Moved], *, restore: bool = True) -> None:
    """Put back what ``moves`` replaced, remove what they created (best effort: the error
    that stopped the commit is the one reported)."""
    for m in reversed(moves):
        with contextlib.suppress(OSError):
            if m.backup is not None:
                if restore:
                    os.replace(m.backup, m.target)
                else:
                    m.backup.unlink()
            elif restore:
                m.target.unlink(missing_ok=True)
        for d in reversed(m.created):
            with contextlib.suppress(OSError):
                d.rmdir()


def _existing_ancestor(path: Path) -> Path:
    for parent in path.parents:
        if parent.exists():
            return parent
    return Path("/")


class OutputSet:
    """The outputs of one run. ``inputs``: every file the run reads (``None`` skipped);
    ``error``: the package's error class (called with a one-line message)."""

    def __init__(
        self,
        inputs: Iterable[str | Path | None] = (),
        *,
        error: Callable[[str], Exception] = ValueError,
    ) -> None:
        self._error = error
        self._inputs: dict[tuple[int, int], str] = {}
        for p in inputs:
            if p is None or str(p) in ("", "-"):
                continue
            ident = _identity(Path(p))
            if ident is not None:
                self._inputs[ident] = str(p)
        self._staged: list[_Staged] = []
        self._done = False

    # -- declaring -------------------------------------------------------------------
    def file(self, target: str | Path, option: str = "--out") -> Path:
        """The path to write the file ``target`` to."""
        return self._stage(Path(target), option, is_dir=False)

    def directory(self, target: str | Path, option: str = "--out") -> Path:
        """The directory to write the files meant for directory ``target`` into."""
        return self._stage(Path(target), option, is_dir=True)

    def final(self, staged: str | Path) -> Path:
        """Where a path under a staging path will be once committed (for messages and
        documents that name their own files)."""
        p = Path(staged)
        for s in self._staged:
            if p == s.staged or s.staged in p.parents:
                return s.shown / p.relative_to(s.staged)
        return p

    def _refuse_input(self, target: Path, option: str, shown: Path | None = None) -> None:
        ident = _identity(target)
        if ident is not None and ident in self._inputs:
            raise self._error(
                f"{option} {shown or target}: is an input of this run ({self._inputs[ident]}); "
                "choose another output path"
            )

    def _stage(self, target: Path, option: str, *, is_dir: bool) -> Path:
        # lexically normal and absolute: 'sub/../data.csv' is data.csv even when 'sub'
        # does not exist (the file system would refuse to resolve it, and then create it)
        shown, target = target, Path(os.path.abspath(target))
        self._refuse_input(target, option, shown)
        if target.exists() or target.is_symlink():
            if is_dir and not target.is_dir():
                raise self._error(f"{option} {shown}: exists and is not a directory")
            if not is_dir and target.is_dir():
                raise self._error(f"{option} {shown}: is a directory, expected a file path")
        for s in self._staged:
            if s.target == target:
                raise self._error(f"{option} {shown}: also given as {s.option}")
        anchor = _existing_ancestor(target)
        if not anchor.is_dir():
            raise self._error(f"{option} {shown}: {anchor} is not a directory")
        name = target.name or "out"
        try:
            root = Path(tempfile.mkdtemp(prefix=f".{name}{PARTIAL}", dir=anchor))
        except OSError as exc:
            raise self._error(
                f"{option} {shown}: cannot write in {anchor}: {exc.strerror or exc}"
            ) from None
        staged = root / target.relative_to(anchor)
        try:
            (staged if is_dir else staged.parent).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            shutil.rmtree(root, ignore_errors=True)
            raise self._error(f"{option} {shown}: cannot stage: {exc.strerror or exc}") from None
        self._staged.append(_Staged(target, shown, staged, root, is_dir, option))
        return staged

    # -- ending ----------------------------------------------------------------------
    def _moves(self) -> list[tuple[Path, Path, str]]:
        moves: list[tuple[Path, Path, str]] = []
        for s in self._staged:
            if not s.is_dir:
                if s.staged.exists():
                    moves.append((s.staged, s.target, s.option))
                continue
            for dirpath, _dirs, files in os.walk(s.staged):
                for f in sorted(files):
                    src = Path(dirpath) / f
                    moves.append((src, s.target / src.relative_to(s.staged), s.option))
        return moves

    def commit(self) -> list[Path]:
        """Move every staged file into place (all destinations checked first; a move that
        fails undoes the ones before it); the final paths, in order."""
        if self._done:
            return []
        moves = self._moves()
        for _src, dst, option in moves:
            self._refuse_input(dst, option)
            if dst.is_dir() and not dst.is_symlink():
                raise self._error(f"{option}: {dst} is a directory, cannot write a file there")
        for anchor, option in {self._writable_anchor(dst): o for _s, dst, o in moves}.items():
            if not os.access(anchor, os.W_OK | os.X_OK):
                raise self._error(f"{option} {anchor}: cannot write: permission denied")
        done: list[_Moved] = []
        for src, dst, option in moves:
            try:
                done.append(_move(src, dst))
            except OSError as exc:
                _undo(done)
                raise self._error(f"{option} {dst}: cannot write: {exc.strerror or exc}") from None
        for m in done:
            if m.backup is not None:
                m.backup.unlink(missing_ok=True)
        self.discard()
        return [m.target for m in done]

    def _writable_anchor(self, dst: Path) -> Path:
        """The directory a move to ``dst`` writes in: its parent, or the nearest existing
        directory above it (where the missing ones are made)."""
        parent = dst.parent
        return parent if parent.exists() else _existing_ancestor(parent)

    def discard(self) -> None:
        """Remove the staging areas (the targets are untouched)."""
        self._done = True
        for s in self._staged:
            shutil.rmtree(s.root, ignore_errors=True)

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            try:
                self.commit()
            finally:
                self.discard()
        else:
            self.discard()
