"""The edges every command goes through: the error boundary, staged outputs, bounded
reads (unit tests; the commands' own bad-input modules run them as processes)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from edges import inputs
from edges.command import EXIT_BUG, EXIT_PIPE, EXIT_USER, run_command, take_debug_flag
from edges.inputs import LIMIT_VARIABLE, read_input_bytes
from edges.outputs import OutputSet
from tests.bad_input import refuse_moves_into


class UserError(Exception):
    pass


def listing(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


# -- OutputSet --------------------------------------------------------------------------------
def test_outputs_appear_together_only_after_success(tmp_path):
    (tmp_path / "old.txt").write_text("old")
    with OutputSet(error=UserError) as outputs:
        f = outputs.file(tmp_path / "a" / "b" / "model.toml")
        d = outputs.directory(tmp_path / "report")
        f.write_text("model")
        (d / "sub").mkdir()
        (d / "sub" / "x.png").write_bytes(b"png")
        assert not (tmp_path / "a").exists() and not (tmp_path / "report").exists()
        assert outputs.final(d / "sub" / "x.png") == tmp_path / "report" / "sub" / "x.png"
    assert (tmp_path / "a/b/model.toml").read_text() == "model"
    assert (tmp_path / "report/sub/x.png").read_bytes() == b"png"
    assert ".partial-" not in " ".join(listing(tmp_path))


def test_a_failed_run_leaves_everything_as_it_was(tmp_path):
    (tmp_path / "model.toml").write_text("earlier")
    before = listing(tmp_path)
    with pytest.raises(RuntimeError), OutputSet(error=UserError) as outputs:
        outputs.file(tmp_path / "model.toml").write_text("half")
        outputs.directory(tmp_path / "new" / "report")
        raise RuntimeError("the fit failed")
    assert listing(tmp_path) == before
    assert (tmp_path / "model.toml").read_text() == "earlier"


def test_a_move_that_fails_at_commit_undoes_the_moves_before_it(tmp_path, monkeypatch):
    (tmp_path / "model.toml").write_text("earlier")
    (tmp_path / "report").mkdir()
    before = listing(tmp_path)
    refuse_moves_into(monkeypatch, tmp_path / "report")
    failed = pytest.raises(UserError, match=r"--report .*report\.md: cannot write")
    with failed, OutputSet(error=UserError) as outputs:
        outputs.file(tmp_path / "model.toml").write_text("new")
        outputs.file(tmp_path / "fresh" / "b.csv").write_text("new")
        outputs.directory(tmp_path / "report", "--report").joinpath("report.md").write_text("x")
    assert listing(tmp_path) == before  # no fresh/, no staging, no backup left
    assert (tmp_path / "model.toml").read_text() == "earlier"


def test_a_directory_that_cannot_be_written_is_refused_before_any_move(tmp_path, monkeypatch):
    (tmp_path / "report").mkdir()
    real = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode: Path(p) != tmp_path / "report" and real(p, mode)
    )
    refused = pytest.raises(UserError, match=r"--report .*report: cannot write: permission")
    with refused, OutputSet(error=UserError) as outputs:
        outputs.file(tmp_path / "model.toml").write_text("new")
        outputs.directory(tmp_path / "report", "--report").joinpath("r.md").write_text("x")
    assert listing(tmp_path) == ["report"]


@pytest.mark.parametrize("spelling", ["data.csv", "./x/../data.csv", "link.csv", "DIR"])
def test_an_output_that_is_an_input_is_refused_however_it_is_spelled(tmp_path, spelling):
    (tmp_path / "data.csv").write_text("a,b\n")
    os.symlink("data.csv", tmp_path / "link.csv")
    target = str(tmp_path / "data.csv") if spelling == "DIR" else str(tmp_path / spelling)
    outputs = OutputSet([tmp_path / "data.csv"], error=UserError)
    with pytest.raises(UserError, match="is an input"):
        outputs.file(target)
    assert listing(tmp_path) == ["data.csv", "link.csv"]


def test_a_directory_output_cannot_overwrite_an_input_inside_it(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "campaign.csv").write_text("input")
    inputs = [tmp_path / "out" / "campaign.csv"]
    with pytest.raises(UserError, match="is an input"), OutputSet(inputs, error=UserError) as out:
        d = out.directory(tmp_path / "out")
        (d / "campaign.csv").write_text("overwritten")
        (d / "other.csv").write_text("new")
    assert (tmp_path / "out" / "campaign.csv").read_text() == "input"
    assert listing(tmp_path) == ["out", "out/campaign.csv"]


def test_kinds_and_places_that_cannot_be_written_are_refused_up_front(tmp_path):
    (tmp_path / "file").write_text("x")
    (tmp_path / "dir").mkdir()
    outputs = OutputSet(error=UserError)
    with pytest.raises(UserError, match="not a directory"):
        outputs.file(tmp_path / "file" / "x.toml")
    with pytest.raises(UserError, match="is a directory"):
        outputs.file(tmp_path / "dir")
    with pytest.raises(UserError, match="not a directory"):
        outputs.directory(tmp_path / "file")
    outputs.file(tmp_path / "same")
    with pytest.raises(UserError, match="also given"):
        outputs.directory(tmp_path / "same")
    outputs.discard()
    assert listing(tmp_path) == ["dir", "file"]


# -- the boundary -----------------------------------------------------------------------------
def _body(exc):
    def body():
        raise exc

    return body


def test_user_errors_and_os_errors_are_one_line_exit_2(capsys):
    assert run_command("tool x", _body(UserError("a.csv: line 3\ncolumn 'q'")),
                       user_errors=(UserError,)) == EXIT_USER  # fmt: skip
    err = capsys.readouterr().err
    assert err == "tool x: error: a.csv: line 3 | column 'q'\n"
    missing = FileNotFoundError(2, "No such file or directory", "nope.csv")
    assert run_command("tool", _body(missing), user_errors=(UserError,)) == EXIT_USER
    assert capsys.readouterr().err == "tool: error: nope.csv: No such file or directory\n"


def test_a_bug_is_one_line_pointing_at_debug_which_shows_the_traceback(capsys):
    assert run_command("tool", _body(KeyError("k")), user_errors=(UserError,)) == EXIT_BUG
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "KeyError" in err and "--debug" in err
    assert "Traceback" not in err
    run_command("tool", _body(KeyError("k")), user_errors=(UserError,), debug=True)
    assert "Traceback" in capsys.readouterr().err
    assert take_debug_flag(["a", "--debug", "b"]) == (["a", "b"], True)
    assert take_debug_flag(["a"]) == (["a"], False)


def test_a_closed_pipe_ends_quietly():
    code = (
        "import sys\n"
        "from edges.command import run_command\n"
        "def body():\n"
        "    for i in range(10**6):\n"
        "        print('line', i)\n"
        "    return 0\n"
        "sys.exit(run_command('tool', body, user_errors=()))\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.readline()
    proc.stdout.close()  # the reader goes away, as `| head` does
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == EXIT_PIPE
    assert err == ""


# -- bounded reads ----------------------------------------------------------------------------
def test_reads_are_bounded(tmp_path, monkeypatch):
    (tmp_path / "f.csv").write_bytes(b"x" * 5000)
    assert read_input_bytes(tmp_path / "f.csv", limit=5000) == b"x" * 5000
    with pytest.raises(UserError, match="larger than the input limit"):
        read_input_bytes(tmp_path / "f.csv", limit=4999, error=UserError)
    with pytest.raises(UserError, match="device"):
        read_input_bytes("/dev/zero", error=UserError)
    with pytest.raises(UserError, match="directory"):
        read_input_bytes(tmp_path, error=UserError)
    with pytest.raises(UserError, match="cannot read"):
        read_input_bytes(tmp_path / "none.csv", error=UserError)
    monkeypatch.setenv(LIMIT_VARIABLE, "0.001")
    with pytest.raises(UserError, match=LIMIT_VARIABLE):
        read_input_bytes(tmp_path / "f.csv", error=UserError)


def test_a_pipe_that_does_not_end_is_cut_at_the_limit(tmp_path):
    fifo = tmp_path / "endless"
    os.mkfifo(fifo)
    stop = threading.Event()

    def writer():
        try:
            with open(fifo, "wb") as fh:
                for _ in range(10_000):  # bounded: 10 MB at most
                    if stop.is_set():
                        return
                    fh.write(b"y" * 1000)
        except BrokenPipeError:
            return

    t = threading.Thread(target=writer, daemon=True)
    t.start()
    with pytest.raises(UserError, match="more than the input limit"):
        read_input_bytes(fifo, limit=100_000, error=UserError)
    stop.set()
    t.join(timeout=10)


def test_a_pipe_without_a_writer_is_refused_after_a_bounded_wait(tmp_path, monkeypatch):
    fifo = tmp_path / "nobody"
    os.mkfifo(fifo)
    monkeypatch.setattr(inputs, "FIFO_WAIT_S", 0.2)
    with pytest.raises(UserError, match="nobody wrote"):
        read_input_bytes(fifo, error=UserError)
